"""`scan_view` node: a running raster scan's image, live (the live view's Scan tab).

It listens to the two scan axes' ``<axis>/loop_samples`` (every sample of the scanner's loop)
and places them with :class:`~piezo_stage.control.scan_live.ScanAccumulator`: each sample's
height of the ``sample`` at its measured position, in the pixel of its desired position, line
by line, a line overwriting the last frame's. The scan is ``scan_file``, one axis of it as
the controllers take it (``trajectory: scan_x.json``); its time origin is found in the record
(:func:`~piezo_stage.control.scan_live.scan_origin`), so the view must run before the scan
starts (as a recorder must).

Publishes at ``publish_rate_hz``: ``scan_image`` (sensor_msgs/Image, mono8: the sample's
height range from black to white, a pixel no sample reached mid-grey), ``scan_line_rms``
(geometry_msgs/PointStamped: x, y the RMS error [m] of the fast and slow axis over the last
line scanned, z its index) and ``scan_position`` (geometry_msgs/PointStamped: the measured x,
y of the newest fast-axis sample). /diagnostics: what it waits for (each axis's
``loop_samples``, the scan's start), or the line it is on; with nothing received
``NOTHING_AFTER`` s after its start it says so once in its log, with the topics and the ROS
domain it listens on (``piezo-stage experiment raster --view`` runs it beside a scan).
"""

from __future__ import annotations

import functools
import math
import sys
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped
from sensor_msgs.msg import Image

from piezo_stage.bag.reader import loop_columns
from piezo_stage.control.scan import ScanAxis, ScanError
from piezo_stage.control.scan_image import load_sample, scan_image
from piezo_stage.control.scan_live import ScanAccumulator, scan_origin
from piezo_stage_msgs.msg import LoopSamples

from .base import PiezoNode
from .diagnostics import OK, WARN, Diagnosis, Diagnostics
from .errors import RosParameterError
from .qos import BATCH_QOS, SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run, set_stamp
from .settings import ScanViewSettings
from .spec import Kind, Param, ParameterTable

#: grey level of a pixel no sample has reached
UNFILLED = 128
#: [ns] the slow axis's samples kept to place the fast axis's with
SLOW_KEEP_NS = 2_000_000_000
#: [s] with nothing received this long after its start, the node says what it waits for
NOTHING_AFTER = 5.0

PARAMETERS = ParameterTable(
    "scan_view",
    (
        Param(
            "scan_file",
            "",
            "the scan: one of its axes' JSON files, as a controller's trajectory",
            read_only=True,
        ),
        Param(
            "axes",
            ["x", "y"],
            "the fast and the slow axis (their namespaces under this node's)",
            kind=Kind.STRING_ARRAY,
            read_only=True,
        ),
        Param(
            "sample",
            "grating",
            "the sample scanned: grating, or a height map (PNG or CSV file)",
            read_only=True,
        ),
        Param(
            "frame_id",
            "scan",
            "header.frame_id of what it publishes",
            read_only=True,
        ),
        Param(
            "publish_rate_hz",
            2.0,
            "scan_image, scan_line_rms and scan_position per second",
            "Hz",
            (0.1, 50.0),
            read_only=True,
        ),
    ),
    "a raster scan's image as it fills, from the axes' loop_samples",
    settings_type=ScanViewSettings,
)


