"""A raster run watched live (``experiment raster --view``): ``scan_view`` and ``live_view`` on
the run's namespace (:data:`VIEW_NAMESPACE`) and ROS domain, so that the Foxglove app's Scan tab
shows the image as it fills.

On a device graph the scanner's loop publishes each axis's ``loop_samples`` itself. The
simulated scanner runs in the core, no graph: :class:`RasterView` publishes each stretch of
the run (:func:`~piezo_stage.control.raster.raster_run`'s ``watch``) as the loop would, in
batches (:func:`loop_batches`, the messages a simulated run's bag holds), at the scan's pace
from a thread of its own, after a few not-stepped rows that ``scan_view`` is seen to receive
(its diagnostics): what is published before it hears the publisher would be lost, and with it
the scan's start. At the end the view stays until ``scan_view`` has shown the run's last
sample, and :data:`LINGER` s more for the app.
"""

from __future__ import annotations

import math
import os
import queue
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator

import numpy as np

from piezo_stage.control.raster import RasterRun
from piezo_stage.control.scan import RasterScan, ScanAxis

if TYPE_CHECKING:
    from piezo_stage.launch import Launcher

__all__ = ["LINGER", "VIEW_NAMESPACE", "RasterView", "loop_batches", "view_graph"]

#: the namespace of a watched run (its own ROS domain keeps other runs out)
VIEW_NAMESPACE = "/raster"
#: [s] the view serves the finished image this long after scan_view has shown it
LINGER = 3.0
#: [s] most a view waits to start, for scan_view to hear the run, and to show its end
VIEW_TIMEOUT = 60.0
#: [s] a device graph's view has shown its run once its newest sample stays this long
SETTLE = 1.5
#: [s] the period of the not-stepped rows published until scan_view hears them
PREROLL_PERIOD = 0.02
#: samples per LoopSamples message of a simulated run, in its bag and to its view (10 ms at
#: 10 kHz, as the scanner's loop sends them)
SIM_BATCH = 100


def loop_batches(
    run: RasterRun, index: int, frame_id: str, batch: int = SIM_BATCH
) -> Iterator[Any]:
    """Axis ``index`` of a simulated run as the scanner's loop publishes it: LoopSamples of
    ``batch`` samples, stamps the run's time [ns] from 0, every sample stepped and closed (a
    controller's open-loop run: not closed, its command the feedforward)."""
    from piezo_stage_msgs.msg import LoopSamples

    stamps = np.round(run.t * 1e9).astype(np.int64)
    for start in range(0, stamps.size, batch):
        part = slice(start, start + batch)
        msg = LoopSamples()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamps[start]), 10**9)
        msg.header.frame_id = frame_id
        msg.stamp = stamps[part].tolist()
        msg.displacement = run.measured[index, part].tolist()
        msg.status = [0] * len(msg.stamp)
        msg.reference = run.desired[index, part].tolist()
        msg.u = msg.applied = run.u[index, part].tolist()
        msg.u_ff = [math.nan] * len(msg.stamp) if run.closed_loop else msg.u
        msg.loop_closed = [run.closed_loop] * len(msg.stamp)
        yield msg


def _preroll(frame_id: str) -> Any:
    """One not-stepped row a millisecond before the scan (a loop's samples before it starts)."""
    from piezo_stage_msgs.msg import LoopSamples

    msg = LoopSamples()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(-1_000_000, 10**9)
    msg.header.frame_id = frame_id
    msg.stamp, msg.status, msg.loop_closed = [-1_000_000], [0], [False]
    msg.displacement = msg.reference = msg.u = msg.u_ff = msg.applied = [math.nan]
    return msg


def view_graph(
    scan: RasterScan, axes: tuple[str, str], sample: str, port: int, folder: Path
) -> dict[str, Any]:
    """The view's graph: scan_view on ``scan`` (its file written in ``folder``) and ``sample``,
    live_view on ``port`` (0: a free one), in :data:`VIEW_NAMESPACE`."""
    scan_file = ScanAxis(scan, 0).save(folder / f"scan_{axes[0]}.json")
    view = {"scan_file": str(scan_file), "axes": list(axes), "sample": sample}
    return {
        "description": "a raster run's live view",
        "namespace": VIEW_NAMESPACE,
        "wait_for_topics": [{"topic": "scan_image", "publishers": 1}],
        "nodes": [
            {"executable": "scan_view", "overrides": view},
            {
                "executable": "live_view",
                "overrides": {"port": port},
                "ready_pattern": "Foxglove live view on",
            },
        ],
    }


