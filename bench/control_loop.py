#!/usr/bin/env python3
"""The rig's loop measured from outside: rig_closed_loop (three processes) beside rig_loop (one).

The devices are the project's emulators, each in a process of its own with the collector off
(as hardware, they never pause): an optoNCDT sensor on a pty (ILD1320 at 1 kHz, ILD2300-class
at 10 kHz) and a PI GCS amplifier on TCP. The sensor streams a
sawtooth of ``LEVELS`` distinct positions (one step of ``STEP`` per sample), the controller is a
proportional law around ``U_BIAS`` (mode pid, k0 = k2 = 0, so every applied voltage names the
sample it was computed from), and the amplifier logs when each ``SVA`` arrived (the kernel's
receive stamp). For every sample:

- latency: from the moment its frame was written to the pty to the arrival of the first voltage
  computed from it or from a later sample (a read that brings several samples is answered by
  the newest);
- unanswered: no such voltage within half a sawtooth period (``LEVELS`` / 2 samples);
- CPU per sample: user + system time of the graph's processes over the window / samples.

Runs, each with its processes started afresh: both forms at 1 kHz, at 1 kHz beside one busy
background process, and at 10 kHz; beside them ``minimal``, a one-thread Python loop (pty ->
parse -> proportional law -> TCP, no checks, no topics): the floor of this host.
``--soak SECONDS`` runs rig_loop alone at 1 kHz for that long (the 1-hour soak: RSS growth and
unanswered samples; outside CI). ``--designs`` runs rig_loop's alternatives instead: Python's
default 5 ms switch interval, the executor's thread draining the hand-off, and publishing every
message at once from the loop thread (no hand-off), beside the shipped design (the loop thread
drains the hand-off after a write every 20 samples' worth, 50 µs switch interval).
``--view`` runs rig_loop at 1 kHz without and with the live view (the live_view node and a
Foxglove WebSocket client watching displacement, voltage_command and controller_state): the
loop's figures side by side, the view's CPU (% of one core) and the messages the client got.

    python bench/control_loop.py [--seconds 10] [--forms rig_closed_loop,rig_loop,minimal]
                                 [--rates 1000,10000] [--param NODE.KEY:=VALUE] [--soak 3600]
                                 [--view]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from piezo_stage.hardware.emulators import EmulatorServer, GCSDeviceModel  # noqa: E402
from piezo_stage.hardware.emulators.optoncdt_device import OptoNCDTDeviceModel  # noqa: E402
from piezo_stage.hardware.optoncdt import frame_format  # noqa: E402
from piezo_stage.launch import Launcher  # noqa: E402
from piezo_stage.stopping import StopFlag  # noqa: E402

NS = "/bench_rig"
LEVELS = 500  # distinct positions of the sawtooth
STEP = 100e-9  # m per sample
BASE = 0.5e-3  # m from the start of the range: the sawtooth's bottom
MR = 2e-3  # measuring range [m]
K1 = 2e6  # V/m: 100 nm -> 0.2 V
U_BIAS = 200.0  # V
REFERENCE = BASE + 0.5 * LEVELS * STEP - 1e-3  # m, in the reader's frame (zero_offset 1 mm)
FAMILY = {1000.0: "ild1320", 10000.0: "ild2300"}
#: rig_loop's targets (docs/design.md §5) by (rate [Hz], busy): p99 [ms], CPU per sample [us];
#: at 1 kHz also against rig_closed_loop (x its p99, x its CPU); in every run none unanswered
TARGETS = {
    (1000.0, False): (0.3, 250.0),
    (1000.0, True): (0.5, None),
    (10000.0, False): (0.5, 70.0),
}
RATIO_TARGETS = (0.2, 0.25)
VIEW_TARGET = 10.0  # % of one core: the live view watching three 1 kHz topics


#: the floor of this host for a Python loop: pty -> parse -> proportional law -> TCP, one thread,
#: nothing else (no ERR? check, no limits beyond the clamp, no stamps, no topics)
MINIMAL = r"""
import os, select, socket, sys, tty
link, port = sys.argv[1], int(sys.argv[2])
mr, zero, k1, bias, ref = (float(a) for a in sys.argv[3:8])
fd = os.open(link, os.O_RDWR | os.O_NOCTTY)
tty.setraw(fd)
sock = socket.create_connection(("127.0.0.1", port))
sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
sock.sendall(b"SVO 1 0\n")
scale, offset, buf = 1.02 / 65520, 0.01, b""
while True:
    select.select([fd], [], [])
    buf += os.read(fd, 65536)
    u = None
    while len(buf) >= 3:
        lo, mid, hi = buf[0], buf[1], buf[2]
        if lo >> 6 == 0 and mid >> 6 == 1 and hi >> 6 == 2:
            x = ((((hi & 63) << 12) | ((mid & 63) << 6) | (lo & 63)) * scale - offset) * mr - zero
            u = min(max(bias - k1 * (x - ref), 0.0), 400.0)
            buf = buf[3:]
        else:
            buf = buf[1:]
    if u is not None:
        sock.sendall(b"SVA 1 %.6f\n" % u)
