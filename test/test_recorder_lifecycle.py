"""The recorder node's services (start paused, ~/start, ~/stop, ~/split), regex selection, and
crash recovery: SIGKILL leaves a bag whose flushed messages `piezo-stage bag reindex` recovers."""

from __future__ import annotations

import signal
import time

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from piezo_stage.bag import bag_info, read_messages
from piezo_stage.bag.files import bag_files
from piezo_stage.cli import main as cli

from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros

KEEP_ALL = QoSProfile(
    depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE
)


class Stage:
    """A voltage publisher in the test process and a view of the recorder's diagnostics."""

    def __init__(self, node, ns: str) -> None:
        from piezo_stage_msgs.msg import Voltage

        self.node, self.ns, self.values = node, ns, {}
        self.Voltage = Voltage
        self.pub = node.create_publisher(Voltage, f"{ns}/voltage", KEEP_ALL)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == f"{self.ns}/recorder":
                self.values = {kv.key: int(kv.value) for kv in status.values if kv.value.isdigit()}

    def count(self, what: str) -> int:
        return self.values.get(f"{self.ns}/voltage {what}", -1)

    def wait_subscribed(self) -> None:
        assert spin_until(self.node, lambda: self.pub.get_subscription_count() >= 1, 15.0)
        spin_until(self.node, lambda: False, 0.2)

    def send(self, first: int, n: int = 10) -> None:
        for k in range(first, first + n):
            self.pub.publish(self.Voltage(voltage=float(k)))

    def wait_count(self, what: str, n: int) -> None:
        assert spin_until(self.node, lambda: self.count(what) == n, 10.0), (what, n, self.values)

    def call(self, service: str) -> Trigger.Response:
        client = self.node.create_client(Trigger, f"{self.ns}/recorder/{service}")
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(self.node, future, timeout_sec=10.0)
        assert future.done()
        return future.result()


def _voltages(path) -> list[float]:
    return [m.voltage for topic, _, m in read_messages(path) if topic.endswith("/voltage")]


def test_start_stop_split_services_and_regex_selection(node, tmp_path):
    bag = tmp_path / "bag"
    stage = Stage(node, "/svc")
    proc = start_node(
        "recorder",
        f"bag:={bag}",
        "start_paused:=true",
        "topic_regex:=^/svc/volt",
        "discovery_period:=0.1",
        "diagnostics_period:=0.1",
        namespace="/svc",
    )
    try:
        stage.wait_subscribed()
        stage.send(0)  # paused: taken, not written
        stage.wait_count("ignored", 10)
        assert stage.call("start").success
        stage.send(100)
        stage.wait_count("written", 10)
        reply = stage.call("split")
        assert reply.success and "bag_1.mcap" in reply.message
        stage.send(200)
        stage.wait_count("written", 20)
        assert stage.call("stop").success
        stage.send(300)
        stage.wait_count("ignored", 20)
        assert stage.count("dropped") == 0
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=15) == 0
    finally:
        out, err = stop(proc)
    assert "Traceback" not in err
    files = bag_files(bag)
    assert [f.name for f in files] == ["bag_0.mcap", "bag_1.mcap"]
    assert _voltages(files[0]) == [float(k) for k in range(100, 110)]
    assert _voltages(files[1]) == [float(k) for k in range(200, 210)]
    info = bag_info(bag)
    assert info["complete"] and set(info["topics"]) == {"/svc/voltage"}  # regex: not /diagnostics


def test_sigkill_leaves_flushed_messages_that_reindex_recovers(node, tmp_path, capsys):
    bag = tmp_path / "bag"
    stage = Stage(node, "/crash")
    proc = start_node(
        "recorder",
        f"bag:={bag}",
        "topics:=[voltage]",
        "flush_period:=0.1",
        "discovery_period:=0.1",
        "diagnostics_period:=0.1",
        namespace="/crash",
    )
    try:
        stage.wait_subscribed()
        stage.send(0, 300)
        stage.wait_count("written", 300)
        time.sleep(0.5)  # several flush periods
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        stop(proc)
    assert not bag_info(bag)["complete"]
    assert cli(["bag", "reindex", str(bag)]) == 0
    assert "300 messages" in capsys.readouterr().out
    info = bag_info(bag)
    assert info["complete"] and info["message_count"] == 300
    assert _voltages(bag) == [float(k) for k in range(300)]


def test_sim_time_stamps_and_qos_readapted_to_a_best_effort_publisher(node, tmp_path):
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock

    bag = tmp_path / "bag"
    stage = Stage(node, "/sim")
    clock = node.create_publisher(Clock, "/clock", 10)
    sim = [1234 * 10**9]  # sim time runs 5x faster than the wall clock

    def advance() -> None:
        sim[0] += 100_000_000
        clock.publish(Clock(clock=Time(sec=sim[0] // 10**9, nanosec=sim[0] % 10**9)))

    tick = node.create_timer(0.02, advance)
    proc = start_node(
        "recorder",
        f"bag:={bag}",
        "topics:=[voltage]",
        "use_sim_time:=true",
        "discovery_period:=0.1",
        "diagnostics_period:=0.1",
        namespace="/sim",
    )
    try:
        stage.wait_subscribed()
        stage.send(0)
        stage.wait_count("written", 10)
        # a best-effort publisher joins: the reliable subscription would not match it
        best_effort = node.create_publisher(
            stage.Voltage,
            "/sim/voltage",
            QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT),
        )
        assert spin_until(node, lambda: best_effort.get_subscription_count() >= 1, 10.0)
        spin_until(node, lambda: False, 0.2)
        for k in range(100, 110):
            best_effort.publish(stage.Voltage(voltage=float(k)))
            spin_until(node, lambda: False, 0.005)
        stage.send(200, 5)  # the reliable publisher is still recorded
        stage.wait_count("written", 25)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=15) == 0
    finally:
        node.destroy_timer(tick)
        _, err = stop(proc)
    assert "Traceback" not in err and "subscription now best effort" in err
    got = [(t, m.voltage) for topic, t, m in read_messages(bag)]
    assert sorted(v for _, v in got) == [
        float(k) for k in [*range(10), *range(100, 110), *range(200, 205)]
    ]
    assert all(1234 * 10**9 < t <= sim[0] for t, _ in got)  # receive time = /clock time
    assert all(t % 100_000_000 == 0 for t, _ in got)
    offered = bag_info(bag)["topics"]["/sim/voltage"]["offered_qos_profiles"]
    assert offered[0]["reliability"] == "reliable"