def _stderr(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


class RasterView:
    """``with RasterView(scan, axes, sample, port) as view:`` serves the view while the run goes
    on in :data:`VIEW_NAMESPACE` (``feed`` it a simulated run's stretches); leaving the block
    without an error waits until the view has shown the run's end (:data:`LINGER` s more),
    then stops it. ``tell`` gets the line that says where to look (default: stderr)."""

    def __init__(
        self,
        scan: RasterScan,
        axes: tuple[str, str],
        sample: str,
        port: int,
        tell: Callable[[str], None] = _stderr,
    ) -> None:
        self.scan, self.axes, self.sample, self.port, self.tell = scan, axes, sample, port, tell
        self.namespace = VIEW_NAMESPACE
        self.lines: list[str] = []  # the view's processes' output
        self._folder = tempfile.TemporaryDirectory(prefix="piezo_view_")
        self._launcher: Launcher | None = None
        self._ros: _ViewNode | None = None
        self._feed: _Feed | None = None

    def __enter__(self) -> RasterView:
        from piezo_stage.launch import Launcher

        graph = view_graph(self.scan, self.axes, self.sample, self.port, Path(self._folder.name))
        try:
            self._launcher = Launcher(graph, sink=self._sink, timeout=VIEW_TIMEOUT)
            self._launcher.start()
            self._launcher.wait_ready()
            self._ros = _ViewNode(self.namespace, self.axes)
        except BaseException:
            self._close()
            for line in self.lines[-10:]:  # why the view did not start
                _stderr(line)
            raise
        # the line live_view was awaited for (its tail holds it before the launcher goes on)
        said = self._launcher.process("live_view").tail
        self.tell(self.where(next((w for x in said for w in x.split() if "ws://" in w), "")))
        return self

    def where(self, url: str) -> str:
        """The line that says where to look."""
        domain = os.environ.get("ROS_DOMAIN_ID", "0") or "0"
        return (
            f"view: the scan live on {url} (Foxglove app, the Scan tab of "
            f"the {self.namespace} layout; ROS_DOMAIN_ID={domain}, namespace {self.namespace}), "
            f"until {LINGER:g} s after the scan"
        )

    def _sink(self, name: str, line: str, err: bool) -> None:
        # its errors only: scan_view's word that it waits (a device graph takes seconds to
        # start) is said by the experiment if the view shows nothing
        self.lines.append(f"[{name}] {line}")
        if name in ("scan_view", "live_view") and "[ERROR]" in line:
            _stderr(f"[{name}] {line}")

    def feed(self, part: RasterRun) -> None:
        """A stretch of a simulated run, published as the scanner's loop publishes it."""
        assert self._ros is not None, "feed() inside the with block"
        if self._feed is None:
            self._feed = _Feed(self._ros, self.axes, self.tell)
            self._feed.start()
        self._feed.parts.put(part)

    def __exit__(self, kind: type[BaseException] | None, *rest: object) -> None:
        try:
            if kind is None and self._ros is not None:
                last = self._feed.finish() if self._feed is not None else None
                self._ros.wait_shown(last, self.tell)
                time.sleep(LINGER)
        finally:
            self._close()

    def _close(self) -> None:
        if self._feed is not None:
            self._feed.stop()
        if self._ros is not None:
            self._ros.close()
        if self._launcher is not None:
            self._launcher.stop()
        self._folder.cleanup()


class _ViewNode:
    """The experiment's node beside the view: what scan_view says (/diagnostics) and has shown
    (the stamp of ``scan_position``: its newest placed sample), and the loop_samples
    publishers of a simulated run."""

    def __init__(self, namespace: str, axes: tuple[str, str]) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        from piezo_stage.nodes.qos import SENSOR_QOS

        self.ctx = rclpy.Context()
        rclpy.init(  # signals stay the command's: the view stops on the way out
            context=self.ctx,
            domain_id=int(os.environ.get("ROS_DOMAIN_ID", "0") or 0),
            signal_handler_options=SignalHandlerOptions.NO,
        )
        self.node = rclpy.create_node("raster_view", namespace=namespace, context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.axes, self.scan_view = axes, f"{namespace}/scan_view"
        self.said, self.heard = "", [0, 0]
        self.shown: tuple[int, float] | None = None  # (stamp, when it last changed)
        self.node.create_subscription(PointStamped, "scan_position", self._shown, SENSOR_QOS)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._said, 10)

    def publishers(self) -> list[Any]:
        from piezo_stage.nodes.qos import BATCH_QOS
        from piezo_stage_msgs.msg import LoopSamples

        return [
            self.node.create_publisher(LoopSamples, f"{axis}/loop_samples", BATCH_QOS)
            for axis in self.axes
        ]

    def _shown(self, msg: Any) -> None:
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        if self.shown is None or stamp != self.shown[0]:
            self.shown = (stamp, time.monotonic())

    def _said(self, msg: Any) -> None:
        for status in msg.status:
            if status.name == self.scan_view:
                self.said = status.message
                values = {v.key: v.value for v in status.values}
                self.heard = [int(values.get(f"{a}_batches", "0")) for a in self.axes]

    def spin_until(self, done: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not done() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
        return done()

    def wait_shown(self, last: int | None, tell: Callable[[str], None]) -> None:
        """Until scan_view has shown the sample stamped ``last`` (None: until its newest
        sample stays :data:`SETTLE` s); a view that shows nothing is said, not waited for."""

        def done() -> bool:
            if self.shown is None:
                return False
            if last is not None:
                return self.shown[0] >= last
            return time.monotonic() - self.shown[1] >= SETTLE

        showing = self.spin_until(lambda: self.shown is not None, 2 * SETTLE)
        if not (showing and self.spin_until(done, VIEW_TIMEOUT)):
            tell(f"view: scan_view did not show the scan's end ({self.said or 'no word'})")

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


class _Feed(threading.Thread):
    """Publishes a simulated run's stretches (``parts``) at the scan's pace: each line of the
    image when the instrument would scan it (a stretch computed later than that goes at once).
    """

    def __init__(self, ros: _ViewNode, axes: tuple[str, str], tell: Callable[[str], None]):
        super().__init__(name="raster-view-feed", daemon=True)
        self.ros, self.axes, self.tell = ros, axes, tell
        self.pubs = ros.publishers()
        self.parts: queue.Queue[RasterRun | None] = queue.Queue()
        self.last: int | None = None  # the stamp of the last sample published
        self._stopping = threading.Event()
        self._origin: float | None = None  # [s] time.monotonic() of the scan's start

    def run(self) -> None:
        if not self._heard():
            self.tell(f"view: scan_view does not hear the run ({self.ros.said or 'no word'})")
            return
        while (part := self.parts.get()) is not None and not self._stopping.is_set():
            self._publish(part)

    def _heard(self) -> bool:
        """Not-stepped rows until scan_view has received some on both axes."""
        deadline = time.monotonic() + VIEW_TIMEOUT
        rows = [_preroll(axis) for axis in self.axes]
        while not all(self.ros.heard) and not self._stopping.is_set():
            if time.monotonic() > deadline:
                return False
            for pub, row in zip(self.pubs, rows):
                pub.publish(row)
            self.ros.spin_until(lambda: False, PREROLL_PERIOD)
        return all(self.ros.heard)

    def _publish(self, part: RasterRun) -> None:
        fast, slow = (list(loop_batches(part, i, a)) for i, a in enumerate(self.axes))
        for x, y in zip(fast, slow):
            t = x.stamp[0] * 1e-9
            if self._origin is None:
                self._origin = time.monotonic() - t
            delay = self._origin + t - time.monotonic()
            if delay > 0 and self._stopping.wait(delay):
                return
            self.pubs[1].publish(y)  # the slow axis first: scan_view places the fast
            self.pubs[0].publish(x)  # axis's samples where the slow axis's record covers them
            self.last = int(x.stamp[-1])

    def finish(self) -> int | None:
        """Publish what is queued; the stamp of the last sample published (None: none was)."""
        self.parts.put(None)
        self.join()
        return self.last

    def stop(self) -> None:
        self._stopping.set()
        self.parts.put(None)
        self.join(timeout=5.0)
