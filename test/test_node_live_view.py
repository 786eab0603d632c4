"""live_view over real DDS and a real WebSocket client (``websockets``, foxglove.sdk.v1): channels
advertised with encoding cdr and their ros2msg schemas, subscribed messages decoding with the
advertised schema to the values published, the rate cap, unsubscribing, channels going with
their topics, latched topics reaching a late client, an abrupt client leaving the graph alone,
and `piezo-stage launch sim_closed_loop --view` serving the loop's topics."""

from __future__ import annotations

import contextlib
import os
import socket
import time

import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from piezo_stage.nodes.errors import RosParameterError
from piezo_stage.nodes.live_view import RateGate, parse_topic_rates

from foxglove_client import FoxgloveClient, decoder
from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def ns() -> str:
    return f"/view_{os.getpid()}_{time.monotonic_ns() % 10**9}"


# ---------------------------------------------------------------------------------- units
@given(rate=st.floats(0.5, 5000.0), gaps=st.lists(st.integers(0, 10**8), min_size=1, max_size=300))
@example(rate=100.0, gaps=[0] * 50)
@example(rate=1000.0, gaps=[10**6] * 300)
@example(rate=1e9 / 1000001, gaps=[0, 500000, 1000001])  # 3 pass over 1.5 periods: the cap's case
def test_the_rate_gate_never_bursts_nor_exceeds_its_rate(rate, gaps):
    """Over any stream of receive times the first message passes, no two that pass are less
    than half a period P apart, and over a span S from the first to the last that pass at most
    2 + (S - P // 2) // P pass.

    The cap: after the first pass at t1 the next slot is t1 + P // 2, and each pass moves the
    slot on by at least P, so the k-th pass (k >= 2) comes at or after t1 + P // 2 + (k - 2)·P.
    It is reached (3 pass over S = 1.5000005 P in the example above), so "at most S / P + 1.5"
    does not hold."""
    gate = RateGate(rate)
    t, passed = 10**12, []
    for gap in gaps:
        t += gap
        if gate(t):
            passed.append(t)
    assert passed and passed[0] == 10**12 + gaps[0]
    period = round(1e9 / rate)
    assert all(b - a >= period // 2 for a, b in zip(passed, passed[1:]))
    assert len(passed) <= 2 + (passed[-1] - passed[0] - period // 2) // period


def test_rate_gate_zero_passes_everything_and_a_steady_stream_is_thinned_evenly():
    everything = RateGate(0.0)
    assert all(everything(t) for t in [5, 5, 5, 6])
    gate = RateGate(100.0)
    kept = [t for t in range(0, 10**9, 10**6) if gate(t)]  # 1 kHz for 1 s
    assert len(kept) == 100
    assert {b - a for a, b in zip(kept, kept[1:])} == {10**7}


def test_topic_rates_parse_or_say_what_is_wrong():
    resolve = lambda t: t if t.startswith("/") else "/piezo/" + t  # noqa: E731
    assert parse_topic_rates(["displacement=500", "/diagnostics=0"], resolve) == {
        "/piezo/displacement": 500.0,
        "/diagnostics": 0.0,
    }
    for bad in ["displacement", "=5", "x=fast", "x=-1", "x=nan", "x=1e7"]:
        with pytest.raises(RosParameterError, match="TOPIC=HZ"):
            parse_topic_rates([bad], resolve)


# ---------------------------------------------------------------------------------- node
class View:
    def __init__(self, namespace: str, *params: str) -> None:
        self.port = free_port()
        self.proc = start_node(
            "live_view", f"port:={self.port}", "discovery_period:=0.1", *params, namespace=namespace
        )
        self.url = f"ws://127.0.0.1:{self.port}"
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    return
            except OSError:
                assert self.proc.poll() is None, stop(self.proc)
                time.sleep(0.1)
        raise AssertionError(stop(self.proc))


@contextlib.contextmanager
def watched(space: str, *params: str):
    """A live view of ``space`` and a client connected to it; the view stops after, exit 0."""
    view = View(space, *params)
    client = None
    try:
        client = FoxgloveClient(view.url)
        yield client
    finally:
        if client is not None:
            client.close()
        _, err = stop(view.proc)
    assert view.proc.returncode == 0, err


def publish_for(node, pub, make, seconds: float, rate: float) -> list:
    sent, k, t_end = [], 0, time.monotonic() + seconds
    while time.monotonic() < t_end:
        msg = make(k)
        pub.publish(msg)
        sent.append(msg)
        k += 1
        time.sleep(1.0 / rate)
    return sent


def displacement(k: int):
    from piezo_stage_msgs.msg import Displacement

    msg = Displacement()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1000 + k, 7 * k
    msg.displacement = 1e-6 * k
    return msg


def test_channels_schemas_values_rate_cap_and_unsubscribing(node):
    from piezo_stage_msgs.msg import Displacement

    space = ns()
    pub = node.create_publisher(Displacement, f"{space}/displacement", 10)
    other = node.create_publisher(Displacement, "/elsewhere/displacement", 10)
    with watched(space, "max_rate_hz:=40.0") as client:
        assert client.subprotocol == "foxglove.sdk.v1"
        assert client.wait(lambda: client.channel(f"{space}/displacement") is not None), (
            client.channels
        )
        channel = client.channel(f"{space}/displacement")
        assert channel["encoding"] == "cdr" and channel["schemaEncoding"] == "ros2msg"
        assert channel["schemaName"] == "piezo_stage_msgs/msg/Displacement"
        assert "MSG: std_msgs/Header" in channel["schema"]  # the dependencies come along
        assert client.channel("/elsewhere/displacement") is None  # another namespace's
        decode = decoder(channel)
        sub = client.subscribe(channel["id"])
        time.sleep(0.5)  # the view subscribes on the client's request
        sent = publish_for(node, pub, displacement, 2.0, 500.0)
        assert client.wait(lambda: len(client.received(sub)) >= 20)
        got = client.received(sub)
        values = [decode(m.payload) for m in got]
        by_value = {round(m.displacement * 1e6): m for m in sent}
        for v in values:  # each is one message published, byte for byte what the topic had
            k = round(v.displacement * 1e6)
            assert v.displacement == by_value[k].displacement
            assert (v.header.stamp.sec, v.header.stamp.nanosec) == (1000 + k, 7 * k)
        span = (got[-1].log_time - got[0].log_time) * 1e-9
        # 500 msg/s published, 40 msg/s asked: even thinning, at most one per 25 ms
        assert len(got) <= 40 * span + 2 and len(got) >= 20, (len(got), span)
        client.unsubscribe(sub)
        time.sleep(0.5)
        before = len(client.received(sub))
        publish_for(node, pub, displacement, 1.0, 200.0)
        time.sleep(0.3)
        assert len(client.received(sub)) == before
        node.destroy_publisher(pub)  # the topic goes: so does its channel
        assert client.wait(lambda: channel["id"] in client.unadvertised, 10.0), client.channels
    node.destroy_publisher(other)


def test_every_nodes_diagnostics_reach_the_app_whatever_the_rate_cap(node):
    """/diagnostics gathers every node's reports: bursts of three reports every 0.2 s, with
    max_rate_hz 1, reach the app each of them (5 of each within a generous timeout; a cap over
    the topic kept only the first report of each burst: a graph's later nodes never showed)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    space = ns()
    names = [f"{space}/node_{k}" for k in range(3)]
    pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
    try:
        with watched(space, "max_rate_hz:=1.0") as client:
            assert client.wait(lambda: client.channel("/diagnostics") is not None), client.channels
            channel = client.channel("/diagnostics")
            decode = decoder(channel)
            sub = client.subscribe(channel["id"])

            def seen() -> dict[str, int]:
                got = [s.name for m in client.received(sub) for s in decode(m.payload).status]
                return {name: got.count(name) for name in names}

            deadline = time.monotonic() + 30.0  # the view subscribes on the client's request
            while min(seen().values()) < 5 and time.monotonic() < deadline:
                for name in names:
                    pub.publish(DiagnosticArray(status=[DiagnosticStatus(name=name)]))
                time.sleep(0.2)
            assert min(seen().values()) >= 5, seen()
    finally:
        node.destroy_publisher(pub)


def test_a_latched_topic_reaches_a_late_client_and_a_vanished_client_disturbs_nothing(node):
    from piezo_stage_msgs.msg import Displacement

    space = ns()
    latched = QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
    )
    pub_latched = node.create_publisher(Displacement, f"{space}/parameters_like", latched)
    pub_latched.publish(displacement(42))
    pub = node.create_publisher(Displacement, f"{space}/displacement", 10)
    view = View(space)
    try:
        rude = FoxgloveClient(view.url)
        assert rude.wait(lambda: rude.channel(f"{space}/displacement") is not None)
        rude.subscribe(rude.channel(f"{space}/displacement")["id"])
        time.sleep(0.3)
        publish_for(node, pub, displacement, 0.3, 200.0)
        rude.drop()  # no closing handshake
        polite = FoxgloveClient(view.url)
        assert polite.wait(lambda: polite.channel(f"{space}/parameters_like") is not None)
        ch = polite.channel(f"{space}/parameters_like")
        sub = polite.subscribe(ch["id"])
        assert polite.wait(lambda: polite.received(sub), 10.0)
        assert decoder(ch)(polite.received(sub)[0].payload).displacement == 42e-6
        sub2 = polite.subscribe(polite.channel(f"{space}/displacement")["id"])
        time.sleep(0.3)
        publish_for(node, pub, displacement, 0.5, 200.0)
        assert polite.wait(lambda: len(polite.received(sub2)) >= 5)
        polite.close()
        assert view.proc.poll() is None
    finally:
        out, err = stop(view.proc)
        node.destroy_publisher(pub)
        node.destroy_publisher(pub_latched)
    assert view.proc.returncode == 0, err


@pytest.mark.parametrize(
    "param, why",
    [
        ("topic_rates:=['displacement']", "TOPIC=HZ"),
        ("max_rate_hz:=-1.0", "max_rate_hz"),
        ("no_such:=1", "no_such"),
    ],
)
def test_bad_parameters_exit_2_with_one_line(param, why):
    proc = start_node("live_view", f"port:={free_port()}", param, namespace=ns())
    out, err = stop(proc, timeout=30.0) if proc.wait(timeout=30.0) is None else proc.communicate()
    assert proc.returncode == 2, err
    assert why in err


def test_a_busy_port_is_refused_with_exit_2():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        proc = start_node("live_view", f"port:={s.getsockname()[1]}", namespace=ns())
        proc.wait(timeout=30.0)
        _, err = proc.communicate()
    assert proc.returncode == 2 and "cannot serve on 127.0.0.1" in err, err


def loop_runs(node, topic: str, samples: int, timeout: float) -> bool:
    """Whether ``samples`` Displacement messages on ``topic`` reach the probe ``node`` within
    ``timeout`` s: the lockstep loop is stepping."""
    from piezo_stage.nodes.qos import SENSOR_QOS
    from piezo_stage_msgs.msg import Displacement

    got: list = []
    subscription = node.create_subscription(Displacement, topic, got.append, SENSOR_QOS)
    try:
        return spin_until(node, lambda: len(got) >= samples, timeout)
    finally:
        node.destroy_subscription(subscription)


def test_launch_sim_closed_loop_with_view_serves_the_loop(node, tmp_path):
    """`piezo-stage launch sim_closed_loop --view`: displacement, voltage_command,
    controller_state and /diagnostics reach a client (30 messages of each loop topic, 3 of
    /diagnostics, within a generous timeout) and decode with the advertised schemas; the loop's
    topics come thinned to the view's cap (20 msg/s here: the lockstep loop runs faster, ~70
    samples/s of wall time on a busy host), by the view's own stamps (RateGate's cap, see the
    property test above)."""
    from piezo_stage.launch import Launcher
    from piezo_stage.launch.graph import load_graph

    port = free_port()
    space = ns()
    graph = load_graph("sim_closed_loop").with_node(
        {"executable": "live_view", "overrides": {"port": port, "max_rate_hz": 20.0}}
    )
    lines: list[str] = []
    launcher = Launcher(graph, namespace=space, sink=lambda name, line, *_: lines.append(line))
    wanted = [
        f"{space}/displacement",
        f"{space}/voltage_command",
        f"{space}/controller_state",
        "/diagnostics",
    ]
    launcher.start()
    client = None
    try:
        launcher.wait_ready(timeout=60.0)
        # the loop stepping first: its first steps compile the plant's kernels when numba's
        # cache of them is cold (a fresh clone, an edited model file: 40-60 s on a 2-core host,
        # 0.4 s cached); the waits below then see a running loop
        assert loop_runs(node, f"{space}/displacement", 10, 600.0), "\n".join(lines[-30:])
        deadline = time.monotonic() + 30.0
        while client is None and time.monotonic() < deadline:
            try:
                client = FoxgloveClient(f"ws://127.0.0.1:{port}")
            except OSError:
                time.sleep(0.2)
        assert client is not None, "\n".join(lines[-30:])
        assert client.wait(lambda: all(client.channel(t) for t in wanted), 30.0), (
            client.channels,
            "\n".join(lines[-30:]),
        )
        subs = {
            t: (client.subscribe(client.channel(t)["id"]), decoder(client.channel(t)))
            for t in wanted
        }
        enough = {topic: 30 for topic in wanted[:3]} | {"/diagnostics": 3}

        decode_diag = subs["/diagnostics"][1]

        def counts() -> dict[str, int]:
            return {topic: len(client.received(subs[topic][0])) for topic in wanted}

        def diag_names() -> set[str]:
            return {
                s.name
                for m in client.received(subs["/diagnostics"][0])
                for s in decode_diag(m.payload).status
            }

        # every node's status at 1 Hz (wall time), not thinned: the controller's arrives
        assert client.wait(
            lambda: (
                all(counts()[t] >= n for t, n in enough.items())
                and f"{space}/controller" in diag_names()
            ),
            60.0,
        ), (counts(), diag_names(), "\n".join(lines[-30:]))
        for sub, decode in subs.values():
            for m in client.received(sub)[-5:]:
                decode(m.payload)  # decodes with the advertised schema
        period = round(1e9 / 20.0)  # max_rate_hz
        for topic in wanted[:3]:
            stamps = [m.log_time for m in client.received(subs[topic][0])]
            assert stamps == sorted(stamps), topic
            assert len(stamps) <= 2 + (stamps[-1] - stamps[0] - period // 2) // period, topic
        assert len(diag_names()) >= 2, diag_names()
        state = subs[f"{space}/controller_state"][1](
            client.received(subs[f"{space}/controller_state"][0])[-1].payload
        )
        controller = next(n for n in graph.nodes if n.name == "controller")
        assert state.mode == controller.overrides["mode"]  # the graph's law
    finally:
        if client is not None:
            client.close()
        launcher.stop()
