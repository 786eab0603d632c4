"""A lean single-threaded executor for nodes on a per-message hot path.

It is built on rclpy internals that are not public API (``rclpy.impl``'s ``WaitSet``, the
executor's ``_tasks``/``_tasks_lock``/``_guard``/``_context``, a subscription's
``_callback_type``): test/test_node_executor.py fails loudly when an rclpy upgrade changes them.
Everything else in piezo_stage uses rclpy's public API only.
"""

from __future__ import annotations

import inspect
from typing import Any

from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor, ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.waitable import NumberOfEntities


class LeanExecutor(Executor):
    """A single-threaded executor for nodes on a per-message hot path (the lockstep plant, the
    sample-triggered controller, the clock-triggered excitation).

    rclpy's SingleThreadedExecutor rebuilds its wait set, a Task and a timeout Timer on every
    wake-up and wakes a second time after each callback (its guard condition); for a node that
    answers one message per simulated step that is most of the step's CPU. This one builds the
    entity lists and the wait set once (again only when the node creates or destroys an entity:
    rclpy calls :meth:`wake` then), waits with the timeout given to rcl directly, and calls the
    ready callbacks in rclpy's order (waitables, timers, subscriptions, guard conditions,
    services), one message per ready subscription and wake-up, like rclpy.

    Limits (checked): plain (not ``async``) callbacks, no service clients; tasks created with
    :meth:`create_task` run between wake-ups.
    """

    def __init__(self, *, context: Any = None) -> None:
        super().__init__(context=context)
        self._dirty = True
        self._wait_set: Any = None

    def wake(self) -> None:
        """An entity was created or destroyed: rebuild before the next wait."""
        self._dirty = True
        super().wake()

    def add_node(self, node: Node) -> bool:
        self._dirty = True
        return super().add_node(node)

    def remove_node(self, node: Node) -> None:
        self._dirty = True
        super().remove_node(node)

    def _rebuild(self) -> None:
        self._dirty = False
        nodes = self.get_nodes()
        self._subs = [s for n in nodes for s in n.subscriptions]
        self._timers = [t for n in nodes for t in n.timers]
        self._services = [s for n in nodes for s in n.services]
        self._node_guards = [g for n in nodes for g in n.guards]
        self._waitables = [w for n in nodes for w in n.waitables]
        if any(True for n in nodes for _ in n.clients):
            raise RuntimeError(
                "LeanExecutor does not serve clients: run the node with the standard executor"
            )
        self._sub_by_ptr = {s.handle.pointer: s for s in self._subs}
        self._timer_by_ptr = {t.handle.pointer: t for t in self._timers}
        self._srv_by_ptr = {s.handle.pointer: s for s in self._services}
        # room for the waitables' own entities too (rclpy's QoS event handlers: one event each)
        count = NumberOfEntities(
            len(self._subs),
            len(self._node_guards) + 1,  # + our guard (wake)
            len(self._timers),
            0,
            len(self._services),
        )
        for w in self._waitables:
            count += w.get_num_entities()
        self._wait_set = _rclpy.WaitSet(
            count.num_subscriptions,
            count.num_guard_conditions,
            count.num_timers,
            count.num_clients,
            count.num_services,
            count.num_events,
            self._context.handle,
        )

    def spin_once(self, timeout_sec: float | None = None) -> None:
        """Wait up to ``timeout_sec`` (None: forever) and run what is ready."""
        if self._is_shutdown:
            return
        if self._tasks:
            self._run_tasks()
        if self._dirty:
            self._rebuild()
        ws = self._wait_set
        ws.clear_entities()
        for s in self._subs:
            ws.add_subscription(s.handle)
        for t in self._timers:
            ws.add_timer(t.handle)
        for srv in self._services:
            ws.add_service(srv.handle)
        for g in self._node_guards:
            ws.add_guard_condition(g.handle)
        ws.add_guard_condition(self._guard.handle)
        for w in self._waitables:
            w.add_to_wait_set(ws)
        handle = self._context.handle
        assert handle is not None  # Context.init set it for good; _rebuild gave it to the WaitSet
        with handle:
            ws.wait(-1 if timeout_sec is None else int(max(timeout_sec, 0.0) * 1e9))
        if not self._context.ok():
            raise ExternalShutdownException()
        self._dispatch(ws)

    def _dispatch(self, ws: Any) -> None:
        """Run the callbacks of what the wait set reports ready, in rclpy's order."""
        for w in self._waitables:
            if w.is_ready(ws):
                _drive(w.execute(w.take_data()))
        for ptr in ws.get_ready_entities("timer"):
            t = self._timer_by_ptr.get(ptr)
            if t is not None:
                try:
                    with t.handle:
                        if not t.handle.is_timer_ready():
                            continue
                        t.handle.call_timer()
                except InvalidHandle:
                    continue
                _complete(t.callback())
        for ptr in ws.get_ready_entities("subscription"):
            s = self._sub_by_ptr.get(ptr)
            if s is not None:
                try:
                    with s.handle:
                        info = s.handle.take_message(s.msg_type, s.raw)
                except InvalidHandle:
                    continue
                if info is not None:
                    _complete(
                        s.callback(info[0])
                        if s._callback_type is s.CallbackType.MessageOnly
                        else s.callback(*info)
                    )
        if self._node_guards:
            self._run_guards(ws)
        for ptr in ws.get_ready_entities("service"):
            self._serve(ptr)

    def _run_guards(self, ws: Any) -> None:
        """Call the triggered node guards' callbacks (rare: nodes without guards skip it)."""
        ready = ws.get_ready_entities("guard_condition")
        for g in self._node_guards:
            if g.handle.pointer in ready and g.callback is not None:
                _complete(g.callback())

    def _serve(self, ptr: Any) -> None:
        """Answer one request of the ready service at ``ptr`` (rare: parameters, commands)."""
        srv = self._srv_by_ptr.get(ptr)
        if srv is not None:
            srv_type: Any = srv.srv_type  # a rosidl service class (rclpy: an unbound TypeVar)
            try:
                with srv.handle:
                    request, header = srv.handle.service_take_request(srv_type.Request)
            except InvalidHandle:
                return
            if header is not None:
                response = srv.callback(request, srv_type.Response())
                _complete(response)
                srv.send_response(response, header)

    def _run_tasks(self) -> None:
        with self._tasks_lock:
            tasks = list(self._tasks)
        for task, _entity, _node in tasks:
            if not task.executing() and not task.done():
                task()
        with self._tasks_lock:
            self._tasks = [t for t in self._tasks if not t[0].done()]


def _drive(coroutine: Any) -> None:
    """Run a waitable's ``execute`` coroutine (rclpy's QoS event handlers finish in one step)."""
    try:
        coroutine.send(None)
    except StopIteration:
        return
    coroutine.close()
    raise RuntimeError(
        "a waitable awaited a future: LeanExecutor cannot run it, use the standard executor"
    )


def _complete(result: Any) -> None:
    """The lean executor runs plain callbacks only: refuse a coroutine rather than drop it."""
    if inspect.iscoroutine(result):
        result.close()
        raise TypeError(
            "LeanExecutor runs plain callbacks only (got a coroutine): use the standard executor"
        )
