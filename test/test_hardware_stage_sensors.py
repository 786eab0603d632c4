"""The stage's loop on emulated devices: three optoNCDT sensors on ptys read in one thread
(hardware/stage_sensors.py), one supervised law per axis, one GCS amplifier of axes 1, 2, 3 on
TCP written once per cycle (control/stage_loop.py); a sensor that fails holds its axis alone;
each axis's slew cap and limits hold (they are StageDriver's)."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from piezo_stage.control.controller import ControllerConfig, OnClose, TimeVaryingPID
from piezo_stage.control.laws import Gains
from piezo_stage.control.setpoint import ReferenceSource, SetPoint
from piezo_stage.control.stage_loop import StageLoop, SupervisedLaw, run_stage_loop
from piezo_stage.control.supervision import LoopSupervisor, SupervisionConfig
from piezo_stage.hardware.axis_link import make_axis_link
from piezo_stage.hardware.driver import DriverConfig
from piezo_stage.hardware.emulators import EmulatorServer, GCSDeviceModel
from piezo_stage.hardware.emulators.optoncdt_device import OptoNCDTDeviceModel
from piezo_stage.hardware.emulators.server import Faults
from piezo_stage.hardware.errors import ConfigError
from piezo_stage.hardware.optoncdt import frame_format
from piezo_stage.hardware.sensor import SensorConfig, SensorReader
from piezo_stage.hardware.stage_driver import StageDriver
from piezo_stage.hardware.stage_sensors import StageSensors

pytestmark = pytest.mark.ros  # ptys and a TCP port

AXES = ("1", "2", "3")
RATE, MR = 200.0, 2e-3
U_BIAS, K1 = 200.0, 2e6  # V, V/m
REF = 1e-3  # m: every axis's set point
SLEW, PERIOD = 2000.0, 0.001  # V/s and the driver's write period: at most 2 V per write
# a low rate: the emulators share this process (and its GIL) with the loop under test


def square(amplitude: float, hz: float):
    """REF ± amplitude at ``hz``: the law asks for steps of 2·K1·amplitude."""

    def source(t):
        return REF + amplitude * np.sign(np.sin(2 * np.pi * hz * np.asarray(t) + 0.1))

    return source


class Rig:
    """The devices, the sensors, the laws and the loop thread."""

    def __init__(self, amplitudes=(2e-6, 4e-6, 6e-6), v_max=400.0, slew=math.inf) -> None:
        self.models = [
            OptoNCDTDeviceModel(frame_format("ild1320"), MR, RATE, source=square(a, 5.0))
            for a in amplitudes
        ]
        self.faults = [Faults() for _ in AXES]
        self.sensors = [
            EmulatorServer(m, pty=True, faults=f) for m, f in zip(self.models, self.faults)
        ]
        self.log: list[tuple[str, float]] = []
        self.amp = GCSDeviceModel(
            axes=AXES,
            v_min=0.0,
            v_max=400.0,
            on_axis_voltage=lambda a, v, t: self.log.append((a, v)),
        )
        self.amp_server = EmulatorServer(self.amp, tcp_port=0)
        self.v_max, self.slew = v_max, slew

    def __enter__(self) -> "Rig":
        t0 = time.monotonic() + 0.05  # the sensors on one sync line
        for model in self.models:
            model.synchronise(t0)
        for server in (*self.sensors, self.amp_server):
            server.start()
        config = DriverConfig(
            v_min=0.0,
            v_max=self.v_max,
            slew_rate=self.slew,
            write_period=PERIOD,
            command_timeout=1.0,
        )
        self.driver = StageDriver(
            make_axis_link("gcs", self.amp_server.url, AXES), {a: config for a in AXES}
        )
        self.driver.connect()
        readers = [
            SensorReader.from_url(s.url, SensorConfig("ild1320", MR, rate=RATE))
            for s in self.sensors
        ]
        self.stage = StageSensors(readers, RATE)
        self.stage.connect()
        self.laws = [law() for _ in AXES]
        self.loop = StageLoop(AXES, self.laws, self.driver)
        self.stop = threading.Event()
        self.thread = threading.Thread(
            target=run_stage_loop, args=(self.stage, self.loop, self.stop), daemon=True
        )
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(5.0)
        self.stage.close()
        self.driver.close()
        for server in (*self.sensors, self.amp_server):
            server.stop()

    def writes(self) -> list[list[str]]:
        """The axes of every SVA the amplifier received."""
        return [c.split()[1::2] for c in list(self.amp.commands) if c.startswith("SVA ")]

    def volts(self, axis: str, since: int = 0) -> np.ndarray:
        return np.array([v for a, v in self.log[since:] if a == axis])


class CountingLaw(SupervisedLaw):
    """The law, counting the samples it was given."""

    calls = 0

    def on_sample(self, stamp_ns: int, x: float, ok: bool, publish: bool = True) -> float | None:
        self.calls += 1
        return super().on_sample(stamp_ns, x, ok, publish)


def law() -> CountingLaw:
    pid = TimeVaryingPID(
        ControllerConfig(
            gains=Gains(k0=0.0, k1=K1, k2=0.0), u_min=-200.0, u_max=200.0, on_close=OnClose.RESET
        ),
        closed=False,
    )
    config = SupervisionConfig(
        RATE,
        u_bias=U_BIAS,
        u_min=0.0,
        u_max=400.0,
        start_closed=True,
        max_gap=0.5,  # a silent sensor; a loaded host's stalls stay below it
        start_grace=0.0,
    )
    return CountingLaw(LoopSupervisor(pid, config), SetPoint(ReferenceSource.CONSTANT, REF))


def until(condition, timeout: float = 60.0) -> bool:
    """Wait until ``condition()`` holds (True) or ``timeout`` s pass (False): the loop shares
    this process with the emulators, so a loaded host gives it fewer cycles per second, not
    other cycles."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_every_axis_reaches_its_channel_in_one_sva_per_cycle():
    with Rig() as rig:
        assert until(lambda: sum(w == list(AXES) for w in rig.writes()) > 150)
    writes = rig.writes()
    full = [w for w in writes if w == list(AXES)]
    # each axis enters the write once its sensor's frame lock holds; from then on all three,
    # in order, each once (synchronised sensors: a frame later than half a period misses its
    # cycle and is stepped in the next, rarely idle; the loop shares its GIL with the three
    # emulators: 14 of 155 for one axis was seen beside a busy process, one bound for both)
    first = writes.index(list(AXES))
    assert all(w == sorted(set(w)) for w in writes), writes
    assert len(full) >= 0.8 * len(writes[first:]) and len(full) > 150
    assert len(writes) <= rig.loop.cycles and rig.loop.write_failures == 0
    assert max(rig.stage.dropped) < 0.2 * len(full)
    # every sample decoded was stepped, or dropped and counted (more than a cycle holds)
    for i, x in enumerate(rig.laws):
        assert x.calls == rig.stage.samples[i] - rig.stage.dropped[i] > 150
    for i, axis in enumerate(AXES):  # each axis's law answered its own sensor
        assert rig.laws[i].supervisor.pid.loop_closed
        swing = np.ptp(rig.volts(axis)[-100:])
        assert swing == pytest.approx(2 * K1 * (2e-6, 4e-6, 6e-6)[i], rel=0.05)


