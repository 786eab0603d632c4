"""The lockstep clock of a simulated stage of N >= 1 axes (the ``plant`` node).

The node owns ``/clock``. At step k it publishes ``/clock`` = t_k and the samples at t_k, then
waits for every axis's ``voltage_command`` stamped t_k (any publisher: the excitation's clock
trigger, the controller's sample trigger) and only then integrates to t_k + 1/rate_hz. After
``lockstep_timeout`` wall seconds without them it advances with the held commands and counts a
late step. Identical inputs give identical samples, as fast as the graph can go. Stepping
starts once every axis's ``voltage_command`` has a publisher (``wait_for_commander``) and the
sample publishers have ``wait_for_subscribers`` matched subscribers each. Step 0 waits for
every axis: it is offered again every ``REOFFER_AFTER`` until each has answered (a commander
may have just appeared, or hold step 0 until its own recorder listens), the answers given
kept, so that every axis starts on the same sample. Commanders in the plant's own process (the
``sim_loop`` and ``sim_excitation`` hosts) are asked by direct calls instead
(:meth:`LockstepClock.drive`): the same steps in the same order, without a message round trip
per step.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Sequence

from builtin_interfaces.msg import Time
from rosgraph_msgs.msg import Clock

from .qos import LOCKSTEP_QOS
from .runtime import subscribers_matched

#: wall seconds a step 0 not every axis answered waits before it is offered again
REOFFER_AFTER = 0.1
#: wall seconds a lockstep driven by direct calls steps before the executor serves the rest
BATCH_S = 0.01


def _ready() -> bool:
    return True


class LockstepClock:
    """Steps a node's simulation in lockstep with its commanders (module docstring).

    ``emit(stamp)`` publishes the samples at ``stamp``; ``advance()`` integrates one step with
    the commands held; ``samples`` are the sample publishers, ``command_topics`` each axis's
    resolved ``voltage_command`` topic and ``sample_topics`` each axis's displacement topic.
    """

    def __init__(
        self,
        node: Any,
        *,
        dt_ns: int,
        start_ns: int,
        timeout: float,
        command_topics: Sequence[str],
        sample_topics: Sequence[str],
        samples: Sequence[Any],
        emit: Callable[[Time], None],
        advance: Callable[[], None],
    ) -> None:
        self.node = node
        self.k = 0
        self.late = 0
        self.started = False
        self._dt_ns, self._t0_ns, self._timeout = dt_ns, start_ns, timeout
        self._commands = list(command_topics)
        self._sample_topics = list(sample_topics)
        self._samples = list(samples)
        self._emit_samples, self._integrate = emit, advance
        self._answered = [False] * len(self._commands)
        self._waiting_since = 0.0
        self._sample_first = False
        self._pub_clock = node.create_publisher(Clock, "/clock", LOCKSTEP_QOS)
        self._timer = node.create_timer(min(0.01, max(timeout, 1e-3) / 4), self._watch)
        self._ask: Callable[[int, Time], bool] | None = None
        self._commanders_ready: Callable[[], bool] = _ready
        self._fresh = True  # step k's samples not emitted yet (direct calls)

    def drive(self, ready: Callable[[], bool], ask: Callable[[int, Time], bool]) -> None:
        """Step by direct calls, not commands on topics (the commanders in this process).
        Once ``ready()``, each step emits its samples and ``/clock``, then ``ask(i, t_k)`` asks
        axis i's commander for its command (True: it answered, and the command is applied),
        again on the next turns for the axes that have not answered; the simulation integrates
        once every axis has, or after ``lockstep_timeout`` (a late step; never step 0), as
        across processes. Runs for :data:`BATCH_S` at a time between the executor's other
        callbacks."""
        self._ask, self._commanders_ready = ask, ready
        self.node.destroy_timer(self._timer)
        self._timer = self.node.create_timer(1e-3, self._run_batch)

    def _run_batch(self) -> None:
        ask = self._ask
        assert ask is not None  # drive() made this timer
        if not self.started:
            if not (self._ready() and self._commanders_ready()):
                return
            self.started = True
        end = time.monotonic() + BATCH_S
        answered = self._answered
        while True:
            if self._fresh:
                stamp = self.stamp()
                self._emit_samples(stamp)
                self._pub_clock.publish(Clock(clock=stamp))
                answered[:] = [False] * len(answered)
                self._waiting_since, self._fresh = time.monotonic(), False
            else:
                stamp = self.stamp()
            for i, done in enumerate(answered):
                if not done:
                    answered[i] = ask(i, stamp)
            if not all(answered) and not self._timed_out():
                return  # asked again on the next turn
            self._integrate()
            self.k += 1
            self._fresh = True
            if time.monotonic() > end:
                return

    def _timed_out(self) -> bool:
        """Step k (not 0) has waited ``lockstep_timeout``: counted and said, then advanced."""
        waited = time.monotonic() - self._waiting_since
        if self.k == 0 or self._timeout <= 0 or waited <= self._timeout:
            return False
        self.late += 1
        missing = [t for t, done in zip(self._commands, self._answered) if not done]
        self.node.get_logger().warn(
            f"no command for step {self.k} after {self._timeout:g} s on "
            f"{', '.join(missing)}: advancing with the commands held",
            throttle_duration_sec=5.0,
        )
        return True

    def stamp(self) -> Time:
        """t_k as a message stamp."""
        sec, nanosec = divmod(self._t0_ns + self.k * self._dt_ns, 1_000_000_000)
        return Time(sec=sec, nanosec=nanosec)

    def answered(self, axis: int, stamp: Time) -> None:
        """A command for ``axis`` arrived stamped ``stamp`` (finite or not: it answers the
        step either way); the step advances once every axis has answered it."""
        if not self.started:
            return
        ns: int = stamp.sec * 1_000_000_000 + stamp.nanosec
        if abs(ns - (self._t0_ns + self.k * self._dt_ns)) >= self._dt_ns // 2:
            return
        self._answered[axis] = True
        if all(self._answered):
            self._advance()

    def _advance(self) -> None:
        self._integrate()
        self.k += 1
        self._emit()

    def _emit(self, again: bool = False) -> None:
        """Publish step k (``again``: a step 0 offered again, the answers given kept)."""
        stamp = self.stamp()
        if not again:
            self._answered = [False] * len(self._commands)
        if self._sample_first:  # a sample-triggered commander (controller) waits for the sample
            self._emit_samples(stamp)
            self._pub_clock.publish(Clock(clock=stamp))
        else:  # a clock-triggered one (excitation) waits for /clock
            self._pub_clock.publish(Clock(clock=stamp))
            self._emit_samples(stamp)
        self._waiting_since = time.monotonic()

    def _commanders_read_samples(self) -> bool:
        """True when a voltage_command publisher subscribes to a displacement (a controller):
        then the samples are on the step's critical path and go out before /clock."""
        node = self.node
        commanders = {
            (i.node_name, i.node_namespace)
            for topic in self._commands
            for i in node.get_publishers_info_by_topic(topic)
        }
        readers = {
            (i.node_name, i.node_namespace)
            for topic in self._sample_topics
            for i in node.get_subscriptions_info_by_topic(topic)
        }
        return bool(commanders & readers)

    def _ready(self) -> bool:
        node = self.node
        if node.get_parameter("wait_for_commander").value and any(
            node.count_publishers(topic) == 0 for topic in self._commands
        ):
            return False
        return subscribers_matched(self._samples, node.get_parameter("wait_for_subscribers").value)

    def _watch(self) -> None:
        if not self.started:
            if self._ready():
                self.started = True
                self._sample_first = self._commanders_read_samples()
                self._emit()
            return
        waited = time.monotonic() - self._waiting_since
        if self.k == 0:  # same stamp and values: a commander that answered ignores it
            if waited > REOFFER_AFTER:
                self._sample_first = self._commanders_read_samples()
                self._emit(again=True)
            return
        if self._timed_out():
            self._advance()