"""


class LoggingSensor(OptoNCDTDeviceModel):
    """The sensor model, keeping (write time, first sample, end sample) of each burst."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.log: list[tuple[float, int, int]] = []

    def stream(self, now: float) -> bytes:
        first = self.sent_samples
        data = super().stream(now)
        if self.sent_samples > first:
            self.log.append((now, first, self.sent_samples))
        return data


def sawtooth(rate: float):
    def source(t: np.ndarray) -> np.ndarray:
        k = np.rint(np.asarray(t) * rate).astype(np.int64)
        return BASE + (k % LEVELS) * STEP

    return source


@dataclass
class Figures:
    label: str
    samples: int = 0
    latencies: np.ndarray = field(default_factory=lambda: np.empty(0))
    unanswered: int = 0
    cpu_per_sample: float = float("nan")
    rss_growth: float = float("nan")  # bytes
    view: str = ""  # the live view's figures, when it watched
    view_cpu: float = float("nan")  # % of one core the live view took, when it watched

    def p99(self) -> float:
        return float(np.percentile(self.latencies, 99)) if self.latencies.size else float("nan")

    def line(self) -> str:
        if not self.latencies.size:
            return f"{self.label:<34} no sample answered ({self.samples} samples)"
        p50, p99 = np.percentile(self.latencies, [50, 99]) * 1e3
        text = (
            f"{self.label:<34} samples {self.samples:7d}  latency ms: p50 {p50:6.3f}  "
            f"p99 {p99:6.3f}  max {self.latencies.max() * 1e3:7.3f}  unanswered "
            f"{self.unanswered:5d}  CPU/sample {self.cpu_per_sample * 1e6:7.1f} us"
        )
        if np.isfinite(self.rss_growth):
            text += f"  RSS growth {self.rss_growth / 1e6:.2f} MB"
        return text + (f"\n{'':<34} {self.view}" if self.view else "")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


EXTRA: list[str] = []  # --param NODE.KEY:=VALUE given on the command line


def graph_params(form: str, rate: float, port: int, link: str) -> list[str]:
    params = [
        f"voltage_driver.url:=tcp://127.0.0.1:{port}",
        "voltage_driver.v_max:=400.0",
        "voltage_driver.slew_rate:=0.0",
        "voltage_driver.max_command_age:=0.0",
        "voltage_driver.command_timeout:=1.0",
        f"laser_reader.url:={link}",
        f"laser_reader.family:={FAMILY[rate]}",
        f"laser_reader.measuring_range:={MR}",
        "laser_reader.zero_offset:=0.001",
        f"laser_reader.rate_hz:={rate}",
        "laser_reader.max_speed:=10.0",
        "controller.trigger:=sample",
        f"controller.rate_hz:={rate}",
        "controller.mode:=pid",
        "controller.k0:=0.0",
        f"controller.k1:={K1}",
        "controller.k2:=0.0",
        "controller.on_close:=reset",
        "controller.allow_unverified_gains:=true",
        f"controller.u_bias:={U_BIAS}",
        "controller.u_min:=0.0",
        "controller.u_max:=400.0",
        "controller.reference_source:=constant",
        f"controller.reference:={REFERENCE}",
        "controller.start_closed:=true",
        "controller.max_gap:=1.0",
    ]
    return params + EXTRA


def cpu_seconds(pids: list[int]) -> float:
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / tick
    return total


def rss_bytes(pids: list[int]) -> int:
    total = 0
    for pid in pids:
        try:
            for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
        except OSError:
            continue
    return total


@contextlib.contextmanager
def loop_under_test(
    form: str, rate: float, port: int, link: str, lines: list[str]
) -> Iterator[list[int]]:
    """The graph ``form`` launched (or the ``minimal`` loop started); yields its pids."""
    if form == "minimal":
        proc = subprocess.Popen(
            [
                sys.executable,
                "-c",
                MINIMAL,
                link,
                str(port),
                str(MR),
                "1e-3",
                str(K1),
                str(U_BIAS),
                str(REFERENCE),
            ]
        )
        try:
            yield [proc.pid]
        finally:
            proc.kill()
            proc.wait()
        return
    with Launcher(
        form,
        namespace=NS,
        params=graph_params(form, rate, port, link),
        sink=lambda name, line, err: lines.append(f"[{name}] {line}"),
        timeout=30.0,
    ) as launch:
        yield list(launch.pids.values())


