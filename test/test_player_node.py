"""The player node over real DDS: timing scaled by rate, /clock, topic filter and remapping,
pause/resume services, loop, QoS from the bag, and the recorded bytes played as they are."""

from __future__ import annotations

import signal
import time

import pytest
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from std_srvs.srv import SetBool, Trigger

from piezo_stage.bag import BagWriter, qos, read_raw
from piezo_stage.bag.playback import PlaybackClock, PlaybackError, parse_remaps
from piezo_stage.nodes.player import playback_qos

from ros_support import call_idempotent, fill, msg_class, spin_until, start_node, stop

pytestmark = pytest.mark.ros

NS = "/pl"
N = 51  # messages per stream, 10 ms apart: 0.5 s of bag time
T0 = 1_700_000_000_000_000_000
DT = 10_000_000
KEEP_ALL = QoSProfile(
    depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE
)
BEST_EFFORT = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
LATCHED = QoSProfile(
    depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)


def _data(type_name: str, seed: int) -> bytes:
    """Serialised message (its CDR padding bytes are whatever rclpy leaves: compare with the
    bytes stored in the bag, not with a second serialisation)."""
    return serialize_message(fill(msg_class(type_name)(), seed))


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    """A bag as the recorder writes it: reliable voltage, best-effort displacement, latched
    parameters; receive times 10 ms apart."""
    path = tmp_path_factory.mktemp("play") / "bag"
    with BagWriter(path) as writer:
        writer.add_topic(f"{NS}/voltage", "piezo_stage_msgs/msg/Voltage", [qos.RELIABLE])
        writer.add_topic(
            f"{NS}/displacement", "piezo_stage_msgs/msg/Displacement", [qos.SENSOR_DATA]
        )
        writer.add_topic(
            f"{NS}/bouc_wen_parameters", "piezo_stage_msgs/msg/BoucWenParameters", [qos.LATCHED]
        )
        writer.write(f"{NS}/bouc_wen_parameters", _data("BoucWenParameters", 999), T0)
        for k in range(N):
            writer.write(f"{NS}/voltage", _data("Voltage", k), T0 + k * DT)
            writer.write(
                f"{NS}/displacement", _data("Displacement", 1000 + k), T0 + k * DT + DT // 2
            )
    return path


class Sink:
    """Raw subscriptions: arrival times [s, monotonic] and bytes per topic."""

    def __init__(self, node, topics: dict[str, tuple[str, QoSProfile]]) -> None:
        self.got: dict[str, list[tuple[float, bytes]]] = {t: [] for t in topics}
        self.subscriptions = []
        for topic, (type_name, profile) in topics.items():
            self.subscriptions.append(
                node.create_subscription(
                    msg_class(type_name),
                    topic,
                    lambda data, topic=topic: self.got[topic].append((time.monotonic(), data)),
                    profile,
                    raw=True,
                )
            )

    def close(self, node) -> None:
        for sub in self.subscriptions:
            node.destroy_subscription(sub)

    def count(self, topic: str) -> int:
        return len(self.got[topic])


def same_bytes(played: bytes, recorded: bytes) -> bool:
    """Equal, up to the zero padding to 4 bytes Fast DDS adds between processes."""
    return (
        played[: len(recorded)] == recorded
        and len(played) - len(recorded) < 4
        and not any(played[len(recorded) :])
    )


def _sink_all(node) -> Sink:
    return Sink(
        node,
        {
            f"{NS}/voltage": ("Voltage", KEEP_ALL),
            f"{NS}/displacement": ("Displacement", BEST_EFFORT),
            f"{NS}/bouc_wen_parameters": ("BoucWenParameters", LATCHED),
        },
    )


def _play(node, sink: Sink, bag, *params: str) -> tuple[int, str]:
    proc = start_node("player", f"bag:={bag}", "wait_for_subscribers:=1", *params, namespace=NS)
    try:
        assert spin_until(node, lambda: proc.poll() is not None, 30.0)
        spin_until(node, lambda: False, 0.2)
    finally:
        _, err = stop(proc)
    return proc.returncode, err


