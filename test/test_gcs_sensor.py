"""A PI controller's own sensor as the loop's displacement source
(piezo_stage/hardware/gcs_sensor.py): ``POS? <axis>`` polled on a deadline grid. Against a
scripted link (unit): strict replies, a property that no reply bytes but ``<axis>=<number>``
become a finite displacement. Against the E-727 emulator on loopback TCP (in this process):
values equal the controller's position, pacing, garbled replies, a stall and a hang-up. Over
real DDS: the laser_reader node refuses an axis SAI? does not list (exit 2), and the
pi_rig_loop graph closes the loop on the PI sensor."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from test_pi_controller_pipython import NOISE, V_MAX, V_MIN, _stage

from piezo_stage.hardware.emulators import EmulatorServer, Faults
from piezo_stage.hardware.emulators.pi_controller import PIControllerModel
from piezo_stage.hardware.errors import ConfigError, TransportError
from piezo_stage.hardware.gcs_sensor import GCSPositionReader, GCSReaderConfig, parse_position
from piezo_stage.hardware.optoncdt import Status
from piezo_stage.hardware.transport import Transport

from property_support import examples

NS = "/pi_sensor"
UM = 1e-6


# --- a scripted link (unit) ----------------------------------------------------------------------
class ScriptedLink(Transport):
    """Answers ``SAI?`` with axes 1, 2, 3 and every ``POS?`` with the next of ``replies``."""

    url = "scripted://e727"

    def __init__(self, replies: list[bytes]) -> None:
        self.replies, self.out, self.queries = list(replies), bytearray(), 0
        self._open = False

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def write(self, data: bytes) -> None:
        if data.startswith(b"SAI?"):
            self.out += b"1 \n2 \n3\n"
        elif data.startswith(b"POS?"):
            self.queries += 1
            self.out += self.replies.pop(0) if self.replies else b""

    def read(self, timeout: float) -> bytes:
        data, self.out = bytes(self.out), bytearray()
        return data

    def reset_input(self) -> None:
        self.out.clear()


def scripted(replies: list[bytes], rate: float = 1e4) -> tuple[GCSPositionReader, ScriptedLink]:
    link = ScriptedLink(replies)
    reader = GCSPositionReader(link, GCSReaderConfig("1", rate, reply_timeout=0.005))
    reader.connect()
    return reader, link


def read_all(reader: GCSPositionReader, n: int) -> tuple[list[float], list[int]]:
    """``n`` polls' samples, reopening the link after a timeout as the node does."""
    values: list[float] = []
    status: list[int] = []
    while len(status) < n:
        try:
            block = reader.read(0.05)
        except TransportError:
            reader.reconnect()
            continue
        values += block.displacement.tolist()
        status += block.status.tolist()
    return values, status


@pytest.mark.unit
def test_a_reply_is_the_axis_position_in_metres_and_anything_else_is_invalid():
    assert parse_position(b"1=12.5\n", "1") == pytest.approx(12.5e-6)
    assert parse_position(b"1=-3e-1\n", "1") == pytest.approx(-0.3e-6)
    assert parse_position(b"A=.5\r\n", "A") == pytest.approx(0.5e-6)
    for bad in (
        b"2=12.5\n",  # another axis
        b"1=12.5 \n2=3\n",  # two lines
        b"1=nan\n",
        b"1=inf\n",
        b"1=1e999\n",  # not finite
        b"1=\n",
        b"=12.5\n",
        b"1 12.5\n",
        b"1=12.5x\n",
        b"1=1_2\n",
        b"1= 12.5\n",
        b"\x001=12.5\n",
        b"1=12.5\xff\n",
    ):
        assert parse_position(bad, "1") is None, bad


@pytest.mark.unit
def test_invalid_replies_and_silence_are_invalid_samples_counted():
    reader, link = scripted([b"1=2.5\n", b"1=x\n", b"", b"1=3.5\n"])
    values, status = read_all(reader, 4)
    assert status == [Status.OK, Status.INVALID, Status.INVALID, Status.OK]
    assert values[0] == pytest.approx(2.5e-6) and values[3] == pytest.approx(3.5e-6)
    assert math.isnan(values[1]) and math.isnan(values[2])
    counts = reader.counters()
    assert (counts["frames"], counts["invalid_replies"], counts["reply_timeouts"]) == (2, 1, 1)
    assert reader.reconnects == 1  # after the timeout: a fresh link, no late reply taken
    # (and the slots the 5 ms wait for the silent reply missed at 10 kHz, when it did)
    assert reader.warning({}, counts).startswith(
        "1 reply(ies) not '<axis>=<number>', 1 poll(s) unanswered"
    )