def serve(device: str, args: list[str]) -> None:
    """A device in a process of its own (``--serve sensor RATE LINK LOG`` or ``--serve
    amplifier PORT LOG N``: LOG.running appears after N voltages), as real devices are: no
    thread of the measuring process between taking a time and writing a frame, or between a
    voltage's arrival and its log entry, and
    the collector off (a device does not pause; a full collection over a long log would stall
    the emulator for tens of ms, which the loop under test would be charged for). The log goes
    to LOG on SIGTERM."""
    import gc
    import signal

    gc.disable()
    if device == "sensor":
        rate, link, log_path = float(args[0]), args[1], args[2]
        sensor = LoggingSensor(frame_format(FAMILY[rate]), MR, rate, source=sawtooth(rate))
        server = EmulatorServer(sensor, pty=True, pty_link=link)
        log: list = sensor.log
    else:
        port, log_path, running_after = int(args[0]), args[1], int(args[2])
        log = []

        def on_voltage(v: float, at: float | None) -> None:
            log.append((time.monotonic() if at is None else at, v))
            if len(log) == running_after:  # the loop runs
                Path(log_path + ".running").touch()

        amp_model = GCSDeviceModel(v_min=0.0, v_max=400.0, on_voltage=on_voltage)
        server = EmulatorServer(amp_model, tcp_port=port)
    stop = StopFlag()
    signal.signal(signal.SIGTERM, stop)
    server.start()
    Path(log_path + ".ready").touch()
    while not stop.is_set():
        time.sleep(0.05)
    server.stop()
    np.save(log_path, np.array(log, dtype=np.float64).reshape(len(log), -1))


