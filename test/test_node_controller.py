"""The controller node over real DDS: loop close/open services, safety on invalid or stale
sensor samples, run-time gain changes checked against Theorem 4 and the sampled-loop check."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from piezo_stage.bag.types import stamp_seconds
from piezo_stage.nodes.qos import COMMAND_QOS, SENSOR_QOS

from ros_support import call_idempotent, spin_until, start_node, stop

pytestmark = pytest.mark.ros

NS = "/ctl"


def _call(node, srv_type, name, request, timeout=10.0):
    client = node.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=timeout), name
    result = call_idempotent(node, client, request, timeout)
    assert result is not None, name
    return result


def _sample(value, status=0, t=0.0):
    from piezo_stage_msgs.msg import Displacement

    msg = Displacement(displacement=value, status=status)
    msg.header.stamp.sec = int(t)
    msg.header.stamp.nanosec = int(round((t - int(t)) * 1e9))
    return msg


def test_invalid_sample_opens_the_loop_and_holds(node):
    from piezo_stage_msgs.msg import ControllerState, Displacement, Voltage

    proc = start_node(
        "controller",
        "trigger:=sample",
        "hold_voltage:=50.0",
        "reference_source:=constant",
        "reference:=1e-6",
        namespace=NS,
    )
    states: list = []
    cmds: list[float] = []
    diags: list = []
    node.create_subscription(ControllerState, "controller_state", states.append, COMMAND_QOS)
    node.create_subscription(
        Voltage, "voltage_command", lambda m: cmds.append(m.voltage), COMMAND_QOS
    )
    node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    pub = node.create_publisher(Displacement, "displacement", SENSOR_QOS)
    try:
        assert spin_until(node, lambda: node.count_subscribers("displacement") >= 1, 15.0)
        refused = _call(node, Trigger, "controller/close_loop", Trigger.Request())
        assert not refused.success  # no valid sample yet
        t = 1.0
        for _ in range(5):
            pub.publish(_sample(0.0, t=t))
            t += 1e-3
            spin_until(node, lambda: False, 0.02)
        assert _call(node, Trigger, "controller/close_loop", Trigger.Request()).success
        for _ in range(20):
            pub.publish(_sample(0.0, t=t))
            t += 1e-3
            spin_until(node, lambda: False, 0.01)
        assert spin_until(node, lambda: any(s.loop_closed for s in states), 5.0)
        closed_u = [s.u for s in states if s.loop_closed]
        assert closed_u and closed_u[-1] > 0  # x below the 1 um reference: push up
        n_before = len(cmds)
        pub.publish(_sample(float("nan"), status=Displacement.NO_TARGET, t=t))
        assert spin_until(node, lambda: len(cmds) > n_before, 5.0)
        assert cmds[-1] == pytest.approx(50.0)  # hold_voltage
        assert spin_until(
            node,
            lambda: any(
                st.level == DiagnosticStatus.ERROR and "loop opened" in st.message
                for d in diags
                for st in d.status
            ),
            5.0,
        )
        # later valid samples keep the loop open until asked
        pub.publish(_sample(0.0, t=t + 1e-3))
        spin_until(node, lambda: False, 0.3)
        assert not states[-1].loop_closed and states[-1].u == pytest.approx(50.0)
    finally:
        stop(proc)


class _StartClosed:
    """A start_closed controller at 1 kHz (timer, stale after 20 periods) and what it says;
    ``driver``: the probe listens on voltage_command as the amplifier driver would (without a
    listener start_closed holds off)."""

    def __init__(self, node, driver: bool = True) -> None:
        from piezo_stage_msgs.msg import ControllerState, Displacement

        self.node = node
        self.proc = start_node(
            "controller",
            "trigger:=timer",
            "rate_hz:=1000.0",
            "start_closed:=true",
            "max_gap:=0.02",
            namespace=NS,
        )
        self.states: list = []
        self.diags: list = []
        node.create_subscription(
            ControllerState, "controller_state", self.states.append, COMMAND_QOS
        )
        node.create_subscription(DiagnosticArray, "/diagnostics", self.diags.append, 10)
        self.commands: list = []
        self.driver = None
        if driver:
            self.listen()
        self.pub = node.create_publisher(Displacement, "displacement", SENSOR_QOS)
        assert spin_until(
            node,
            lambda: (
                node.count_subscribers("displacement") >= 1
                and node.count_publishers("controller_state") >= 1
            ),
            15.0,
        )

    def listen(self) -> None:
        """Subscribe to voltage_command, as the driver does."""
        from piezo_stage_msgs.msg import Voltage

        self.driver = self.node.create_subscription(
            Voltage, "voltage_command", self.commands.append, COMMAND_QOS
        )

    def closed(self) -> bool:
        """The loop has closed: a closed state, or the ERROR that only a closed loop can give
        (on a busy host the probe may miss the few closed states before a gap opens it)."""
        return any(s.loop_closed for s in self.states) or self.said("loop opened:")

    def said(self, text: str) -> bool:
        return any(text in st.message for d in self.diags for st in d.status)

    def feed_until(self, done, sample, period: float) -> bool:
        """Publish ``sample()`` every ``period`` s until ``done()`` (60 s at most: matching can
        lag the graph on a busy host, and a stalled probe's gaps beyond max_gap make the samples
        stale until they flow again)."""
        import rclpy

        next_at = time.monotonic()
        deadline = next_at + 60.0
        while not done() and time.monotonic() < deadline:
            self.pub.publish(sample())
            # the rest of the period only: the samples stay within max_gap of each other
            next_at = max(next_at + period, time.monotonic())
            while (left := next_at - time.monotonic()) > 0:
                rclpy.spin_once(self.node, timeout_sec=left)
        return done()

    def fresh(self):
        return _sample(0.0, t=self.node.get_clock().now().nanoseconds * 1e-9)


def test_stale_sensor_opens_the_loop(node):
    c = _StartClosed(node)
    try:
        assert c.feed_until(c.closed, c.fresh, 0.002)
        # the sensor goes silent
        assert spin_until(node, lambda: c.said("no sensor sample"), 10.0)
    finally:
        stop(c.proc)


def test_start_closed_waits_out_a_stale_or_invalid_sensor_before_closing(node):
    """An invalid (or stale) sample before start_closed has closed the loop delays the closing
    (WARN), it does not latch a fault that would keep the loop open for good."""
    from piezo_stage_msgs.msg import Displacement

    c = _StartClosed(node)
    try:
        # invalid samples (a sensor that sees no target yet): no closing, a WARN saying why
        no_target = lambda: _sample(math.nan, status=Displacement.NO_TARGET)  # noqa: E731
        assert c.feed_until(lambda: c.said("waiting to close"), no_target, 0.05)
        assert not c.closed()
        # valid samples flow: the loop closes
        assert c.feed_until(c.closed, c.fresh, 0.002)
    finally:
        stop(c.proc)


def test_start_closed_holds_off_until_a_driver_listens_on_voltage_command(node):
    """The separate controller does not close the loop on commands nobody applies: with valid
    samples but no subscriber on voltage_command it waits (WARN saying so); once one listens
    it closes."""
    c = _StartClosed(node, driver=False)
    try:
        assert c.feed_until(lambda: c.said("no subscriber on voltage_command"), c.fresh, 0.002)
        assert not c.closed() and not c.commands
        c.listen()
        assert c.feed_until(c.closed, c.fresh, 0.002)
    finally:
        stop(c.proc)


def test_a_held_off_lockstep_sample_is_stepped_when_offered_again(node):
    """trigger=sample (the lockstep plant's mode): a sample the controller held off on (no
    driver on voltage_command yet) is not marked answered, so the plant's second offer of the
    same step is stepped on; a third offer of a sample already answered is not stepped twice."""
    from piezo_stage.nodes.controller import ControllerNode
    from piezo_stage_msgs.msg import Voltage

    settings = {"trigger": "sample", "reference_source": "constant", "start_closed": True}
    overrides = [Parameter(k, value=v) for k, v in settings.items()]
    controller = ControllerNode(overrides=overrides, namespace=NS)
    commands: list = []
    try:
        step0 = _sample(0.0, t=1.0)
        controller._on_displacement(step0)  # no driver listens: held off, nothing sent
        node.create_subscription(Voltage, "voltage_command", commands.append, COMMAND_QOS)
        assert spin_until(node, lambda: controller._pub_cmd.get_subscription_count() > 0, 15.0)
        assert not commands
        controller._on_displacement(step0)  # the plant offers step 0 again: answered now
        assert spin_until(node, lambda: len(commands) >= 1, 15.0)
        assert stamp_seconds(commands[0].header.stamp) == pytest.approx(1.0)
        controller._on_displacement(step0)  # answered already: not stepped twice
        spin_until(node, lambda: len(commands) >= 2, 0.5)
        assert len(commands) == 1, [stamp_seconds(c.header.stamp) for c in commands]
    finally:
        controller.destroy_node()


def test_unsafe_gain_change_is_refused_with_a_reason(node):
    proc = start_node("controller", namespace=NS)
    try:
        req = SetParameters.Request(parameters=[Parameter("k2", value=100.0).to_parameter_msg()])
        result = _call(node, SetParameters, "controller/set_parameters", req).results[0]
        assert not result.successful and "k2_min" in result.reason
        ok = SetParameters.Request(parameters=[Parameter("k2", value=600.0).to_parameter_msg()])
        assert _call(node, SetParameters, "controller/set_parameters", ok).results[0].successful
        bad_mode = SetParameters.Request(
            parameters=[Parameter("mode", value="bang_bang").to_parameter_msg()]
        )
        result = _call(node, SetParameters, "controller/set_parameters", bad_mode).results[0]
        assert not result.successful and "bang_bang" in result.reason
    finally:
        stop(proc)


@pytest.mark.parametrize(
    "param, reason",
    [
        # 20 kHz with the thesis gains and a one-sample delay: the sampled loop is unstable
        # (docs/design.md §7)
        ("rate_hz:=20000.0", "sampled loop unstable"),
        ("sensor_qos:=fastest", "sensor_qos: 'fastest' is not one of best_effort, reliable"),
    ],
)
def test_bad_start_parameters_exit_with_the_reason(param, reason):
    proc = start_node("controller", param, namespace=NS)
    try:
        assert proc.wait(timeout=20) != 0
    finally:
        out, err = stop(proc)
    assert reason in err


def test_learning_and_tables_that_cannot_serve_exit_with_the_reason(tmp_path):
    """A table made for another period, learning without a feedforward to learn, a period that
    is no whole number of samples: each refused at start (exit 2) with what is wrong."""
    from piezo_stage.control.learning import FeedforwardTable

    table = FeedforwardTable(np.zeros(50), 1000.0).save(tmp_path / "table.json")
    tracking = (
        "compensation:=both",
        "feedforward_model:=ch11_rig.yaml",
        "reference_source:=trajectory",
        "rate_hz:=1000.0",
        "delay_samples:=0",
    )
    for params, reason in (
        ((*tracking, f"feedforward_table:={table}"), "holds 50 samples"),
        (("learn_periods:=5",), "learn_periods needs a feedforward"),
        ((*tracking, "trajectory_frequency:=3.0"), "a whole number"),
    ):
        proc = start_node("controller", *params, namespace=NS)
        try:
            assert proc.wait(timeout=30) == 2
        finally:
            out, err = stop(proc)
        assert reason in err, err[-2000:]


@pytest.mark.parametrize(
    "sensor_qos,reliability", [("best_effort", "BEST_EFFORT"), ("reliable", "RELIABLE")]
)
@pytest.mark.slow
def test_sensor_qos_sets_the_displacement_subscription(node, sensor_qos, reliability):
    """best_effort matches the rig's SensorDataQoS reader; reliable (the lockstep graphs) loses no
    sample of the lockstep plant, so no step waits for the plant's timeout."""
    from rclpy.qos import ReliabilityPolicy

    from piezo_stage.nodes.qos import LOCKSTEP_QOS
    from piezo_stage_msgs.msg import Displacement, Voltage

    proc = start_node(
        "controller",
        "trigger:=sample",
        "rate_hz:=1000.0",
        f"sensor_qos:={sensor_qos}",
        "start_closed:=true",
        "reference_source:=constant",
        namespace=NS,
    )
    try:
        topic = f"{NS}/displacement"
        assert spin_until(node, lambda: node.get_subscriptions_info_by_topic(topic), 20)
        info = node.get_subscriptions_info_by_topic(topic)[0]
        assert info.qos_profile.reliability == getattr(ReliabilityPolicy, reliability)
        commands = []
        node.create_subscription(Voltage, "voltage_command", commands.append, COMMAND_QOS)
        pub = node.create_publisher(
            Displacement, "displacement", LOCKSTEP_QOS if sensor_qos == "reliable" else SENSOR_QOS
        )
        assert spin_until(node, lambda: pub.get_subscription_count() > 0, 20)
        k = [0]

        def feed():
            pub.publish(_sample(1e-6, t=k[0] * 1e-3))
            k[0] += 1
            return len(commands) >= 5

        assert spin_until(node, feed, 20), "the controller did not answer the samples"
    finally:
        stop(proc)