@pytest.mark.unit
def test_bytes_waiting_before_a_query_are_dropped_not_taken_as_its_reply():
    # the first reply carries an LF in front: "junk\n" answers the first query, and what
    # follows it ("1=9\n", a stale answer) is dropped before the second query
    reader, link = scripted([b"junk\n1=9\n", b"1=4\n"])
    values, status = read_all(reader, 2)
    assert status == [Status.INVALID, Status.OK] and values[1] == pytest.approx(4e-6)
    assert reader.counters()["unsolicited_bytes_dropped"] == len(b"1=9\n")


@pytest.mark.unit
def test_an_axis_sai_does_not_list_is_a_config_error():
    reader = GCSPositionReader(ScriptedLink([]), GCSReaderConfig("7"))
    with pytest.raises(ConfigError, match=r"axis '7' not on the controller .*SAI\? lists"):
        reader.connect()
    with pytest.raises(ConfigError):
        GCSReaderConfig("1 2")


NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.from_regex(r"\A[+-]?\d{0,4}\.?\d{0,4}(e[+-]?\d{1,4})?\Z"),
)
REPLY = st.one_of(
    st.binary(max_size=40),
    st.builds(
        lambda axis, eq, number, end: f"{axis}{eq}{number}".encode("ascii", "replace") + end,
        st.sampled_from(["1", "2", "11", "", " 1"]),
        st.sampled_from(["=", "==", " ", ""]),
        NUMBER,
        st.sampled_from([b"\n", b" \n", b"\r\n", b"", b"\n1=5\n", b" \n2=1\n"]),
    ),
)


def well_formed(reply: bytes, value: float) -> bool:
    """The reply's first line (up to its LF: a GCS reply ends at an LF without a space before
    it) is ``1=<text>``, the text a finite number equal to ``value`` um."""
    line = reply[: reply.index(b"\n")]
    head, _, number = line.rstrip(b"\r").decode("ascii").partition("=")
    return (
        not line.endswith(b" ")
        and head == "1"
        and math.isfinite(float(number))
        and float(number) * UM == value
    )


@pytest.mark.unit
@settings(max_examples=examples(300), deadline=None)
@given(REPLY)
@example(b"1=12.5\n")
@example(b"1=12.5 \n1=13\n")
def test_no_reply_but_axis_equals_number_becomes_a_finite_displacement(reply):
    reader, link = scripted([reply])
    values, status = read_all(reader, 1)
    if status[0] == Status.OK:
        assert math.isfinite(values[0]) and well_formed(reply, values[0]), reply
    else:
        assert math.isnan(values[0])


