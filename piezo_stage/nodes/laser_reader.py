"""`laser_reader` node ("the reader"): a Micro-Epsilon optoNCDT laser sensor, or a PI controller's
own sensor polled over GCS (``family`` ``pi_gcs``), on ``displacement``.

Same topic, type, units and QoS as the simulated ``plant`` (docs/design.md §3): publishes
``displacement`` (SENSOR_QOS, metres; status != OK carries NaN) and ``/diagnostics``. Frame
parsing, resynchronisation, the frame lock and speed gate (``relock_frames``, ``max_speed``:
nothing OK next to damaged bytes), error values and link handling are
:class:`piezo_stage.hardware.sensor.SensorReader`; this node reads it in a thread of its own
(blocking reads: each block is stamped as it arrives) and only adds:

- the output convention: ``displacement = sign · (d − zero_offset)`` with d the distance from
  the start of the measuring range [m];
- decimation (:class:`piezo_stage.hardware.decimation.Decimator`): ``decimation`` = N
  consecutive samples -> one message, the mean of the N when all are OK; a group holding any
  non-OK sample takes the status of its first non-OK sample and NaN (N = 1: every sample);
- stamps on the sensor's sample clock (:class:`piezo_stage.hardware.timing.SampleClock`): the
  k-th sample since (re)connecting was taken at ``t0 + k / rate_hz``, ``t0`` being the lower
  envelope of ``t_reception − k / rate_hz`` over ``stamp_window`` seconds (frames reach the host
  in bursts, which only ever add delay); a message is stamped at the mean time of the samples it
  averages, minus ``latency`` (the sensor's own delay: exposure, processing and the serial frame
  time). ``rate_hz`` must be the sensor's measuring rate (MEASRATE).

``family`` ``pi_gcs``: the controller's own (capacitive, strain-gauge) sensor,
:class:`piezo_stage.hardware.gcs_sensor.GCSPositionReader` on a GCS link of its own (``url``
``tcp://host:port``: a second TCP connection next to the voltage driver's), ``POS? <gcs_axis>``
polled on a grid of ``rate_hz`` (um -> m); an answer that is not ``<axis>=<number>`` or a poll
left unanswered is a sample with status INVALID (then the link is reopened). An axis that the
controller's ``SAI?`` does not list: one line, exit code 2. ``measuring_range``, ``bits``,
``max_speed`` and ``relock_frames`` are the optoNCDT's and not used.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Sequence

from rclpy.parameter import Parameter

from piezo_stage.hardware import ConfigError, SensorConfig, SensorReader, Status
from piezo_stage.hardware.axis_sensor import AxisSensor
from piezo_stage.hardware.gcs_sensor import GCSPositionReader, GCSReaderConfig
from piezo_stage.hardware.optoncdt import FAMILIES
from piezo_stage.hardware.sensor_frame import SensorFrame
from piezo_stage_msgs.msg import Displacement

from .base import PiezoNode
from .diagnostics import ERROR, OK, STALE, WARN, Diagnosis, Diagnostics
from .errors import RosParameterError
from .parameters import on_set
from .qos import SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run, set_stamp, stamp_clock
from .settings import LaserReaderSettings
from .spec import Param, ParameterTable

PI_GCS = "pi_gcs"  #: the ``family`` of a PI controller's own sensor

PARAMETERS = ParameterTable(
    "laser_reader",
    (
        Param(
            "url",
            "/dev/ttyUSB0",
            "link: /dev/tty..., serial:///dev/ttyUSB0?baudrate=921600, tcp://host:port",
            read_only=True,
        ),
        Param(
            "baud",
            0,
            "serial baud rate (0: the family's default)",
            range=(0, 4_000_000),
            read_only=True,
        ),
        Param(
            "family",
            "ild1320",
            "optoNCDT family, or pi_gcs: a PI controller's own sensor (POS? over GCS)",
            choices=(*FAMILIES, PI_GCS),
            read_only=True,
        ),
        Param(
            "gcs_axis",
            "1",
            "pi_gcs: the controller's axis whose POS? is polled (an axis SAI? lists)",
            read_only=True,
        ),
        Param(
            "bits",
            0,
            "output word width (ILD1320 family: 16 or 18; 0: the family's default)",
            range=(0, 18),
            read_only=True,
        ),
        Param("measuring_range", 10e-3, "measuring range MR", "m", (1e-6, 10.0), read_only=True),
        Param(
            "zero_offset",
            0.0,
            "distance from the start of the range published as zero",
            "m",
            read_only=True,
        ),
        Param(
            "sign",
            1,
            "+1: away from the sensor is positive; -1: towards it",
            range=(-1, 1),
            step=2,
            read_only=True,
        ),
        Param(
            "decimation",
            1,
            "N samples -> one message (mean of N OK samples)",
            range=(1, 100000),
            read_only=True,
        ),
        Param(
            "rate_hz",
            1000.0,
            "the sensor's measuring rate (stamp correction); pi_gcs: the poll rate",
            "Hz",
            (1e-3, 1e6),
            read_only=True,
        ),
        Param(
            "latency",
            0.0,
            "sensor delay subtracted from the reception time",
            "s",
            (0.0, 10.0),
            read_only=True,
        ),
        Param(
            "stamp_window",
            2.0,
            "window of the sample clock's lower envelope (see module docstring)",
            "s",
            (0.01, 3600.0),
            read_only=True,
        ),
        Param(
            "poll_period",
            0.002,
            "longest wait of the read thread's blocking read before it checks "
            "the link and shutdown (samples are taken as they arrive)",
            "s",
            (1e-4, 1.0),
            read_only=True,
        ),
        Param(
            "stale_timeout",
            0.5,
            "no frame for this long: stale (diagnostics)",
            "s",
            (1e-3, 60.0),
            read_only=True,
        ),
        Param(
            "max_speed",
            0.1,
            "plausibility gate: a value implying a faster stage since the last "
            "accepted one is refused (set it a little above the stage's top speed; an accepted "
            "value is then off by at most max_speed / rate_hz)",
            "m/s",
            (1e-6, 1e3),
            read_only=True,
        ),
        Param(
            "relock_frames",
            6,
            "after a framing error, consecutive well-formed frames that must "
            "agree (within the gate) before values are OK again",
            range=(2, 1000),
            read_only=True,
        ),
    ),
    summary="Micro-Epsilon optoNCDT laser, or a PI controller's own sensor -> displacement.",
    settings_type=LaserReaderSettings,
)


Reader = SensorReader | GCSPositionReader


def make_reader(p: LaserReaderSettings) -> tuple[Reader, str]:
    """The reader ``p`` describes, connected, and its name for logs and /diagnostics; a
    configuration the reader or the device refuses is bad input (RosParameterError)."""
    reader: Reader
    try:
        if p.family == PI_GCS:
            gcs = GCSReaderConfig(p.gcs_axis, p.rate_hz, stale_timeout=p.stale_timeout)
            reader = GCSPositionReader.from_url(p.url, gcs, baudrate=p.baud or None)
            name = f"PI GCS sensor, POS? {p.gcs_axis}, {p.url}"
        else:
            config = SensorConfig(
                p.family,
                p.measuring_range,
                bits=p.bits or None,
                stale_timeout=p.stale_timeout,
                rate=p.rate_hz,
                max_speed=p.max_speed,
                relock_frames=p.relock_frames,
            )
            reader = SensorReader.from_url(p.url, config, baudrate=p.baud or None)
            name = f"optoNCDT {p.family} {p.url}"
        reader.connect()
    except ConfigError as exc:
        raise RosParameterError(f"laser_reader: {exc}") from None
    return reader, name


class LaserReaderNode(PiezoNode):
    """The read thread (:class:`~piezo_stage.hardware.axis_sensor.AxisSensor`'s ``wait``, then
    publish) starts at once, or, ``start`` False, never: a composed loop (:mod:`.stage_loop`)
    reads ``sensor`` (one axis) or the link (several) in its own thread and publishes through
    :meth:`publish_samples`. ``namespace``: the node's (a composing process gives each axis its
    own)."""

    def __init__(
        self,
        overrides: Sequence[Parameter] = (),
        start: bool = True,
        namespace: str = DEFAULT_NAMESPACE,
    ) -> None:
        super().__init__("laser_reader", namespace=namespace, parameter_overrides=list(overrides))
        p: LaserReaderSettings = self.declare_settings(PARAMETERS)
        on_set(
            self,
            lambda changed: (
                "use_sim_time is fixed at start (the sample clock stamps depend on it)"
                if "use_sim_time" in changed
                else None
            ),
        )

        self.reader, self.source = make_reader(p)
        self.url = p.url
        self.family = p.family
        self.frame = SensorFrame(float(p.zero_offset), float(p.sign), float(p.latency))
        self.rate = float(p.rate_hz)
        self.decimation = int(p.decimation)
        self.published = 0
        self.by_status = [0] * len(Status)  # samples read, per status
        # (time, published, the reader's counters) at the last /diagnostics
        self._last_diag: tuple[float, int, dict[str, int]] = (time.monotonic(), 0, {})

        self.stamp_ns = stamp_clock(self)  # use_sim_time is fixed (refused above)
        self._reader_stop = threading.Event()
        self.sensor = AxisSensor(
            self.reader,
            self.rate,
            self.decimation,
            self.stamp_ns,
            p.stamp_window,
            on_link=self._on_link,
            sleep=self._reader_stop.wait,
        )
        self._pub = self.create_publisher(Displacement, "displacement", SENSOR_QOS)
        self._msg = Displacement()  # reused: rclpy serializes at publish
        self._wait = float(p.poll_period)
        self._thread = threading.Thread(target=self._read_loop, name="laser-reader", daemon=True)
        if start:
            self.sensor.connect()
            self._thread.start()
        Diagnostics(self, self.source, self._diagnose)
        range_text = "" if p.family == PI_GCS else f", MR {p.measuring_range:g} m"
        self.get_logger().info(
            f"{self.source}{range_text}: decimation {p.decimation}, rate {self.rate:g} Hz"
        )

    def stream_reader(self) -> SensorReader:
        """The optoNCDT reader: a loop that waits on several sensors' byte streams at once
        (the stage's loop) cannot take a polled ``pi_gcs`` one (RosParameterError)."""
        if not isinstance(self.reader, SensorReader):
            raise RosParameterError(
                f"laser_reader: family {PI_GCS} is polled, not streamed: a loop of several "
                "axes reads optoNCDT streams only"
            )
        return self.reader

    def _on_link(self, error: str | None) -> None:
        if error is None:
            self.get_logger().info(f"reconnected to {self.url}")
        else:
            self.get_logger().error(f"sensor link: {error}", throttle_duration_sec=1.0)

    def _read_loop(self) -> None:
        while not self._reader_stop.is_set():
            try:
                self._poll(self._wait)
            except Exception as exc:  # a bug must not silently end the stream: say it, go on
                self.sensor.last_error = f"reader thread: {exc!r}"
                self.get_logger().error(self.sensor.last_error, throttle_duration_sec=1.0)
                self._reader_stop.wait(self._wait)

    def on_shutdown(self) -> None:
        """Stop the read thread before the node goes away (called by ``common.run``)."""
        self._reader_stop.set()
        if self._thread.ident is not None:
            self._thread.join(timeout=2.0)

    def _poll(self, timeout: float = 0.0) -> None:
        """Read what arrived (waiting up to ``timeout`` s for it), stamp, decimate, publish."""
        sensor = self.sensor
        if not sensor.wait(timeout):
            return
        block, frame, counts = sensor.block, self.frame, self.by_status
        for st in block.status:
            counts[st] += 1
        value = frame.values(block.displacement, block.status)
        self.publish_samples(value, block.status, frame.stamps(block.stamp))
        sensor.next_cycle()

    def publish_samples(
        self, value: Sequence[float], status: Sequence[int], stamp: Sequence[int]
    ) -> None:
        """Publish samples on ``displacement`` (value [m] in the published frame, stamp [ns])."""
        msg, publish = self._msg, self._pub.publish
        for x, st, ns in zip(value, status, stamp):
            set_stamp(msg.header, ns)
            msg.displacement, msg.status = x, st
            publish(msg)
        self.published += len(status)

    def _diagnose(self) -> Diagnosis:
        counts = self.reader.counters()
        now = time.monotonic()
        t0, published0, counts0 = self._last_diag
        self._last_diag = (now, self.published, counts)
        dt = max(now - t0, 1e-9)
        values = {
            "connected": self.sensor.connected,
            "stale": self.reader.stale,
            "family": self.family,
            "frame_rate": (counts["frames"] - counts0.get("frames", 0)) / dt,
            "publish_rate": (self.published - published0) / dt,
            "frames": counts["frames"],
            "published": self.published,
            **{f"samples_{s.name.lower()}": int(self.by_status[s]) for s in Status},
            **{key: n for key, n in counts.items() if key != "frames"},
            "reconnects": self.reader.reconnects,
            "link_errors": self.sensor.link_errors,
            "last_error": self.sensor.last_error,
        }
        if not self.sensor.connected:
            return Diagnosis(ERROR, f"disconnected from {self.url}", values)
        if self.reader.stale:
            return Diagnosis(STALE, f"no frames for {self.reader.config.stale_timeout:g} s", values)
        warning = self.reader.warning(counts0, counts)
        if warning:
            return Diagnosis(WARN, f"{warning} in the last {dt:.3g} s", values)
        return Diagnosis(OK, "streaming", values)


def main(args: list[str] | None = None) -> int:
    return run(LaserReaderNode, args)


if __name__ == "__main__":
    sys.exit(main())
