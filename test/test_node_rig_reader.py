"""laser_reader node over real DDS against the optoNCDT emulator on a pty in this process: metres
and sign convention, error values as statuses with NaN, lost and corrupted bytes never becoming
an invalid displacement, decimation and stamps on the sensor's sample clock, reconnecting after
the sensor's link drops."""

from __future__ import annotations

import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus

from piezo_stage.hardware.emulators import EmulatorServer, Faults, OptoNCDTDeviceModel
from piezo_stage.hardware.optoncdt import Status, frame_format
from piezo_stage.nodes.qos import SENSOR_QOS

from rig_support import DiagnosticsProbe
from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros

NS = "/rig"
MR = 10e-3


class Level:
    """A settable constant distance [m] as the emulator's source (NaN: no target)."""

    def __init__(self, d: float) -> None:
        self.d = d

    def __call__(self, t: np.ndarray) -> np.ndarray:
        return np.full(t.shape, self.d)


class Reader:
    def __init__(self, probe, server: EmulatorServer, family: str, *params: str) -> None:
        from piezo_stage_msgs.msg import Displacement

        self.probe = probe
        self.proc = start_node(
            "laser_reader",
            f"url:={server.url}",
            f"family:={family}",
            f"measuring_range:={MR}",
            *params,
            namespace=NS,
        )
        self.samples: list = []
        probe.create_subscription(Displacement, "displacement", self.samples.append, SENSOR_QOS)
        self.diag = DiagnosticsProbe(probe, f"{NS}/laser_reader")
        assert spin_until(probe, lambda: len(self.samples) > 50, 20.0), stop(self.proc)

    def wait(self, predicate, timeout: float = 5.0) -> bool:
        return spin_until(self.probe, predicate, timeout)

    def collect(self, n: int, timeout: float = 10.0) -> list:
        start = len(self.samples)
        assert self.wait(lambda: len(self.samples) - start >= n, timeout)
        return self.samples[start:]


def quantised(family: str, d: float) -> float:
    """The distance the sensor can report for d (its digital value, converted back)."""
    fmt = frame_format(family)
    return float(fmt.to_metres(fmt.from_metres(np.array([d]), MR), MR)[0])


@pytest.mark.parametrize("family", ["ild1700", "ild1750"])
def test_valid_frames_give_metres_with_offset_and_sign(probe, family):
    model = OptoNCDTDeviceModel(frame_format(family), MR, 1000.0, source=Level(3e-3))
    with EmulatorServer(model, pty=True) as server:
        r = Reader(probe, server, family, "zero_offset:=0.001", "sign:=-1", "rate_hz:=1000.0")
        try:
            got = r.collect(200)
            assert r.wait(
                lambda: r.diag.latest is not None and r.diag.latest.level == DiagnosticStatus.OK,
                3.0,
            )
            assert float(r.diag.value("frame_rate")) > 100.0
        finally:
            stop(r.proc)
    expected = -(quantised(family, 3e-3) - 1e-3)
    assert abs(expected + 2e-3) < 1e-6  # the quantum is well below a micrometre
    assert all(
        s.status == Status.OK and s.displacement == pytest.approx(expected, abs=1e-12) for s in got
    )
    t = np.array([s.header.stamp.sec + 1e-9 * s.header.stamp.nanosec for s in got])
    # samples of one block are stamped 1/rate apart, back from the reception time
    assert np.median(np.diff(t)) == pytest.approx(1e-3, rel=0.05)


def test_error_values_become_statuses_with_nan(probe):
    level = Level(5e-3)
    model = OptoNCDTDeviceModel(frame_format("ild1320"), MR, 1000.0, source=level, seed=3)
    with EmulatorServer(model, pty=True) as server:
        r = Reader(probe, server, "ild1320")
        try:
            seen = {}
            for d, status in (
                (math.nan, Status.NO_TARGET),
                (-1e-3, Status.TOO_CLOSE),
                (2 * MR, Status.TOO_FAR),
            ):
                level.d = d
                assert r.wait(lambda s=status: r.samples[-1].status == s), (d, r.samples[-1])
                seen[status] = r.collect(20)[-10:]
            model.error_probability = 1.0  # every sample an error code of the family's table
            r.collect(300)
            codes = {s.status for s in r.samples[-200:]}
            assert r.wait(
                lambda: r.diag.latest is not None and r.diag.latest.level == DiagnosticStatus.WARN,
                3.0,
            )
            model.error_probability = 0.0
            level.d = 5e-3
            assert r.wait(lambda: r.samples[-1].status == Status.OK)
        finally:
            stop(r.proc)
    for status, samples in seen.items():
        assert all(s.status == status and math.isnan(s.displacement) for s in samples)
    assert Status.INVALID in codes and Status.OK not in codes, codes
    assert all(math.isnan(s.displacement) for s in r.samples if s.status != Status.OK)
    assert r.samples[-1].displacement == pytest.approx(quantised("ild1320", 5e-3), abs=1e-12)


