"""`piezo-stage emulate scanner`: one amplifier and one sensor per axis around the coupled stage
of a stage file (the xy scanner: y's sensor sees 2 % of x's motion), its log, its refusals."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_hardware_emulate import run_in_thread

from piezo_stage.cli import main
from piezo_stage.hardware.emulators.voltage_log import read_voltage_log
from piezo_stage.hardware.gcs import GCSConnection
from piezo_stage.hardware.mdt69x import MDTConnection
from piezo_stage.hardware.optoncdt import SampleBlock, Status
from piezo_stage.hardware.sensor import SensorConfig, SensorReader
from piezo_stage.hardware.transport import make_transport
from piezo_stage.model.stage import CoupledStage
from piezo_stage.model.stage_file import load_stage

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
XY = ROOT / "config" / "xy_scanner.yaml"
MR = 2e-3  # with the ILD1750's 18-bit words: 7.6 nm steps, 2 % of 10 um is 26 of them
LSB = MR / 262074


def read_at_least(reader: SensorReader, n: int) -> SampleBlock:
    """The next n samples or more (a loaded host delivers them late, never fewer)."""
    blocks, deadline = [], time.monotonic() + 5.0
    while sum(len(b) for b in blocks) < n and time.monotonic() < deadline:
        blocks.append(reader.read(0.1))
    return SampleBlock.concat(blocks)


def settled(readers: dict[str, SensorReader]) -> dict[str, float]:
    """Each sensor's median over 50 samples, after 400 (0.4 s) to let the stage settle."""
    for reader in readers.values():
        read_at_least(reader, 400)
    out = {}
    for axis, reader in readers.items():
        block = read_at_least(reader, 50)
        assert np.all(block.status == Status.OK), axis
        out[axis] = float(np.median(block.displacement))
    return out


def expected_motion(volts: float) -> tuple[float, float]:
    """The stage file's own coupled stage, x held at ``volts`` for 1 s: (x's, y's) reading."""
    stage = CoupledStage(load_stage(XY))
    for _ in range(1000):
        sample = stage.step([volts, 0.0], 1e-3)
    return float(sample.readings[0]), float(sample.readings[1])


def test_sva_on_x_moves_x_and_y_by_the_coupling(capsys, tmp_path):
    log = tmp_path / "applied.csv"
    argv = [
        "emulate",
        "scanner",
        "--stage",
        str(XY),
        "--amp-tcp",
        "0",
        "--family",
        "ild1750",
        "--measuring-range",
        str(MR),
        "--log",
        str(log),
        "--duration",
        "10",
        "--amp-bandwidth",
        "0",  # ideal: each 1 ms step reaches the stage, as expected_motion steps it
    ]
    thread, ends, result = run_in_thread(argv, capsys, 4)
    assert set(ends) == {"gcs", "optoncdt x", "optoncdt y", "scanner"}
    assert ends["scanner"] == "2 axes (x, y) at 1000 Hz"
    config = SensorConfig("ild1750", MR)
    readers = {axis: SensorReader.from_url(ends[f"optoncdt {axis}"], config) for axis in "xy"}
    for reader in readers.values():
        reader.connect()
    with make_transport(ends["gcs"]) as transport:
        conn = GCSConnection(transport, timeout=1.0)
        assert conn.query("SAI?") == ["1", "2"]  # the stage file's channels, nothing else
        conn.command("SVO 1 0 2 0")
        rest = settled(readers)
        conn.command("SVA 1 100")
        moved = settled(readers)
        conn.command("SVA 1 0")
    for reader in readers.values():
        reader.close()
    thread.join(15)
    assert result["rc"] == 0
    x_expected, y_expected = expected_motion(100.0)
    dx, dy = moved["x"] - rest["x"], moved["y"] - rest["y"]
    assert rest["x"] == pytest.approx(MR / 2, abs=3 * LSB)  # standoff MR/2 at rest
    assert x_expected > 5e-6 and dx == pytest.approx(x_expected, rel=0.02, abs=3 * LSB)
    assert y_expected == pytest.approx(0.02 * x_expected, rel=1e-9)
    assert dy == pytest.approx(0.02 * dx, abs=3 * LSB)  # y's sensor: 2 % of x's motion
    rows = read_voltage_log(log)
    assert {axis: [v for _, v in r] for axis, r in rows.items()} == {"1": [100.0, 0.0]}
    assert 0.0 < rows["1"][0][0] < rows["1"][1][0] < 10.0


