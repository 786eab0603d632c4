"""The environment works: messages cross real DDS between processes, rosbags reads rclpy's CDR
byte for byte, and test runs are isolated by ROS domain."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message

from ros_support import (
    MSG_TYPES,
    ROOT,
    call_idempotent,
    fill,
    msg_class,
    spawn_python,
    spin_until,
    stop,
    to_plain,
)

pytestmark = pytest.mark.ros

ECHO = r"""
import sys, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
import piezo_stage_msgs.msg as m
from std_srvs.srv import Trigger
sys.path.insert(0, sys.argv[1])
from ros_support import fill
rclpy.init()
node = rclpy.create_node("echo", namespace="probe")
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
keep = []
for name in sys.argv[2].split(","):
    cls = getattr(m, name)
    pub = node.create_publisher(cls, "out_" + name, qos)
    keep.append(node.create_subscription(cls, "in_" + name, lambda msg, p=pub: p.publish(msg), qos))
def identify(req, resp):
    resp.success = True
    resp.message = "echo"
    return resp
node.create_service(Trigger, "identify", identify)
print("ready", flush=True)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
    pass
"""


@pytest.fixture()
def ros_node():
    rclpy.init()
    node = rclpy.create_node("tester", namespace="probe")
    yield node
    node.destroy_node()
    rclpy.shutdown()


def test_every_message_round_trips_between_processes(ros_node):
    from std_srvs.srv import Trigger

    echo = spawn_python(ECHO, str(Path(__file__).parent), ",".join(MSG_TYPES))
    try:
        assert echo.stdout.readline().strip() == "ready", stop(echo)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        received: dict[str, object] = {}
        pubs = {}
        for i, name in enumerate(MSG_TYPES):
            cls = msg_class(name)
            pubs[name] = (
                ros_node.create_publisher(cls, "in_" + name, qos),
                fill(cls(), seed=10 * i),
            )
            ros_node.create_subscription(
                cls, "out_" + name, lambda msg, n=name: received.setdefault(n, msg), qos
            )

        # publish until every echo is back (discovery takes a moment)
        def all_back() -> bool:
            for name, (pub, msg) in pubs.items():
                if name not in received:
                    pub.publish(msg)
            return len(received) == len(MSG_TYPES)

        assert spin_until(ros_node, all_back, timeout=20.0), (
            f"missing: {set(MSG_TYPES) - set(received)}"
        )
        for name, (_, sent) in pubs.items():
            assert to_plain(received[name]) == to_plain(sent), name
            assert received[name] is not sent

        client = ros_node.create_client(Trigger, "identify")  # the nodes' services are std_srvs
        assert client.wait_for_service(timeout_sec=10.0)
        resp = call_idempotent(ros_node, client, Trigger.Request(), timeout=10.0)
        assert resp is not None and resp.success and resp.message == "echo"
    finally:
        stop(echo)


def _rosbags_typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted((ROOT / "piezo_stage_msgs" / "msg").glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"piezo_stage_msgs/msg/{path.stem}"))
    store.register(types)
    return store


@pytest.mark.parametrize("name", MSG_TYPES)
def test_rosbags_reads_rclpy_cdr_byte_for_byte(name):
    store = _rosbags_typestore()
    sent = fill(msg_class(name)(), seed=3)
    data = serialize_message(sent)
    typename = f"piezo_stage_msgs/msg/{name}"
    decoded = store.deserialize_cdr(data, typename)
    assert to_plain(decoded) == to_plain(sent)
    # Same bytes back from rosbags, except CDR alignment padding: Fast CDR leaves padding bytes
    # uninitialised (they hold whatever was in the buffer), rosbags writes zeros there.
    again = bytes(store.serialize_cdr(decoded, typename))
    data = bytes(data)
    assert len(again) == len(data)
    differing = [i for i in range(len(data)) if again[i] != data[i]]
    assert all(again[i] == 0 for i in differing)
    assert len(differing) < len(data) // 4
    assert to_plain(deserialize_message(again, msg_class(name))) == to_plain(sent)


def test_status_constants_match_the_contract():
    d = msg_class("Displacement")
    assert (d.OK, d.NO_TARGET, d.TOO_CLOSE, d.TOO_FAR, d.INVALID) == (0, 1, 2, 3, 4)
    c = msg_class("ControllerState")
    assert (c.MODE_PID, c.MODE_PID_SINE, c.MODE_PID_TV) == ("pid", "pid_sine", "pid_tv")


TALKER = r"""
import sys, time, rclpy
from piezo_stage_msgs.msg import Voltage
rclpy.init()
node = rclpy.create_node("talker")
pub = node.create_publisher(Voltage, "/probe/isolation", 10)
end = time.monotonic() + float(sys.argv[1])
while time.monotonic() < end:
    pub.publish(Voltage(voltage=float(sys.argv[2])))
    time.sleep(0.05)
"""


def test_ros_domain_isolation(ros_node):
    from piezo_stage.launch.domain import (
        DOMAIN_LOCK_DIR,
    )  # the lock files held by running test sessions

    own = int(os.environ["ROS_DOMAIN_ID"])
    assert 1 <= own <= 100 and (DOMAIN_LOCK_DIR / f"{own}.lock").exists()
    other = 1 + own % 100
    got: list[float] = []
    ros_node.create_subscription(
        msg_class("Voltage"), "/probe/isolation", lambda m: got.append(m.voltage), 10
    )
    env_backup = os.environ["ROS_DOMAIN_ID"]
    os.environ["ROS_DOMAIN_ID"] = str(other)
    foreign = spawn_python(TALKER, "4", "-1.0")
    os.environ["ROS_DOMAIN_ID"] = env_backup
    try:
        spin_until(ros_node, lambda: False, timeout=3.0)
        assert got == [], "a talker in another ROS domain was heard"
    finally:
        stop(foreign)
    same = spawn_python(TALKER, "6", "2.5")
    try:
        assert spin_until(ros_node, lambda: 2.5 in got, timeout=10.0), (
            "a talker in the same domain was not heard"
        )
    finally:
        stop(same)