@pytest.mark.parametrize("family", ["ild1700", "ild1320"])
def test_lost_bytes_never_become_a_displacement(probe, family):
    model = OptoNCDTDeviceModel(frame_format(family), MR, 2000.0, source=Level(4e-3))
    faults = Faults(drop=0.05, seed=7)
    with EmulatorServer(model, pty=True, faults=faults) as server:
        r = Reader(probe, server, family, "rate_hz:=2000.0")
        try:
            got = r.collect(1000)
            assert r.wait(lambda: int(r.diag.value("resync_bytes_discarded", "0")) > 20, 3.0), (
                r.diag.values
            )
            sent = model.sent_samples
            published = int(r.diag.value("published"))
        finally:
            stop(r.proc)
    assert published < 0.95 * sent  # frames were lost...
    value = quantised(family, 4e-3)
    ok = [s for s in got if s.status == Status.OK]
    assert all(s.displacement == value for s in ok)  # ...none misread
    # the frames after each gap are withheld (INVALID) until the lock is back
    assert 0.3 * len(got) < len(ok) < len(got)
    assert all(
        s.status == Status.INVALID and math.isnan(s.displacement)
        for s in got
        if s.status != Status.OK
    )


@pytest.mark.parametrize("family", ["ild1700", "ild1320", "ild1750"])
def test_corrupted_bytes_never_become_an_invalid_displacement(probe, family):
    """Bytes replaced at random on the link: the frames they break are dropped (resync, counted on
    /diagnostics) and the next relock_frames withheld; a flipped data bit inside a well-formed
    frame (optoNCDT frames have no checksum) is refused by the speed gate (the level does not
    move: max_speed 0.1 mm/s): no OK message is off the true value, none carries a value with a
    non-OK status."""
    model = OptoNCDTDeviceModel(frame_format(family), MR, 2000.0, source=Level(4e-3))
    faults = Faults(corrupt=0.03, seed=11)
    with EmulatorServer(model, pty=True, faults=faults) as server:
        r = Reader(
            probe, server, family, "rate_hz:=2000.0", "zero_offset:=0.002", "max_speed:=1e-4"
        )
        try:
            got = r.collect(1500)
            assert r.wait(
                lambda: (
                    int(r.diag.value("resync_bytes_discarded", "0")) > 20
                    and r.diag.latest.level == DiagnosticStatus.WARN
                ),
                3.0,
            ), r.diag.values
            diag = r.diag.values
        finally:
            stop(r.proc)
    ok = [s for s in got if s.status == Status.OK]
    bad = [s for s in got if s.status != Status.OK]
    value = quantised(family, 4e-3) - 2e-3
    assert all(math.isfinite(s.displacement) and -2e-3 <= s.displacement <= MR - 2e-3 for s in ok)
    assert all(math.isnan(s.displacement) for s in bad)
    assert all(abs(s.displacement - value) <= 1e-3 * MR for s in ok)
    assert len(ok) > 0.2 * len(got) and int(diag["framing_errors"]) > 10
    assert (
        int(diag["published"]) < model.sent_samples
    )  # the broken frames were dropped, not guessed