@pytest.mark.slow
def test_rate_scales_timing_and_recorded_bytes_are_played_as_they_are(node, bag):
    """The bytes as recorded, at rate 1 and 5; the rate from the player's /clock, published
    every TICK of wall time with the bag time then. Each tick is due TICK after the one before
    and no earlier than the one before was published, so ticks j apart were published at least
    (j - 1)·TICK apart, and their bag times differ by at least rate·(j - 1)·TICK; ticks lost on
    the way only widen the true distance. Stamps only, no wall clock here: a busy host makes
    ticks late, which only widens them more."""
    recorded: dict[str, list[bytes]] = {}
    for topic, _, _, data in read_raw(bag):
        recorded.setdefault(topic, []).append(bytes(data))
    tick_ns = 1_000_000  # clock_rate_hz 1000
    for rate in (1.0, 5.0):
        sink = _sink_all(node)
        clocks: list[int] = []
        clock_sub = node.create_subscription(
            Clock,
            "/clock",
            lambda m, clocks=clocks: clocks.append(m.clock.sec * 10**9 + m.clock.nanosec),
            KEEP_ALL,
        )
        code, err = _play(
            node, sink, bag, f"rate:={rate}", "publish_clock:=true", "clock_rate_hz:=1000.0"
        )
        assert code == 0, err
        assert sink.count(f"{NS}/voltage") == N
        voltages = [data for _, data in sink.got[f"{NS}/voltage"]]
        assert all(same_bytes(v, r) for v, r in zip(voltages, recorded[f"{NS}/voltage"]))
        got = [d for _, d in sink.got[f"{NS}/displacement"]]
        assert len(got) >= 0.9 * N  # best effort, as recorded
        index = [
            next(j for j, r in enumerate(recorded[f"{NS}/displacement"]) if same_bytes(d, r))
            for d in got
        ]
        assert index == sorted(set(index))
        latched = [d for _, d in sink.got[f"{NS}/bouc_wen_parameters"]]
        assert len(latched) == 1 and same_bytes(
            latched[0], recorded[f"{NS}/bouc_wen_parameters"][0]
        )
        sink.close(node)
        node.destroy_subscription(clock_sub)
        # 0.5 s of bag time: ~500 ticks at rate 1, ~100 at rate 5 (the first few may come
        # before this reader is matched)
        assert len(clocks) >= 3 and clocks == sorted(clocks), clocks
        assert T0 <= clocks[0]
        short = [
            (j, c - clocks[0])
            for j, c in enumerate(clocks)
            if c - clocks[0] < rate * (j - 1) * tick_ns - 1000  # 1 µs: int ns rounding
        ]
        assert not short, (rate, short[:5])


def test_clock_topic_filter_and_remap(node, bag):
    sink = Sink(
        node,
        {
            "/moved/voltage": ("Voltage", KEEP_ALL),
            f"{NS}/voltage": ("Voltage", KEEP_ALL),
            f"{NS}/displacement": ("Displacement", BEST_EFFORT),
        },
    )
    clocks: list[int] = []
    node.create_subscription(
        Clock, "/clock", lambda m: clocks.append(m.clock.sec * 10**9 + m.clock.nanosec), KEEP_ALL
    )
    code, err = _play(
        node,
        sink,
        bag,
        "publish_clock:=true",
        "clock_rate_hz:=100.0",
        f"topics:=['{NS}/voltage']",
        f"remap:=['{NS}/voltage:=/moved/voltage']",
    )
    assert code == 0, err
    assert sink.count("/moved/voltage") == N
    assert sink.count(f"{NS}/voltage") == 0 and sink.count(f"{NS}/displacement") == 0
    assert len(clocks) >= 10  # ~50 ticks in 0.5 s
    assert clocks == sorted(clocks)
    assert T0 <= clocks[0] and clocks[-1] <= T0 + N * DT + 20 * DT


def _call(node, srv_type, name: str, request) -> object:
    client = node.create_client(srv_type, f"{NS}/player/{name}")
    assert client.wait_for_service(timeout_sec=10.0)
    response = call_idempotent(node, client, request)  # pause, resume: the same twice
    assert response is not None and response.success
    return response


def test_pause_resume_services(node, bag):
    sink = _sink_all(node)
    voltage = f"{NS}/voltage"
    proc = start_node("player", f"bag:={bag}", "start_paused:=true", "rate:=0.5", namespace=NS)
    try:
        assert spin_until(node, lambda: node.count_publishers(voltage) >= 1, 15.0)
        spin_until(node, lambda: False, 0.5)
        assert sink.count(voltage) == 0  # paused from the start
        _call(node, Trigger, "resume", Trigger.Request())
        assert spin_until(node, lambda: sink.count(voltage) >= 10, 10.0)
        _call(node, Trigger, "pause", Trigger.Request())
        spin_until(node, lambda: False, 0.1)
        held = sink.count(voltage)
        spin_until(node, lambda: False, 0.4)  # 20 messages' worth at rate 0.5
        assert sink.count(voltage) == held < N
        _call(node, SetBool, "set_paused", SetBool.Request(data=False))
        assert spin_until(node, lambda: proc.poll() is not None, 15.0)
        assert proc.returncode == 0
        assert sink.count(voltage) == N
    finally:
        _, err = stop(proc)
    assert "Traceback" not in err