@pytest.mark.parametrize("fault", ["silent", "corrupt"])
def test_a_failed_sensor_holds_its_axis_and_the_others_go_on(fault):
    with Rig() as rig:
        assert until(lambda: all(law.supervisor.pid.loop_closed for law in rig.laws))
        assert until(lambda: rig.loop.cycles > 100)
        setattr(rig.faults[1], fault, True if fault == "silent" else 1.0)
        assert until(lambda: rig.laws[1].supervisor.fault)  # max_gap, or the frame lock
        since = len(rig.log)
        cycles = rig.loop.cycles
        # 100 cycles: 0.5 s of the 5 Hz squares at least, however slowly they come
        assert until(lambda: rig.loop.cycles - cycles >= 100)
        cycles = rig.loop.cycles - cycles
    held = rig.volts("2", since)
    assert np.ptp(held) == 0.0 if held.size else True
    assert not rig.laws[1].supervisor.pid.loop_closed
    assert rig.laws[1].supervisor.fault
    for axis in ("1", "3"):
        moving = rig.volts(axis, since)
        assert moving.size >= 0.8 * cycles >= 80  # a loaded host: a frame may miss its cycle
        assert np.ptp(moving) > 5.0
    assert rig.laws[0].supervisor.pid.loop_closed and rig.laws[2].supervisor.pid.loop_closed