def test_decimation_averages_and_stamps_each_group(probe):
    rate, n, slope = 1000.0, 5, 2e-3  # 2 mm/s: 2 um per sample

    def ramp(t: np.ndarray) -> np.ndarray:
        return 1e-3 + slope * (t % 3.0)

    model = OptoNCDTDeviceModel(frame_format("ild1320"), MR, rate, source=ramp)
    with EmulatorServer(model, pty=True) as server:
        r = Reader(
            probe, server, "ild1320", f"decimation:={n}", f"rate_hz:={rate}", "latency:=0.001"
        )
        try:
            got = r.collect(200)
            assert r.wait(lambda: r.diag.latest is not None, 3.0)
            frame_rate, publish_rate = (
                float(r.diag.value("frame_rate")),
                float(r.diag.value("publish_rate")),
            )
        finally:
            stop(r.proc)
    x = np.array([s.displacement for s in got])
    t = np.array([s.header.stamp.sec + 1e-9 * s.header.stamp.nanosec for s in got])
    step = np.diff(x)
    step = step[step > 0]  # leave out the wrap of the ramp
    assert np.median(step) == pytest.approx(n * slope / rate, rel=0.02)  # one message per N samples
    # stamped on the sensor's sample clock: one message every n samples, exactly n/rate apart
    assert np.median(np.diff(t)) == pytest.approx(n / rate, abs=1e-6)
    assert publish_rate == pytest.approx(frame_rate / n, rel=0.2)
    assert all(s.status == Status.OK for s in got)


def test_reconnects_after_the_sensor_link_drops(probe, tmp_path):
    """The adapter is unplugged and re-plugged (a new pty behind the same stable link): the node
    reports the loss, reopens the link, and streams again on a fresh sample clock."""
    link = str(tmp_path / "laser")
    model = OptoNCDTDeviceModel(frame_format("ild1320"), MR, 1000.0, source=Level(4e-3))
    with EmulatorServer(model, pty=True, pty_link=link) as server:
        r = Reader(probe, server, "ild1320")
        try:
            server.disconnect()
            assert r.wait(lambda: int(r.diag.value("reconnects", "0")) >= 1, 10.0), r.diag.values
            before = len(r.samples)
            got = r.collect(200)
            assert r.wait(lambda: r.diag.latest.level == DiagnosticStatus.OK, 5.0), r.diag.values
            link_errors = int(r.diag.value("link_errors"))
        finally:
            stop(r.proc)
    assert before > 0 and link_errors >= 1
    assert all(s.status == Status.OK and s.displacement == quantised("ild1320", 4e-3) for s in got)
    t = np.array([s.header.stamp.sec + 1e-9 * s.header.stamp.nanosec for s in got])
    assert np.all(np.diff(t) > 0)


def test_a_reader_started_late_forgets_what_the_link_held(probe):
    """``start=False`` (the composed loop reads the sensor itself, once the process is built):
    samples the sensor sent before the loop's :meth:`AxisSensor.connect` never reach the loop,
    which would otherwise step the law through a late block of stale samples. The sensor reads
    2 mm before the start and 6 mm after (it is silent while the level changes), so a stale
    sample is told by its value, not by timing."""
    import time

    from rclpy.parameter import Parameter

    from piezo_stage.nodes.laser_reader import LaserReaderNode

    values: list[float] = []
    level, faults = Level(2e-3), Faults()
    model = OptoNCDTDeviceModel(frame_format("ild1320"), MR, 1000.0, source=level)
    with EmulatorServer(model, pty=True, faults=faults) as server:
        node = LaserReaderNode(
            start=False,
            overrides=[
                Parameter("url", value=server.url),
                Parameter("family", value="ild1320"),
                Parameter("measuring_range", value=MR),
                Parameter("rate_hz", value=1000.0),
            ],
        )
        sensor = node.sensor
        try:
            deadline = time.monotonic() + 10.0
            while model.sent_samples < 300 and time.monotonic() < deadline:
                time.sleep(0.01)  # samples at 2 mm wait in the link
            assert model.sent_samples >= 300 and node.published == 0
            faults.silent = True
            time.sleep(0.05)  # the server's last write is out
            level.d = 6e-3
            sensor.connect()
            faults.silent = False
            deadline = time.monotonic() + 10.0
            while len(values) < 50 and time.monotonic() < deadline:
                if sensor.wait(0.05):
                    block = sensor.block
                    ok = np.asarray(block.status) == Status.OK  # the first frames relock
                    values.extend(np.asarray(block.displacement)[ok].tolist())
                    sensor.next_cycle()
        finally:
            node.on_shutdown()
            node.destroy_node()
    assert len(values) >= 50
    assert values == [quantised("ild1320", 6e-3)] * len(values), values[:5]