def test_a_parameter_set_on_a_playing_node_is_answered(node, bag):
    """The player keeps rclpy's ROS clock (Node._clock), which stamps parameter events: a
    set_parameters request (use_sim_time, as `ros2 param set` sends it) succeeds before and
    during playback, and the node stays up."""
    from rcl_interfaces.msg import Parameter as ParameterMsg
    from rcl_interfaces.msg import ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    proc = start_node("player", f"bag:={bag}", "start_paused:=true", "rate:=0.5", namespace=NS)
    try:
        client = node.create_client(SetParameters, f"{NS}/player/set_parameters")
        assert client.wait_for_service(timeout_sec=15.0)
        for resume in (False, True):  # paused (no playback clock yet), then playing
            if resume:
                _call(node, Trigger, "resume", Trigger.Request())
            value = ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=resume)
            request = SetParameters.Request(
                parameters=[ParameterMsg(name="use_sim_time", value=value)]
            )
            response = call_idempotent(node, client, request)
            assert response is not None, "the player did not answer set_parameters"
            assert response.results[0].successful, response.results[0].reason
        assert proc.poll() is None or proc.returncode == 0
    finally:
        _, err = stop(proc)
    assert "Traceback" not in err, err


def test_loop_replays_until_stopped(node, bag):
    """Every loop plays the bag's messages in order; the first may lack a few at its start (the
    player's writer can match before this reader has: DDS discovery is not symmetric)."""
    recorded = [d for _, _, _, d in read_raw(bag, f"{NS}/voltage")]
    sink = _sink_all(node)
    proc = start_node(
        "player",
        f"bag:={bag}",
        "loop:=true",
        "rate:=0.0",
        "wait_for_subscribers:=1",
        f"topics:=['{NS}/voltage']",
        namespace=NS,
    )
    try:
        assert spin_until(node, lambda: sink.count(f"{NS}/voltage") >= 3 * N, 20.0)
        assert proc.poll() is None  # looping: does not exit by itself
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    finally:
        _, err = stop(proc)
    assert "Traceback" not in err
    got = [d for _, d in sink.got[f"{NS}/voltage"]]
    end = got.index(recorded[-1]) + 1  # the first loop's end
    assert got[:end] == recorded[N - end :] and end >= N // 2
    assert got[end : end + N] == recorded and got[end + N : end + 2 * N] == recorded


def test_unknown_topic_in_the_filter_is_refused(bag):
    proc = start_node("player", f"bag:={bag}", "topics:=['/not/there']", namespace=NS)
    try:
        assert proc.wait(timeout=20) == 1
    finally:
        _, err = stop(proc)
    assert "/not/there" in err and "not in" in err


# -- pure parts ---------------------------------------------------------------------------------
def test_playback_clock_scales_and_freezes_while_paused():
    clock = PlaybackClock(T0, rate=2.0, paused=True)
    assert clock.due(T0) is None and clock.now(5.0) == T0
    clock.resume(10.0)
    assert clock.now(10.5) == T0 + 1_000_000_000  # 0.5 s wall at rate 2
    assert clock.due(T0 + 3_000_000_000) == pytest.approx(11.5)
    clock.pause(11.0)
    assert clock.now(20.0) == T0 + 2_000_000_000  # frozen
    clock.resume(30.0)
    assert clock.due(T0 + 3_000_000_000) == pytest.approx(30.5)
    with pytest.raises(PlaybackError, match="rate > 0"):
        PlaybackClock(T0, rate=0.0)


def test_remaps_and_playback_qos():
    assert parse_remaps(["/a:=/b", "c := d"]) == {"/a": "/b", "c": "d"}
    with pytest.raises(PlaybackError, match="from:=to"):
        parse_remaps(["/a=/b"])
    sensor = playback_qos([qos.SENSOR_DATA], 100)
    assert sensor.reliability == ReliabilityPolicy.BEST_EFFORT and sensor.depth == 100
    latched = playback_qos([qos.LATCHED, qos.LATCHED], 100)
    assert latched.durability == DurabilityPolicy.TRANSIENT_LOCAL and latched.depth == 1
    mixed = playback_qos([qos.RELIABLE, qos.SENSOR_DATA], 10)
    assert mixed.reliability == ReliabilityPolicy.BEST_EFFORT
    assert playback_qos([], 10).reliability == ReliabilityPolicy.RELIABLE