def test_slew_cap_and_limits_hold_per_axis():
    # axis 3 asks for 200 ± 24 V: the limit 210 V clips it; every step asks 8-48 V: capped at 2.
    # From 176 V, 210 V takes 17 writes of a 20-sample half period: a loaded host, whose cycles
    # take several samples at once, writes fewer in some half periods (14, 204 V, was seen
    # beside the busy suite), so the run lasts until axis 3 reached the limit
    with Rig(amplitudes=(2e-6, 4e-6, 12e-6), v_max=210.0, slew=SLEW) as rig:
        assert until(
            lambda: (
                min(rig.volts(axis).size for axis in AXES) > 150
                and rig.volts("3").max() >= 210.0 - 1e-6
            )
        ), rig.volts("3").max()
    cap = SLEW * PERIOD
    for axis in AXES:
        v = rig.volts(axis)
        assert v.size > 120
        steps = np.abs(np.diff(v))
        assert steps.max() <= cap + 1e-6
        assert steps.max() == pytest.approx(cap)  # the cap was reached: it held something back
        assert v.max() <= 210.0
    assert rig.volts("3").max() == pytest.approx(210.0)


def test_stage_sensors_refuse_bad_settings():
    reader = SensorReader.from_url("serial:///dev/null", SensorConfig("ild1320", MR))
    with pytest.raises(ConfigError, match="one sensor per axis"):
        StageSensors([], RATE)
    with pytest.raises(ConfigError, match="align"):
        StageSensors([reader], RATE, align=0.01)
    with pytest.raises(ConfigError, match="before connect"):
        StageSensors([reader], RATE).wait(0.0)


def test_a_stalled_loop_catches_up_the_newest_samples_and_counts_the_rest():
    """A loop that reads nothing for 0.3 s (a stalled thread) finds the sensor's backlog in
    its link: it keeps the newest ``max_pending`` samples, each with its own stamp one period
    apart, the newest at the time it read them, and counts every older one as dropped."""
    model = OptoNCDTDeviceModel(frame_format("ild1320"), MR, RATE, source=square(2e-6, 5.0))
    model.synchronise(time.monotonic())
    with EmulatorServer(model, pty=True) as server:
        reader = SensorReader.from_url(server.url, SensorConfig("ild1320", MR, rate=RATE))
        stage = StageSensors([reader], RATE, max_pending=8)
        stage.connect()
        try:

            def cycle() -> bool:  # a loop that takes each cycle as it comes
                due = stage.wait(0.1)
                stage.next_cycle()
                return due and stage.samples[0] > 5

            assert until(cycle, 30.0)
            before = stage.samples[0]
            time.sleep(0.3)  # 60 periods at 200 Hz
            assert stage.wait(1.0)
            read = stage.samples[0] - before
            depth = stage.depth()
            stamps = []
            for j in range(depth):
                stage.take(j, depth)
                stamps.append(stage.stamp[0])
        finally:
            stage.close()
    assert read >= 40  # the backlog was there, in one cycle
    assert depth == 8
    assert stage.dropped[0] == read - 8
    assert np.diff(stamps) == pytest.approx(1e9 / RATE, rel=0.05)
    assert time.time_ns() - stamps[-1] < 2e8  # the nodes' clock: a topic's stamps are ROS time