class ScanViewNode(PiezoNode):
    def __init__(self) -> None:
        super().__init__("scan_view", namespace=DEFAULT_NAMESPACE)
        s: ScanViewSettings = self.declare_settings(PARAMETERS)
        axes = list(s.axes)
        if len(axes) != 2 or len(set(axes)) != 2:
            raise RosParameterError(f"scan_view: axes must name two axes, got {axes}")
        try:
            self.scan = ScanAxis.read(s.scan_file).scan
            sample = load_sample(s.sample, self.scan)
        except ScanError as exc:
            raise RosParameterError(f"scan_view: {exc}") from None
        self.live = ScanAccumulator(self.scan, sample)
        ideal = scan_image(self.scan, sample, np.empty(0), np.empty((2, 0))).ideal
        self._low, self._span = float(ideal.min()), float(np.ptp(ideal)) or 1.0
        self._pending: list[list[Any]] = [[], []]  # batches before the origin is known
        empty: tuple[np.ndarray, np.ndarray] = (np.empty(0, np.int64), np.empty(0))
        self._slow = self._fast = empty  # samples not yet placed (fast), kept to place (slow)
        self.t0: int | None = None
        self._axes, self._received, self._missed = axes, [0, 0], ""
        self._topics = [self.resolve_topic_name(f"{axis}/loop_samples") for axis in axes]
        for index, topic in enumerate(self._topics):
            take = functools.partial(self._on_batch, index)
            self.create_subscription(LoopSamples, topic, take, BATCH_QOS)
        self._pub_image = self.create_publisher(Image, "scan_image", SENSOR_QOS)
        self._pub_lines = self.create_publisher(PointStamped, "scan_line_rms", SENSOR_QOS)
        self._pub_position = self.create_publisher(PointStamped, "scan_position", SENSOR_QOS)
        self._position = (math.nan, math.nan, 0)
        self.frame_id = s.frame_id
        self.create_timer(1.0 / s.publish_rate_hz, self._publish)
        self._nothing = self.create_timer(NOTHING_AFTER, self._say_nothing)
        Diagnostics(self, "scan_view", self._diagnose)

    # ------------------------------------------------------------------ samples
    def _on_batch(self, index: int, msg: LoopSamples) -> None:
        self._received[index] += 1
        if self.t0 is None:
            self._pending[index].append(msg)
            self._find_origin()
            return
        self._take(index, loop_columns([msg]))

    def _find_origin(self) -> None:
        if not all(self._pending):
            return
        columns = [loop_columns(p) for p in self._pending]
        if not all(np.isfinite(c["reference"]).any() for c in columns):
            return  # not stepping yet
        try:
            self.t0 = scan_origin(self.scan, columns)
        except ScanError as exc:
            self._missed = f"{exc} (start the view before the scan)"
            self._pending = [[], []]
            return
        self._pending = [[], []]
        self._take(1, columns[1])
        self._take(0, columns[0])

    def _take(self, index: int, c: dict[str, Any]) -> None:
        """A batch of an axis: the slow axis's samples are kept (the last SLOW_KEEP_NS), the fast
        axis's wait until the slow axis's record covers them, then go to the image with the
        slow axis's position at their stamps (the two batches arrive in either order)."""
        ok = np.isfinite(c["reference"]) & np.isfinite(c["displacement"])
        stamp, x = c["stamp"][ok], c["displacement"][ok]
        if index == 1:
            stamps = np.concatenate([self._slow[0], stamp])
            keep = stamps >= (stamps[-1] - SLOW_KEEP_NS if stamps.size else 0)
            self._slow = (stamps[keep], np.concatenate([self._slow[1], x])[keep])
        else:
            self._fast = (
                np.concatenate([self._fast[0], stamp]),
                np.concatenate([self._fast[1], x]),
            )
        self._place()

    def _place(self) -> None:
        assert self.t0 is not None
        if not (self._slow[0].size and self._fast[0].size):
            return
        covered = self._fast[0] <= self._slow[0][-1]
        if not covered.any():
            return
        stamp, x = self._fast[0][covered], self._fast[1][covered]
        self._fast = (self._fast[0][~covered], self._fast[1][~covered])
        y = np.interp(stamp, self._slow[0], self._slow[1])
        self.live.add((stamp - self.t0) * 1e-9, np.vstack([x, y]))
        self._position = (float(x[-1]), float(y[-1]), int(stamp[-1]))

    # ------------------------------------------------------------------ output
    def _publish(self) -> None:
        if self.t0 is None:
            return
        image = self.live.image()
        grey = np.where(
            np.isfinite(image),
            np.clip((image - self._low) / self._span * 255.0, 0.0, 255.0),
            UNFILLED,
        ).astype(np.uint8)
        msg = Image()
        stamp = self._position[2]
        set_stamp(msg.header, stamp)
        msg.header.frame_id = self.frame_id
        msg.height, msg.width = grey.shape
        msg.encoding, msg.is_bigendian, msg.step = "mono8", 0, grey.shape[1]
        msg.data = grey[::-1].tobytes()  # the image's first row is its top: the last line
        self._pub_image.publish(msg)
        line = self.live.last_line
        if line >= 0:
            rms = self.live.line_rms()[line]
            self._pub_lines.publish(self._point(stamp, float(rms[0]), float(rms[1]), line))
        self._pub_position.publish(self._point(stamp, *self._position[:2], 0.0))

    def _point(self, stamp: int, x: float, y: float, z: float) -> PointStamped:
        msg = PointStamped()
        set_stamp(msg.header, stamp)
        msg.header.frame_id = self.frame_id
        msg.point.x, msg.point.y, msg.point.z = x, y, float(z)
        return msg

    def waiting_for(self) -> str:
        """What the view waits for ('' once the scan's origin is found)."""
        if self.t0 is not None:
            return ""
        missing = [t for t, n in zip(self._topics, self._received) if not n]
        if missing:
            domain = self.context.get_domain_id()
            return (
                f"waiting for {' and '.join(missing)} on ROS domain {domain}: nothing received "
                "(the scan's loop publishes them; start this view before the scan)"
            )
        return self._missed or "waiting for the scan's start: samples arrive, none stepped yet"

    def _say_nothing(self) -> None:
        self._nothing.cancel()
        if not any(self._received):
            self.get_logger().warning(self.waiting_for())

    def _diagnose(self) -> Diagnosis:
        values: dict[str, Any] = {"samples": self.live.samples, "last_line": self.live.last_line}
        values |= {f"{a}_batches": n for a, n in zip(self._axes, self._received)}
        if self.t0 is None:
            return Diagnosis(WARN, self.waiting_for(), values)
        return Diagnosis(OK, f"line {self.live.last_line} of {self.scan.lines}", values)


def main(args: list[str] | None = None) -> int:
    return run(ScanViewNode, args)


if __name__ == "__main__":
    sys.exit(main())
