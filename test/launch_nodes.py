"""Tiny nodes for the launcher tests, run through piezo_stage.nodes.runtime.run like the product's:
``python -m launch_nodes talker|listener --ros-args ...`` (a graph entry ``module: launch_nodes``
with ``args: [talker]``)."""

from __future__ import annotations

import sys
import threading
import time

from rclpy.node import Node
from std_msgs.msg import String

from piezo_stage.nodes.parameters import declare_table
from piezo_stage.nodes.qos import COMMAND_QOS
from piezo_stage.nodes.runtime import run
from piezo_stage.nodes.spec import Param, ParameterTable

#: the talker's parameters (the launcher checks a graph's overrides against it)
PARAMETERS = ParameterTable(
    "talker",
    (
        Param("text", "hello", "what to say"),
        Param(
            "exit_after",
            0.0,
            "seconds after chatter's first subscriber matched before exiting by itself (0: never)",
            "s",
        ),
        Param("fail_code", 0, "exit code when exiting by itself"),
    ),
)


class Talker(Node):
    """Publishes ``"<text> <count>"`` on ``chatter`` at 20 Hz; with exit_after > 0 it ends by
    itself that many seconds after a subscriber matched (discovery takes seconds on a loaded
    host) with exit code `fail_code`."""

    def __init__(self) -> None:
        super().__init__("talker")
        p = declare_table(self, PARAMETERS)
        self.text, exit_after, self.fail_code = p["text"], p["exit_after"], p["fail_code"]
        self.pub = self.create_publisher(String, "chatter", COMMAND_QOS)
        self.count = 0
        self.finished = False  # from the start, as run() asks (nodes.runtime.Finishes)
        self.exit_after = exit_after
        self.exit_timer = None
        self.create_timer(0.05, self.tick)
        print(f"talker {self.get_fully_qualified_name()} says {self.text!r}", flush=True)

    def tick(self) -> None:
        if self.exit_after > 0 and self.exit_timer is None and self.pub.get_subscription_count():
            self.exit_timer = self.create_timer(self.exit_after, self.finish)
        self.count += 1
        self.pub.publish(String(data=f"{self.text} {self.count}"))

    def finish(self) -> None:
        if self.finished:
            return
        self.get_logger().info(f"exiting by itself with code {self.fail_code}")
        self.exit_code = self.fail_code
        self.finished = True

    def on_shutdown(self) -> None:
        print(f"talker {self.get_fully_qualified_name()}: clean shutdown", flush=True)


class Listener(Node):
    """Prints ``heard: <data>`` for the first messages on ``chatter``, then every 20th."""

    def __init__(self) -> None:
        super().__init__("listener")
        self.heard = 0
        self.create_subscription(String, "chatter", self.on_message, COMMAND_QOS)

    def on_message(self, msg: String) -> None:
        self.heard += 1
        if self.heard <= 3 or self.heard % 20 == 0:
            print(f"heard: {msg.data}", flush=True)


class StuckInCallback(Node):
    """Says ``stuck`` from its first timer callback, which never returns (a callback blocked on
    a device or a lock): a stop reaches its process but never its spin loop."""

    def __init__(self) -> None:
        super().__init__("stuck_in_callback")
        self.create_timer(0.05, self.on_tick)

    def on_tick(self) -> None:
        print("stuck", flush=True)
        threading.Event().wait()


class StuckInTeardown(Node):
    """Says ``up`` once spinning; its destruction never returns (a middleware that hangs while
    the process leaves it)."""

    def __init__(self, name: str = "stuck_in_teardown") -> None:
        super().__init__(name)
        self.said = False
        self.create_timer(0.05, self.on_tick)

    def on_tick(self) -> None:
        if not self.said:
            print("up", flush=True)
            self.said = True

    def destroy_node(self) -> None:
        threading.Event().wait()


class StuckAtExit(StuckInTeardown):
    """Says ``up`` once spinning and leaves behind a thread that never ends (a device thread
    nobody joins): its run is over, but the interpreter's exit waits for that thread forever."""

    def __init__(self) -> None:
        super().__init__("stuck_at_exit")
        threading.Thread(target=threading.Event().wait, name="never-joined").start()

    def destroy_node(self) -> None:
        Node.destroy_node(self)


class SlowToSafe(Talker):
    """A talker whose on_shutdown takes :data:`SAFE_AFTER` s (a driver ramping its amplifier to
    the safe voltage at a slow slew rate), then says ``safe``."""

    def on_shutdown(self) -> None:
        time.sleep(SAFE_AFTER)
        print("safe", flush=True)


#: seconds SlowToSafe's on_shutdown takes
SAFE_AFTER = 4.0

ROLES = {
    "talker": Talker,
    "listener": Listener,
    "stuck_in_callback": StuckInCallback,
    "stuck_in_teardown": StuckInTeardown,
    "stuck_at_exit": StuckAtExit,
    "slow_to_safe": SlowToSafe,
}


def main() -> int:
    role = sys.argv[1] if len(sys.argv) > 1 else ""
    if role not in ROLES:
        print(f"usage: launch_nodes {{{'|'.join(ROLES)}}} [--ros-args ...]", file=sys.stderr)
        return 2
    return run(ROLES[role])


if __name__ == "__main__":
    sys.exit(main())