def test_decimated_sensors_give_the_loop_one_sample_of_n_stamped_at_the_groups_middle():
    """Sensors at 400 Hz decimated by 2 (as the reader node decimates): the loop's samples are
    200 Hz, 5 ms apart, each the mean of two frames, stamped between them; its rate is 200 Hz
    and its cycles come at that rate."""
    source = square(2e-6, 5.0)
    model = OptoNCDTDeviceModel(frame_format("ild1320"), MR, 2 * RATE, source=source)
    model.synchronise(time.monotonic())
    stamps: list[int] = []
    values: list[float] = []
    with EmulatorServer(model, pty=True) as server:
        reader = SensorReader.from_url(server.url, SensorConfig("ild1320", MR, rate=2 * RATE))
        stage = StageSensors([reader], 2 * RATE, decimation=2)
        stage.connect()
        try:
            cycles, began = 0, None
            deadline = time.monotonic() + 30.0
            while len(stamps) < 150 and time.monotonic() < deadline:
                if stage.wait(0.1):
                    cycles += 1
                    depth = stage.depth()
                    for j in range(depth):
                        stage.take(j, depth)
                        if stage.fresh[0] and stage.status[0] == 0:
                            stamps.append(stage.stamp[0])
                            values.append(stage.value[0])
                    stage.next_cycle()
                    began = time.monotonic() if began is None else began
            wall = time.monotonic() - began
        finally:
            stage.close()
    assert stage.rate == RATE and len(stamps) >= 150
    # one loop sample per two frames: 200 a second of the wall, not the sensor's 400
    assert (len(stamps) - 1) / wall == pytest.approx(RATE, rel=0.15)
    step = np.diff(stamps)
    assert np.median(step) == pytest.approx(1e9 / RATE, rel=0.02)
    assert cycles <= len(stamps) + 5  # a cycle per loop sample, not per frame
    # away from the square's edges both frames of a group read the same level
    level = np.abs(np.array(values) - REF)
    assert np.median(level) == pytest.approx(2e-6, rel=0.05)


def test_a_lost_sensor_link_is_reopened_while_the_other_axes_go_on(tmp_path):
    """The sensor of axis 2 goes away (its adapter unplugged): its axis leaves the cycles
    (``down``, the reason in ``errors``) while axis 1 keeps its cycles, no wait longer than
    the loop asked, though every reconnect attempt fails; once the sensor is back behind the
    same link, a thread of its own reopens it and the loop's next wait takes it back."""
    links = [str(tmp_path / f"sensor_{k}") for k in (1, 2)]

    def sensor(link: str) -> EmulatorServer:
        model = OptoNCDTDeviceModel(frame_format("ild1320"), MR, RATE, source=square(2e-6, 5.0))
        return EmulatorServer(model, pty=True, pty_link=link).start()

    servers = [sensor(link) for link in links]
    readers = [
        SensorReader.from_url(link, SensorConfig("ild1320", MR, rate=RATE)) for link in links
    ]
    stage = StageSensors(readers, RATE)
    fresh, longest = [0, 0], [0.0]

    def cycles_until(condition, timeout: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                return False
            t0 = time.monotonic()
            if stage.wait(0.05):
                fresh[0] += stage.fresh[0]
                fresh[1] += stage.fresh[1]
                stage.next_cycle()
            longest[0] = max(longest[0], time.monotonic() - t0)
        return True

    stage.connect()
    try:
        assert cycles_until(lambda: min(fresh) > 20)
        servers[1].stop()
        assert cycles_until(lambda: stage.down[1])
        longest[0], before = 0.0, fresh[0]
        assert cycles_until(lambda: fresh[0] - before > 100)  # 0.5 s of axis 1's samples
        assert stage.down[1] and stage.errors[1] is not None and stage.reconnects[1] == 0
        assert not stage.down[0]
        servers[1] = sensor(links[1])
        assert cycles_until(lambda: not stage.down[1])
        before = fresh[1]
        assert cycles_until(lambda: fresh[1] - before > 20)
        assert stage.errors == [None, None] and stage.reconnects == [0, 1]
    finally:
        stage.close()
        for server in servers:
            server.stop()
    assert longest[0] < 0.25  # a wait of 0.05 s (a loaded host may add to it), never a reconnect