def _bad_stage(tmp_path: Path) -> Path:
    data = yaml.safe_load(XY.read_text())
    data["coupling"] = [[1.0, 0.01], [0.02, 2.0]]
    for axis in data["axes"].values():
        axis["model_file"] = str(ROOT / "config" / axis["model_file"])
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    "extra, message",
    [
        ([], "coupling: the diagonal must be ones"),
        (["--stage", "no_such_stage.yaml"], "not found"),
        (["--stage", str(XY), "--amplifier", "mdt69x"], "are not MDT693B channels"),
        (["--stage", str(XY), "--sensor-link", "/tmp/sensor"], "needs {axis}"),
    ],
)
def test_a_bad_stage_or_option_is_one_line_and_exit_2(extra, message, capsys, tmp_path):
    stage = ["--stage", str(_bad_stage(tmp_path))] if not extra else []
    rc = main(["emulate", "scanner", *stage, *extra, "--duration", "0.1"])
    assert rc == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert captured.out == ""


def test_mdt693b_scanner_links_each_sensor_and_stops_on_sigint(tmp_path):
    """An xz stage on the MDT693B's channels x and z, each sensor at its linked pty; SIGINT
    stops it (exit 0) and removes the links."""
    stage = tmp_path / "xz.yaml"
    stage.write_text(
        yaml.safe_dump(
            {
                "name": "xz",
                "axes": {
                    "x": {"model_file": "ch11_rig.yaml", "channel": "x"},
                    "z": {"model_file": "ch11_rig.yaml", "channel": "z"},
                },
                "coupling": [[1.0, 0.0], [0.05, 1.0]],
            }
        )
    )
    pattern = str(tmp_path / "sensor_{axis}")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    argv = ["emulate", "scanner", "--stage", str(stage), "--amplifier", "mdt69x"]
    argv += ["--sensor-link", pattern, "--family", "ild1750", "--measuring-range", str(MR)]
    proc = subprocess.Popen(
        [sys.executable, "-m", "piezo_stage.cli", *argv],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        cwd=tmp_path,
    )
    links = {axis: tmp_path / f"sensor_{axis}" for axis in "xz"}
    try:
        lines = [proc.stdout.readline().strip() for _ in range(4)]
        ends = dict(line.split(": ", 1) for line in lines)
        assert lines[-1] == "scanner: 2 axes (x, z) at 1000 Hz"
        assert {ends[f"optoncdt {a}"] for a in "xz"} == {str(p) for p in links.values()}
        assert all(p.is_symlink() for p in links.values())
        config = SensorConfig("ild1750", MR)
        readers = {a: SensorReader.from_url(str(p), config) for a, p in links.items()}
        for reader in readers.values():
            reader.connect()
        with make_transport(ends["mdt69x"]) as transport:
            conn = MDTConnection(transport, timeout=1.0)
            rest = settled(readers)
            conn.exchange("zvoltage=100")
            moved = settled(readers)
        for reader in readers.values():
            reader.close()
        dx, dz = moved["x"] - rest["x"], moved["z"] - rest["z"]
        assert dz > 5e-6 and abs(dx) <= 3 * LSB  # x's sensor sees none of z (C[0][1] = 0)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not any(os.path.lexists(p) for p in links.values())


def test_an_amplifier_bandwidth_filters_each_channel_as_the_rig_does():
    """Through a 1 kHz low-pass a 100 V step on x moves the stage as the single-axis rig's
    low-pass moves x's model alone (y at 0 V adds nothing to x), y's sensor seeing 2 % of it;
    the ideal amplifier's 1 ms step rings x's resonance and lands elsewhere."""
    from piezo_stage.hardware.emulators.rig import OneAxis
    from piezo_stage.hardware.emulators.scanner import ScannerCoupling

    k = np.arange(400)

    def scanner(stage, bandwidth: float) -> np.ndarray:
        coupling = ScannerCoupling(
            stage, ["1", "2"][: len(stage.axes)], 1000.0, 0.0, bandwidth_hz=bandwidth
        )
        coupling.grid_offset(0.0)
        coupling.on_axis_voltage("1", 100.0, at=1e-4)  # x steps just after sample 0
        return np.column_stack([coupling.readings_at(i, k) for i in range(len(stage.axes))])

    alone = scanner(OneAxis(CoupledStage(load_stage(XY)).axes[0]), 1000.0)[:, 0]
    filtered = scanner(CoupledStage(load_stage(XY)), 1000.0)
    ideal = scanner(CoupledStage(load_stage(XY)), 0.0)
    assert filtered[:, 0] == pytest.approx(alone, rel=1e-9, abs=1e-15)
    assert filtered[-1, 1] == pytest.approx(0.02 * filtered[-1, 0], rel=0.05)
    assert abs(ideal[-1, 0] / filtered[-1, 0] - 1.0) > 0.05