def _wait_for(path: Path, label: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        if time.monotonic() > deadline:
            raise RuntimeError(f"{label} did not start")
        time.sleep(0.05)


VIEWED = ("displacement", "voltage_command", "controller_state")


@contextlib.contextmanager
def watched(port: int) -> Iterator[tuple[int, dict[str, int]]]:
    """The live_view node on ``port`` and a Foxglove client subscribed to ``VIEWED``; yields
    the node's pid and the client's message counts per topic."""
    import json
    import threading

    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    view = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "piezo_stage.nodes.live_view",
            "--ros-args",
            "-r",
            f"__ns:={NS}",
            "-p",
            f"port:={port}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    counts: dict[str, int] = {}
    try:
        deadline = time.monotonic() + 30.0
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError("live_view did not start") from None
                time.sleep(0.1)
        with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:
            by_sub: dict[int, str] = {}

            def receive() -> None:
                try:
                    while True:
                        frame = ws.recv()
                        if isinstance(frame, bytes):
                            topic = by_sub.get(int.from_bytes(frame[1:5], "little"))
                            if topic:
                                counts[topic] = counts.get(topic, 0) + 1
                            continue
                        msg = json.loads(frame)
                        if msg["op"] != "advertise":
                            continue
                        for ch in msg["channels"]:
                            short = ch["topic"].rsplit("/", 1)[-1]
                            if (
                                ch["topic"] == f"{NS}/{short}"
                                and short in VIEWED
                                and short not in by_sub.values()
                            ):
                                sub = len(by_sub) + 1
                                by_sub[sub] = short
                                ws.send(
                                    json.dumps(
                                        {
                                            "op": "subscribe",
                                            "subscriptions": [{"id": sub, "channelId": ch["id"]}],
                                        }
                                    )
                                )
                except ConnectionClosed:
                    pass

            thread = threading.Thread(target=receive, daemon=True)
            thread.start()
            yield view.pid, counts
    finally:
        view.terminate()
        view.wait(timeout=30.0)


def measure(
    form: str,
    rate: float,
    seconds: float,
    busy: bool = False,
    label: str | None = None,
    view: bool = False,
) -> Figures:
    """One run: devices up, the loop started, ``seconds`` of loop measured (``view``: with
    the live view watching)."""
    label = label or f"{form} {rate / 1000:g} kHz" + (" + busy" if busy else "")
    port = free_port()
    tmp = Path(tempfile.mkdtemp(prefix="bench_rig_"))
    link, sensor_log, amp_log = str(tmp / "sensor"), str(tmp / "sensor.npy"), str(tmp / "amp.npy")
    devices = [
        subprocess.Popen([sys.executable, __file__, "--serve", *argv])
        for argv in (
            ["sensor", str(rate), link, sensor_log],
            ["amplifier", str(port), amp_log, str(int(rate))],
        )
    ]
    hog = None
    try:
        _wait_for(Path(sensor_log + ".ready"), "the sensor")
        _wait_for(Path(amp_log + ".ready"), "the amplifier")
        lines: list[str] = []
        with (
            loop_under_test(form, rate, port, link, lines) as pids,
            watched(free_port()) if view else contextlib.nullcontext((0, {})) as viewer,
        ):
            if busy:
                hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
            try:  # a second's worth of voltages: the loop runs
                _wait_for(Path(amp_log + ".running"), f"{label}: the loop")
            except RuntimeError as exc:
                raise RuntimeError(f"{exc}\n" + "\n".join(lines[-20:])) from None
            time.sleep(1.0)
            view_pid, counts = viewer
            t0, cpu0, rss0 = time.monotonic(), cpu_seconds(pids), rss_bytes(pids)
            view0, got0 = cpu_seconds([view_pid]) if view else 0.0, dict(counts)
            time.sleep(seconds)
            t1, cpu1, rss1 = time.monotonic(), cpu_seconds(pids), rss_bytes(pids)
            view1, got1 = cpu_seconds([view_pid]) if view else 0.0, dict(counts)
            time.sleep(0.3)  # answers to the last samples
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
        for device in devices:
            device.terminate()
            device.wait(timeout=30.0)
    log = [(t, int(a), int(b)) for t, a, b in np.load(sensor_log)]
    answers = [(float(t), float(v)) for t, v in np.load(amp_log)]
    fig = figures(label, log, answers, rate, t0, t1, cpu1 - cpu0, rss1 - rss0)
    if view:
        rates = [(got1.get(t, 0) - got0.get(t, 0)) / (t1 - t0) for t in VIEWED]
        fig.view_cpu = 100 * (view1 - view0) / (t1 - t0)
        fig.view = f"view: {fig.view_cpu:.1f} % of a core; client got " + ", ".join(
            f"{t} {r:.0f}/s" for t, r in zip(VIEWED, rates)
        )
    return fig


def figures(
    label: str,
    log: list[tuple[float, int, int]],
    answers: list[tuple[float, float]],
    rate: float,
    t0: float,
    t1: float,
    cpu: float,
    rss: float,
) -> Figures:
    """Each sample written in [t0, t1) is answered by the first voltage computed from it or from
    a later sample (a read that brings several samples at once is answered by the newest)."""
    written = np.array([(t, k) for t, a, b in log for k in range(a, b)])
    t_all, k_all = written[:, 0], written[:, 1].astype(np.int64)
    at = np.array([a for a, _ in answers])
    volts = np.array([v for _, v in answers])
    x = REFERENCE + 1e-3 - (volts - U_BIAS) / K1  # the position each voltage was computed from
    level = np.rint((x - BASE) / STEP).astype(np.int64) % LEVELS
    # the sample each answer was computed from: the newest one written before it with its level
    newest = k_all[np.clip(np.searchsorted(t_all, at, side="right") - 1, 0, None)]
    source = newest - (newest - level) % LEVELS
    keep = (at >= t_all[0]) & (np.abs(newest - source) < LEVELS // 2)
    at, source = at[keep], np.maximum.accumulate(source[keep])
    inside = (t_all >= t0) & (t_all < t1)
    t_write, k = t_all[inside], k_all[inside]
    first = np.searchsorted(source, k)  # the first answer from this sample or a later one
    answered = first < source.size
    latencies = np.full(k.size, np.inf)
    latencies[answered] = at[first[answered]] - t_write[answered]
    late = latencies > 0.5 * LEVELS / rate
    return Figures(
        label, int(k.size), latencies[~late], int(np.count_nonzero(late)), cpu / max(k.size, 1), rss
    )


DESIGNS = {
    "loop thread drains, 50 us switch": [],
    "publisher thread drains (sliced)": ["controller.publish_in:=publisher"],
    "executor's thread drains": ["controller.publish_in:=executor"],
    "hand-off, 5 ms switch": ["controller.switch_interval:=0.005"],
    "inline publishing": ["controller.publish_in:=inline"],
}


def compare_designs(seconds: float, rates: list[float]) -> int:
    """rig_loop's design alternatives (controller parameters of its process), in turn."""
    for rate in rates:
        for busy in (False, True):
            for name, params in DESIGNS.items():
                EXTRA.extend(params)
                try:
                    label = f"{name}, {rate / 1000:g} kHz" + (" + busy" if busy else "")
                    print(measure("rig_loop", rate, seconds, busy, label=label).line(), flush=True)
                finally:
                    del EXTRA[len(EXTRA) - len(params) :]
    return 0


def judge_rig_loop(fig: Figures, rate: float, busy: bool) -> None:
    """rig_loop's own targets for one run: p99, CPU per sample, none unanswered."""
    p99_target, cpu_target = TARGETS.get((rate, busy), (None, None))
    if p99_target is not None:
        check(f"{fig.label}: p99", fig.p99() * 1e3, p99_target, "ms")
    if cpu_target is not None:
        check(f"{fig.label}: CPU per sample", fig.cpu_per_sample * 1e6, cpu_target, "us")
    check(f"{fig.label}: unanswered samples", fig.unanswered, 0)


def compare_forms(base: Figures, new: Figures, rate: float) -> None:
    """rig_loop against rig_closed_loop at one rate (targets at 1 kHz)."""
    p99_ratio = new.p99() / base.p99()
    cpu_ratio = new.cpu_per_sample / base.cpu_per_sample
    print(
        f"{rate / 1000:g} kHz, rig_loop / rig_closed_loop: p99 {p99_ratio:.3f}x, "
        f"CPU per sample {cpu_ratio:.3f}x"
    )
    if rate == 1000.0:
        check("1 kHz p99, rig_loop / rig_closed_loop", p99_ratio, RATIO_TARGETS[0], "x")
        check("1 kHz CPU per sample, rig_loop / rig_closed_loop", cpu_ratio, RATIO_TARGETS[1], "x")


def with_view(seconds: float) -> int:
    """rig_loop at 1 kHz without and with the live view, twice; the view's CPU judged."""
    for view in (False, True, False, True):
        label = "rig_loop 1 kHz" + (" + view" if view else "")
        fig = measure("rig_loop", 1000.0, seconds, view=view, label=label)
        print(fig.line(), flush=True)
        if view:
            check(f"{label}: the view's CPU", fig.view_cpu, VIEW_TARGET, "% of a core")
    print("(not judged: the loop's figures unchanged with the view watching)")
    return exit_code()


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=10.0, help="measured seconds per run")
    parser.add_argument(
        "--forms",
        default="rig_closed_loop,rig_loop,minimal",
        help="graphs to run (minimal: a one-thread Python loop, this host's floor)",
    )
    parser.add_argument("--rates", default="1000,10000")
    parser.add_argument(
        "--soak",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="instead: rig_loop alone at 1 kHz for this long (RSS, unanswered)",
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NODE.KEY:=VALUE",
        help="one more parameter for every run, e.g. controller.topics_rate_hz:=500.0",
    )
    parser.add_argument(
        "--designs",
        action="store_true",
        help="instead: rig_loop's design alternatives side by side",
    )
    parser.add_argument(
        "--view",
        action="store_true",
        help="instead: rig_loop at 1 kHz without and with the live view",
    )
    parser.add_argument(
        "--serve", nargs="+", metavar="DEVICE", help=argparse.SUPPRESS
    )  # a device's own process (see serve)
    args = parser.parse_args()
    if args.serve:
        serve(args.serve[0], args.serve[1:])
        return 0
    EXTRA.extend(args.param)
    if args.designs:
        return compare_designs(args.seconds, [float(r) for r in args.rates.split(",")])
    if args.view:
        return with_view(args.seconds)
    if args.soak > 0:
        fig = measure("rig_loop", 1000.0, args.soak, label="rig_loop 1 kHz soak")
        print(fig.line())
        check(f"{fig.label}: unanswered samples", fig.unanswered, 0)
        return exit_code()
    forms = args.forms.split(",")
    rates = [float(r) for r in args.rates.split(",")]
    runs = [(f, r, False) for r in rates for f in forms]
    if 1000.0 in rates:
        runs[len(forms) : len(forms)] = [(f, 1000.0, True) for f in forms]
    results = []
    for form, rate, busy in runs:
        fig = measure(form, rate, args.seconds, busy)
        results.append((form, rate, busy, fig))
        print(fig.line(), flush=True)
        if form == "rig_loop":
            judge_rig_loop(fig, rate, busy)
    by = {(f, r, b): fig for f, r, b, fig in results}
    for rate in rates:
        base, new = by.get(("rig_closed_loop", rate, False)), by.get(("rig_loop", rate, False))
        if base and new and base.latencies.size and new.latencies.size:
            compare_forms(base, new, rate)
    return exit_code()


if __name__ == "__main__":
    sys.exit(main())
