"""The lockstep clock's stepping rule, on a stand-in node (no DDS): a step advances once every
axis has answered it; step 0 is offered again until every axis has, the answers given kept, so
that every axis starts on the same sample."""

from __future__ import annotations

import time
from types import SimpleNamespace
from typing import Any

import pytest
from builtin_interfaces.msg import Time

from piezo_stage.nodes import lockstep
from piezo_stage.nodes.lockstep import LockstepClock

pytestmark = pytest.mark.unit


class _Node:
    """What the clock asks of its node: publishers, a timer, parameters and the graph."""

    def __init__(self) -> None:
        self.timers: list[Any] = []
        self.clock: list[Any] = []

    def create_publisher(self, msg_type: Any, topic: str, qos: Any) -> Any:
        return SimpleNamespace(publish=self.clock.append, get_subscription_count=lambda: 1)

    def create_timer(self, period: float, callback: Any) -> None:
        self.timers.append(callback)

    def get_parameter(self, name: str) -> Any:
        return SimpleNamespace(value={"wait_for_commander": True, "wait_for_subscribers": 0}[name])

    def count_publishers(self, topic: str) -> int:
        return 1

    def get_publishers_info_by_topic(self, topic: str) -> list[Any]:
        return [SimpleNamespace(node_name=f"controller_{topic[0]}", node_namespace="/")]

    def get_subscriptions_info_by_topic(self, topic: str) -> list[Any]:
        return [SimpleNamespace(node_name=f"controller_{topic[0]}", node_namespace="/")]

    def get_logger(self) -> Any:
        return SimpleNamespace(warn=lambda *a, **k: None)


def _clock(monkeypatch: pytest.MonkeyPatch) -> tuple[LockstepClock, list[Time], list[int]]:
    monkeypatch.setattr(lockstep, "REOFFER_AFTER", 0.0)  # every watch offers step 0 again
    node = _Node()
    offered: list[Time] = []
    advanced: list[int] = []
    clock = LockstepClock(
        node,
        dt_ns=1_000_000,
        start_ns=0,
        timeout=3600.0,
        command_topics=["x/voltage_command", "y/voltage_command"],
        sample_topics=["x/displacement", "y/displacement"],
        samples=[node.create_publisher(None, "x", None)],
        emit=offered.append,
        advance=lambda: advanced.append(1),
    )
    clock.watch = node.timers[0]  # type: ignore[attr-defined]
    return clock, offered, advanced


def test_step_zero_is_offered_again_until_every_axis_answered_it(monkeypatch):
    clock, offered, advanced = _clock(monkeypatch)
    clock.watch()  # type: ignore[attr-defined]
    assert clock.started and [t.nanosec for t in offered] == [0]
    clock.answered(0, Time())  # x answers; y still holds step 0 (its recorder not there yet)
    time.sleep(0.001)
    clock.watch()  # type: ignore[attr-defined]
    clock.watch()  # type: ignore[attr-defined]
    assert clock.k == 0 and len(offered) == 3 and all(t.nanosec == 0 for t in offered)
    clock.answered(1, Time())  # y answers step 0: x's answer was kept, the clock advances
    assert clock.k == 1 and advanced == [1] and offered[-1].nanosec == 1_000_000


def test_a_later_step_waits_for_every_axis_and_is_offered_once(monkeypatch):
    clock, offered, advanced = _clock(monkeypatch)
    clock.watch()  # type: ignore[attr-defined]
    clock.answered(0, Time())
    clock.answered(1, Time())
    clock.answered(0, Time(nanosec=1_000_000))
    clock.watch()  # type: ignore[attr-defined]
    assert clock.k == 1 and len(offered) == 2  # step 1 is not offered again
    clock.answered(1, Time(nanosec=5_000_000))  # not this step's stamp: no answer
    assert clock.k == 1
    clock.answered(1, Time(nanosec=1_000_000))
    assert clock.k == 2 and len(advanced) == 2
