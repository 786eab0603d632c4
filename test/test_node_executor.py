"""Guard of the rclpy internals piezo_stage relies on (they are not public API): the
LeanExecutor (piezo_stage/nodes/executor.py) and the overrides given to a node at start
(piezo_stage/nodes/parameters.py). If an rclpy upgrade changes them, this fails here, loudly,
instead of the lockstep graphs stalling or misspelled parameters passing silently."""

from __future__ import annotations

import time

import pytest
import rclpy
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from piezo_stage.nodes.executor import LeanExecutor
from piezo_stage.nodes.parameters import parameter_overrides
from piezo_stage.nodes.qos import COMMAND_QOS

pytestmark = pytest.mark.ros

WAIT_SET_METHODS = (
    "clear_entities",
    "add_subscription",
    "add_timer",
    "add_service",
    "add_guard_condition",
    "wait",
    "get_ready_entities",
)


def test_the_private_rclpy_api_is_still_there():
    from rclpy.impl.implementation_singleton import rclpy_implementation

    missing = [m for m in WAIT_SET_METHODS if not hasattr(rclpy_implementation.WaitSet, m)]
    assert not missing, f"rclpy's WaitSet lost {missing}: update piezo_stage/nodes/executor.py"
    rclpy.init(args=["x", "--ros-args", "-p", "speed:=2.5"])
    try:
        executor = LeanExecutor()
        for name in ("_tasks", "_tasks_lock", "_guard", "_context", "_is_shutdown"):
            assert hasattr(executor, name), f"rclpy's Executor lost {name}: update LeanExecutor"
        node = Node("guard")
        sub = node.create_subscription(String, "chatter", lambda m: None, COMMAND_QOS)
        assert sub._callback_type is sub.CallbackType.MessageOnly, "_callback_type changed"
        assert (
            hasattr(sub.handle, "take_message") and hasattr(sub, "raw") and hasattr(sub, "msg_type")
        )
        timer = node.create_timer(1.0, lambda: None)
        assert hasattr(timer.handle, "is_timer_ready") and hasattr(timer.handle, "call_timer")
        srv = node.create_service(Trigger, "~/t", lambda req, res: res)
        assert hasattr(srv.handle, "service_take_request")
        assert parameter_overrides(node) == {"speed": 2.5}, "Node._parameter_overrides changed"
        node.destroy_node()
    finally:
        rclpy.shutdown()


def test_the_lean_executor_serves_timers_subscriptions_services_and_tasks():
    rclpy.init()
    try:
        node = Node("lean")
        heard: list[str] = []
        ticks: list[int] = []
        node.create_subscription(String, "chatter", lambda m: heard.append(m.data), COMMAND_QOS)
        pub = node.create_publisher(String, "chatter", COMMAND_QOS)
        node.create_timer(0.01, lambda: ticks.append(1))
        node.create_service(
            Trigger, "~/ping", lambda req, res: setattr(res, "success", True) or res
        )
        executor = LeanExecutor()
        executor.add_node(node)
        task_ran: list[bool] = []
        executor.create_task(lambda: task_ran.append(True))
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and not (heard and len(ticks) >= 3 and task_ran):
            pub.publish(String(data="hello"))
            executor.spin_once(timeout_sec=0.05)
        assert heard and heard[0] == "hello"
        assert len(ticks) >= 3 and task_ran == [True]
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.shutdown()
