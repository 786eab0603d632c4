"""Ask the ROS graph which of the awaited topics exist (the launcher's only rclpy module).

The probe lives in its own rclpy Context with no signal handlers, no rosout and no parameter
services, so it neither disturbs a process that already uses rclpy (the demo, experiments) nor
takes over Ctrl-C from the launcher.
"""

from __future__ import annotations

import itertools
import os
from typing import Sequence

import rclpy
from rclpy.context import Context
from rclpy.signals import SignalHandlerOptions

from piezo_stage.launch.graph import TopicWait, resolve_name

_SERIAL = itertools.count()


class TopicProbe:
    def __init__(self) -> None:
        self._context = Context()
        rclpy.init(args=[], context=self._context, signal_handler_options=SignalHandlerOptions.NO)
        try:
            self._node = rclpy.create_node(
                f"piezo_launch_probe_{os.getpid()}_{next(_SERIAL)}",
                context=self._context,
                enable_rosout=False,
                start_parameter_services=False,
            )
        except Exception:
            rclpy.try_shutdown(context=self._context)
            raise

    def missing(self, waits: Sequence[TopicWait], namespace: str) -> list[TopicWait]:
        """The waits not satisfied yet: topic absent, or fewer endpoints than asked."""
        present = {name for name, _types in self._node.get_topic_names_and_types()}
        left = []
        for w in waits:
            topic = resolve_name(w.topic, namespace)
            if (
                topic not in present
                or (w.publishers and self._node.count_publishers(topic) < w.publishers)
                or (w.subscribers and self._node.count_subscribers(topic) < w.subscribers)
            ):
                left.append(w)
        return left

    def close(self) -> None:
        self._node.destroy_node()
        rclpy.try_shutdown(context=self._context)

    def __enter__(self) -> TopicProbe:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
