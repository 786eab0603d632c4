"""The topic probe's child: run by path (``python graph_probe.py TOPIC PUBS SUBS ...``, each
topic resolved), so that it imports rclpy and nothing of the package.

It prints ``missing I J ...`` (indices of the waits not satisfied) each time that set changes,
then ``ready`` once it is empty, and exits; also when its launcher is gone (its parent changed).
No signal handlers (the launcher ends it, not Ctrl-C), no rosout, no parameter services.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from typing import Sequence

POLL_S = 0.1  # between two looks at the ROS graph


def main(argv: Sequence[str]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = os.getppid()
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    waits = [(argv[i], int(argv[i + 1]), int(argv[i + 2])) for i in range(0, len(argv), 3)]
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(
        f"piezo_launch_probe_{os.getpid()}", enable_rosout=False, start_parameter_services=False
    )
    said: list[int] | None = None
    while os.getppid() == parent:
        present = {name for name, _types in node.get_topic_names_and_types()}
        left = [
            i
            for i, (topic, publishers, subscribers) in enumerate(waits)
            if topic not in present
            or (publishers and node.count_publishers(topic) < publishers)
            or (subscribers and node.count_subscribers(topic) < subscribers)
        ]
        if not left:
            print("ready", flush=True)
            break
        if left != said:
            print("missing", *left, flush=True)
            said = left
        time.sleep(POLL_S)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main(sys.argv[1:])
