"""`piezo-stage experiment raster --view`: the run watched live. A short raster on the simulated
scanner (in the core, and through its nodes in lockstep) with its view on a free port: the
line it prints says where (the URL, the ROS domain and namespace); a Foxglove client connected
there sees the scan image build up (a line not yet scanned, then none) and, once the scan is
done, the experiment's own image: the last frame of the samples in its bag, placed as the
experiment's figures place them."""

from __future__ import annotations

import re
import subprocess
import threading
import time

import numpy as np
import pytest

from piezo_stage.bag.reader import read_loop_samples
from piezo_stage.control.scan import RasterScan
from piezo_stage.control.scan_image import load_sample
from piezo_stage.experiments.raster_graph import decode
from piezo_stage.nodes.scan_view import UNFILLED

from foxglove_client import FoxgloveClient, decoder

pytestmark = [pytest.mark.ros, pytest.mark.slow]

#: a short scan at a cheap loop rate: two frames of ~3.6 s, fed to the view at the scan's pace
LINES, PIXELS, LINE_RATE, RATE = 16, 32, 5.0, 1000.0
SCAN = RasterScan(LINES, PIXELS, LINE_RATE, (20e-6, 10e-6), (20e-6, 10e-6))
#: the view's grey levels span the sample's height range (the grating's 100 nm) in 255 steps,
#: rounded down: two steps of it
GREY_STEPS = 2


#: the line the experiment prints: where to look
WHERE = re.compile(r"view: .*(ws://127\.0\.0\.1:\d+).*ROS_DOMAIN_ID=\d+, namespace /raster")


def _read_lines(stream, lines: list[str], seen: threading.Event) -> None:
    """Every line of ``stream`` into ``lines``; ``seen`` set at the view's line (or the end)."""
    for line in iter(stream.readline, ""):
        lines.append(line.rstrip("\n"))
        if WHERE.search(line):
            seen.set()
    seen.set()


def _connect(url: str, timeout: float) -> FoxgloveClient:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return FoxgloveClient(url)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def _experiment_image(bag) -> tuple[np.ndarray, float, float]:
    """The last frame's image of the run in ``bag`` (heights [m]), and the sample's lowest
    height and height range (the view's black and its span to white)."""
    columns = tuple(read_loop_samples(bag, f"/raster/{axis}/loop_samples") for axis in "xy")
    run = decode(SCAN, columns, 0, None, origin=0)  # a simulated run's bag: time from 0
    image = run.image(load_sample("grating", SCAN))
    return image.image, float(image.ideal.min()), float(np.ptp(image.ideal))


@pytest.mark.parametrize("graph", ["core", "sim_scanner"])
def test_raster_with_view_serves_the_image_the_experiment_makes(graph, tmp_path):
    bag = tmp_path / "bag"
    argv = [
        "piezo-stage",
        "experiment",
        "raster",
        *("--graph", graph),
        *("--lines", str(LINES), "--pixels", str(PIXELS), "--line-rate", str(LINE_RATE)),
        *("--rate-hz", str(RATE), "--view-port", "0", "--bag", str(bag), "--json"),
    ]
    proc = subprocess.Popen(
        argv, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    said: list[str] = []
    seen = threading.Event()
    reader = threading.Thread(target=_read_lines, args=(proc.stderr, said, seen), daemon=True)
    reader.start()
    client = None
    try:
        assert seen.wait(300.0), "\n".join(said)  # (a fresh clone's numba cache compiles first)
        found = next((m for m in map(WHERE.search, said) if m), None)
        assert found is not None, "\n".join(said)
        client = _connect(found.group(1), 30.0)
        topic = "/raster/scan_image"
        assert client.wait(lambda: client.channel(topic) is not None, 30.0), client.channels
        channel = client.channel(topic)
        sub = client.subscribe(channel["id"])
        out, _ = proc.communicate(timeout=120.0)
    finally:
        if client is not None:
            client.close()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    reader.join(timeout=5.0)
    assert proc.returncode == 0, "\n".join(said)
    assert '"axes"' in out  # the summary, on stdout alone (--json)
    decode_image = decoder(channel)
    images = []
    for received in client.received(sub):
        msg = decode_image(received.payload)
        assert (msg.height, msg.width, msg.encoding) == (LINES, PIXELS, "mono8")
        # the message's first row is the image's top: the last line
        images.append(np.asarray(msg.data, np.uint8).reshape(LINES, PIXELS)[::-1])
    assert images, "\n".join(said)
    # it built up: a line not yet scanned (all grey) in an early image, none in the last
    assert any((im == UNFILLED).all(axis=1).any() for im in images[:-1]), len(images)
    assert not (images[-1] == UNFILLED).all(axis=1).any()
    want, low, span = _experiment_image(bag)
    assert np.isfinite(want).all()  # every pixel of the last frame was reached
    shown = low + images[-1] / 255.0 * span  # the view's grey levels as heights [m]
    worst = float(np.abs(shown - want).max())
    assert worst <= GREY_STEPS * span / 255.0, (worst, span)
