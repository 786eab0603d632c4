"""Saturation reported by both forms of the controller: the separate node (over DDS) and the
one rig_loop composes (in this process, its publications through a hand-off): every state
says whether its output was clamped, and /diagnostics warns with the share of the steps
saturated since its previous report."""

from __future__ import annotations

import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy

from piezo_stage.nodes.qos import COMMAND_QOS, SENSOR_QOS

from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros

NS = "/sat"
#: 1 mm above the stage: the law asks for thousands of volts, the amplifier gives 100
SETTINGS = {
    "trigger": "sample",
    "reference_source": "constant",
    "reference": 1e-3,
    "u_min": 0.0,
    "u_max": 100.0,
    "start_closed": True,
}


def _sample(t: float):
    from piezo_stage_msgs.msg import Displacement

    msg = Displacement(displacement=0.0, status=Displacement.OK)
    msg.header.stamp.sec = int(t)
    msg.header.stamp.nanosec = int(round((t - int(t)) * 1e9))
    return msg


def test_the_controller_node_reports_saturation_in_its_states_and_on_diagnostics(node):
    from piezo_stage_msgs.msg import ControllerState, Displacement, Voltage

    proc = start_node("controller", *(f"{k}:={v}" for k, v in SETTINGS.items()), namespace=NS)
    states: list = []
    diags: list = []
    node.create_subscription(ControllerState, "controller_state", states.append, COMMAND_QOS)
    # the amplifier's side: start_closed waits for a subscriber on voltage_command
    node.create_subscription(Voltage, "voltage_command", lambda m: None, COMMAND_QOS)
    node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    pub = node.create_publisher(Displacement, "displacement", SENSOR_QOS)

    def warned() -> list[DiagnosticStatus]:
        return [
            s
            for d in diags
            for s in d.status
            if s.level == DiagnosticStatus.WARN and "output saturated on" in s.message
        ]

    try:
        assert spin_until(node, lambda: node.count_subscribers("displacement") >= 1, 15.0)
        t = 1.0
        due = time.monotonic()

        def feed() -> bool:
            # one sample per ms of wall time, as a sensor: fed at every spin (thousands per
            # second into a best-effort queue) the warning did not come in 30 s in 2 runs of 5
            nonlocal t, due
            if time.monotonic() >= due:
                due += 1e-3
                pub.publish(_sample(t))
                t += 1e-3
            return bool(warned()) and any(s.saturated for s in states)

        assert spin_until(node, feed, 30.0), (states[-3:], [d.status for d in diags[-2:]])
        closed = [s for s in states if s.loop_closed]
        assert closed and all(s.u <= 100.0 for s in closed)
        # clamped to u_max whenever saturated (a closing is bumpless: at the held output)
        assert all(s.u == 100.0 for s in closed if s.saturated)
        values = {kv.key: kv.value for kv in warned()[-1].values}
        assert 0.0 < float(values["saturated_share"]) <= 1.0
        assert int(values["saturated_steps"]) >= 1
    finally:
        stop(proc)


def test_the_composed_controller_reports_saturation_in_its_states_and_diagnosis(node):
    """The form rig_loop composes: on_sample() per sensor sample, the states through the
    hand-off; the diagnosis its /diagnostics timer publishes."""
    from piezo_stage.nodes.controller import ControllerNode
    from piezo_stage.nodes.handoff import Handoff
    from piezo_stage_msgs.msg import ControllerState

    overrides = [Parameter(k, value=v) for k, v in SETTINGS.items()]
    # rig_loop's hand-off, publishing at once (what its drain does later)
    controller = ControllerNode(handoff=Handoff(inline=True), overrides=overrides)
    states: list = []
    topic = controller.get_fully_qualified_name().rsplit("/", 1)[0] + "/controller_state"
    deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)  # all 50 kept
    node.create_subscription(ControllerState, topic, states.append, deep)
    try:
        assert spin_until(node, lambda: node.count_publishers(topic) >= 1, 15.0)
        ns = 1_000_000_000
        written = []
        for _ in range(50):
            written.append(controller.on_sample(ns, 0.0, True))
            ns += 1_000_000
        assert written[-1] == 100.0  # the voltage rig_loop writes: clamped
        diagnosis = controller._diagnose()
        assert diagnosis.level == DiagnosticStatus.WARN, diagnosis
        assert "saturated on 98 % of the 50 steps" in diagnosis.message  # all but the first
        assert diagnosis.values["saturated_share"] == pytest.approx(0.98)
        assert spin_until(node, lambda: len(states) >= 50, 15.0), len(states)
        assert [s.saturated for s in states[:50]] == [False] + [True] * 49
        assert controller._diagnose().level == DiagnosticStatus.OK  # no step since
    finally:
        controller.destroy_node()