class FakeClock:
    """Seconds that pass only when slept on or moved on: the reader's grid without wall time."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(seconds, 0.0)


@pytest.mark.unit
def test_polls_keep_to_their_slots_and_a_late_host_skips_and_counts_slots(monkeypatch):
    """On a 200 Hz grid: one poll per slot however long a read may wait, nothing from a wait
    shorter than the time to the next slot, and the slots a host that came back late missed are
    counted and skipped, not caught up with a burst."""
    clock = FakeClock()
    monkeypatch.setattr(time, "sleep", clock.sleep)
    reader = GCSPositionReader(
        ScriptedLink([b"1=1\n"] * 20), GCSReaderConfig("1", 200.0, reply_timeout=0.005), clock
    )
    reader.connect()
    start = clock()
    polled_at = []
    for _ in range(10):
        assert len(reader.read(0.05)) == 1  # a wait longer than the period: one poll, at its slot
        polled_at.append(clock() - start)
    assert polled_at == pytest.approx([0.005 * k for k in range(10)], abs=1e-9)
    assert len(reader.read(0.001)) == 0  # the next slot is 5 ms away
    assert len(reader.read(0.05)) == 1 and clock() - start == pytest.approx(0.050, abs=1e-9)
    clock.sleep(0.023)  # the host comes back in the slot at 70 ms, three slots late
    assert len(reader.read(0.05)) == 1 and reader.stats.missed_polls == 3
    assert len(reader.read(0.001)) == 0  # no burst: the next poll is at the 75 ms slot
    assert len(reader.read(0.05)) == 1 and clock() - start == pytest.approx(0.075, abs=1e-9)
    assert (reader.stats.polls, reader.stats.missed_polls) == (13, 3)  # 16 slots: 0 to 75 ms


# --- the E-727 emulator on loopback TCP ----------------------------------------------------------
@pytest.fixture()
def e727():
    model = PIControllerModel(_stage(), ("1", "2", "3"), v_min=V_MIN, v_max=V_MAX)
    with EmulatorServer(model, tcp_port=0, faults=Faults(seed=3)) as server:
        yield model, server


def reader_on(server: EmulatorServer, rate: float = 1000.0, **config) -> GCSPositionReader:
    """A connected reader on the emulator; a reply may take 1 s (not the node's 50 ms: the
    emulator shares this process's GIL, and a late reply here is a loaded host, not a fault)
    unless the test sets ``reply_timeout``."""
    config.setdefault("reply_timeout", 1.0)
    reader = GCSPositionReader.from_url(server.url, GCSReaderConfig("1", rate, **config))
    reader.connect()
    return reader


def count_queries(model: PIControllerModel) -> list[float]:
    """Arrival times of the model's POS? lines from now on."""
    arrivals: list[float] = []
    execute = model.execute

    def counting(line: str, now: float | None = None) -> bytes:
        if line.startswith("POS?"):
            arrivals.append(time.monotonic())
        return execute(line, now)

    model.execute = counting  # type: ignore[method-assign]
    return arrivals


@pytest.mark.ros
def test_values_are_the_controllers_position_in_metres(e727):
    model, server = e727
    model.execute("SVA 1 50")  # the stage moves to ~4.5 um and settles
    reader = reader_on(server)
    time.sleep(0.3)
    values, status = read_all(reader, 300)
    position = model.position[0] * UM
    assert all(s == Status.OK for s in status)
    assert 3e-6 < position < 6e-6
    assert np.mean(values) == pytest.approx(position, abs=3 * NOISE)
    assert np.std(values) < 3 * NOISE and np.ptp(values) < 20 * NOISE


@pytest.mark.ros
def test_polls_are_paced_one_per_period(e727):
    """In wall time, against the emulator: every read is one poll the device answers, and each
    slot of the 200 Hz grid from the first poll to the last is polled once or counted missed.
    Counts, not durations: a loaded host misses slots (and a reply may come late in its slot);
    the pacing itself is the fake-clock test above."""
    model, server = e727
    reader = reader_on(server, rate=200.0)
    arrivals = count_queries(model)
    t0 = time.monotonic()
    samples = len(reader.read(0.05))  # the first poll starts the grid
    first = last = time.monotonic()
    while last - t0 < 1.0:
        last = time.monotonic()
        samples += len(reader.read(0.05))  # a wait longer than the period: still one per slot
    elapsed = time.monotonic() - t0
    stats = reader.stats
    assert samples == stats.polls == len(arrivals)
    # the grid starts between t0 and `first`; the last read polled at or after `last`
    slots = stats.polls + stats.missed_polls
    assert 200 * (last - first) < slots <= 200 * elapsed + 1, (stats, elapsed)


@pytest.mark.ros
def test_garbled_replies_are_invalid_samples_never_displacements(e727):
    model, server = e727
    reader = reader_on(server)
    server.faults.garbage = 1.0  # 1-32 random bytes in front of every reply
    values, status = read_all(reader, 200)
    server.faults.garbage = 0.0
    counts = reader.counters()
    assert counts["invalid_replies"] >= 150, counts
    position = model.position[0] * UM
    ok = [v for v, s in zip(values, status) if s == Status.OK]
    assert all(abs(v - position) < 20 * NOISE for v in ok)  # an OK one is a real reading
    assert all(math.isnan(v) for v, s in zip(values, status) if s != Status.OK)
    values, status = read_all(reader, 50)
    assert status[-10:] == [Status.OK] * 10


def node_like(reader: GCSPositionReader, stop: threading.Event) -> None:
    """The node's read loop, and the loop of a stage of one axis: its AxisSensor reads, and
    reopens the link after a link error."""
    from piezo_stage.hardware.axis_sensor import AxisSensor

    sensor = AxisSensor(reader, reader.config.rate, sleep=stop.wait)
    while not stop.is_set():
        sensor.wait(0.002)
        sensor.next_cycle()


def stall_once(server: EmulatorServer, seconds: float) -> None:
    """The device stops for ``seconds`` before its next reply (nothing out, input ignored)."""
    server.faults.stall_time = seconds
    server.faults.stall = 1.0
    deadline = time.monotonic() + 2.0
    while server.faults.counts["stalls"] == 0 and time.monotonic() < deadline:
        time.sleep(0.001)
    server.faults.stall = 0.0


@pytest.mark.ros
@pytest.mark.parametrize("fault", ["stall", "hangup"])
def test_a_stalled_or_dropped_link_goes_stale_then_reconnects(e727, fault):
    model, server = e727
    reader = reader_on(server, stale_timeout=0.1, reply_timeout=0.02)
    stop = threading.Event()
    thread = threading.Thread(target=node_like, args=(reader, stop), daemon=True)
    thread.start()
    stale, after, live = False, None, False  # after: frames when first stale (hang-up: dropped)
    try:
        time.sleep(0.2)
        if fault == "stall":
            stall_once(server, 0.5)
        else:
            server.disconnect()
            after = reader.stats.frames
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            if reader.stale and not stale:
                stale, after = True, reader.stats.frames
            if after is not None and reader.stats.frames >= after + 100:
                live = not reader.stale  # while it reads: once it stops, it goes stale
                break
            time.sleep(0.001)
    finally:
        stop.set()
        thread.join(timeout=5.0)
    assert after is not None and reader.stats.frames >= after + 100, reader.counters()
    assert reader.reconnects >= 1 and live
    if fault == "stall":
        assert stale and reader.stats.reply_timeouts >= 1


# --- over DDS ------------------------------------------------------------------------------------
@pytest.mark.ros
def test_the_reader_node_refuses_an_axis_the_controller_does_not_list(e727):
    model, server = e727
    args = ["family:=pi_gcs", f"url:={server.url}", "gcs_axis:='7'"]
    proc = subprocess.run(
        [sys.executable, "-m", "piezo_stage.nodes.laser_reader", "--ros-args"]
        + [a for p in args for a in ("-p", p)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert errors == [errors[0]] and "'7' not on the controller" in errors[0], proc.stderr


SET_POINT = 4e-6  # m: ~45 V on the ch. 11 stage of the E-727 emulator


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.realtime  # a 1 kHz loop over TCP: alone, and not on a host too slow for it
def test_the_pi_rig_loop_closes_on_the_controllers_own_sensor(probe):
    """The graph as shipped (E-727 emulator, driver writing SVA, reader polling POS? at 1 kHz,
    the thesis's PID in one process) with a constant reference: the PI sensor's displacement
    settles on it."""
    from piezo_stage.launch import Launcher
    from piezo_stage.nodes.qos import SENSOR_QOS
    from piezo_stage_msgs.msg import Displacement

    from ros_support import spin_until

    samples: list = []
    probe.create_subscription(Displacement, "displacement", samples.append, SENSOR_QOS)
    lines: list[str] = []
    params = [
        "controller.mode:=pid",
        "controller.start_closed:=true",
        "controller.reference_source:=constant",
        f"controller.reference:={SET_POINT}",
        "controller.max_gap:=1.0",
    ]
    with Launcher(
        "pi_rig_loop",
        namespace=NS,
        params=params,
        timeout=30.0,
        sink=lambda name, line, err: lines.append(f"[{name}] {line}"),
    ):
        settled = spin_until(
            probe,
            lambda: sum(1 for s in samples if abs(s.displacement - SET_POINT) < 0.1e-6) > 1000,
            60.0,
        )
        n = len(samples)
        spin_until(probe, lambda: len(samples) > n + 500, 10.0)
    log = "\n".join(lines[-30:])
    assert settled, log
    x = np.array([s.displacement for s in samples[-500:]])
    assert all(s.status == Status.OK for s in samples[-500:]), log
    assert abs(np.median(x) - SET_POINT) < 0.02 * SET_POINT, np.percentile(x, [5, 50, 95])
    assert np.mean(np.abs(x - SET_POINT) < 0.05 * SET_POINT) > 0.9, np.percentile(x, [5, 50, 95])
