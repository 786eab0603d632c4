"""A raster played by a PI controller: both axes' tables in its wave generator at its servo
rate, both axes' voltages and positions from its data recorder (E-727 manual, "Wave Generator"
and "Data Recording"), the image from the recorded positions.

The tables are the host raster's (:func:`~piezo_stage.control.raster.raster_tables`): the fast
axis's over one line period, the slow axis's over one frame, each from its axis's model with
the coupling taken out. Axis k of the stage plays on its controller axis's generator (servo
off: the table is the voltage, the thesis's feedforward), one point every ``rate`` servo
cycles; one ``WGO`` starts both generators and the recording. A play is
:data:`SETTLE_FRAMES` frames (the stage settles after a change of the tables) and
:data:`MEASURED_FRAMES` recorded one; only the recorded frame is read back.

Learning is per frame, as the host raster learns per line: the fast axis's table from the
recorded frame's line periods' mean error (the sensor's noise falls with their number, the
coupling the slow axis leaves on each line averages to its mean) and the slow axis's from the
frame's error, each with the host's learning (:class:`~piezo_stage.control.learning.
IterativeLearning`: its cutoff from the rate and the model's resonance, its stop rule), until
both stop or ``learn`` frames. Points of a table at the amplifier's limits are counted.

The image (:class:`DetectedRun`): a detector on a clock of its own samples each line's window
pixel by pixel, the position at each pixel interpolated between the recorder's samples
(:func:`~piezo_stage.control.scan_image.detector_samples`), as a detector sampled faster than
the servo is.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from piezo_stage.control.feedforward import FeedforwardModel
from piezo_stage.control.learning import (
    IterativeLearning,
    LearningConfig,
    at_limits,
    default_cutoff,
    feedforward_response,
)
from piezo_stage.control.raster import RasterRun, RasterTables, raster_tables
from piezo_stage.control.scan import RasterScan
from piezo_stage.control.scan_image import (
    Sample,
    ScanFigures,
    ScanImage,
    detector_samples,
    scan_figures,
    scan_image,
)
from piezo_stage.hardware.amplifier import GCSAmplifier
from piezo_stage.hardware.pi_recorder import RecordOption, ServoRecorder
from piezo_stage.model.stage_file import Stage
from piezo_stage.stopping import safe_stop

from .errors import ExperimentError, ExperimentInputError
from .servo_identification import ramp_to, safe_state

__all__ = ["DetectedRun", "ServoAxis", "ServoSetup", "servo_raster", "table_rate"]

#: frames played before the recorded one after each change of the tables
SETTLE_FRAMES = 1
#: frames played (not recorded) before the first play: the slow axis's hysteresis halves its
#: distance to its periodic state per frame, and from the ramp to the first value it is far
#: (one settling frame left a replayed table at 0.2 % where it had learned 0.09 %)
START_FRAMES = 4
#: frames recorded and read back
MEASURED_FRAMES = 1
#: frames of the image played back to back once learned (the tables left as they are, each
#: frame read back while the next plays; fewer where a record table holds fewer)
IMAGE_FRAMES = 4
#: what each axis's two recorder tables hold (tables 2k + 1, 2k + 2 of the fast, slow axis)
RECORD = (RecordOption.PIEZO_VOLTAGE, RecordOption.CURRENT_POSITION)
UM = 1e-6  #: m per um (PI reports positions in um)
#: what learns above the line rate: harmonics of the frame up to this many times the line rate
#: (the slow axis's steps, the coupling between the axes); above it only the fast axis's line
#: harmonics, the slow axis nothing. The learned table's ripple above it reverses the slow
#: axis's held steps, and a Bouc-Wen stage ratchets on reversals that small: at 10 Hz lines
#: the slow axis learned from the default cutoff went from 0.1 % to 5 % in one frame
LEARN_LINE_HARMONICS = 20

Progress = Callable[[float, str], None]
Array = NDArray[np.float64]


@dataclass(frozen=True)
class ServoAxis:
    """An axis of the controller a scan axis plays on: its amplifier (servo off) and the
    wave generator that drives it."""

    amplifier: GCSAmplifier
    generator: int


@dataclass
class DetectedRun(RasterRun):
    """A raster recorded by the controller at its table rate and imaged by a detector of its
    own (module docstring): :meth:`figures` and :meth:`image` on the detector's samples of the
    last frame; ``at_limit`` the fast and slow tables' points at the amplifier's limits;
    ``frame_wall`` the wall time per frame of the image once learned [s]."""

    per_pixel: int = 1
    at_limit: tuple[int, int] = (0, 0)
    frame_wall: float = math.nan
    closed_loop: ClassVar[bool] = False

    def detected(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The detector's times and positions over the last frame."""
        keep = self.last_frame()
        return detector_samples(self.scan, self.t[keep], self.measured[:, keep], self.per_pixel)

    def figures(self, sample: Sample) -> ScanFigures:
        return scan_figures(self.scan, sample, *self.detected())

    def image(self, sample: Sample) -> ScanImage:
        return scan_image(self.scan, sample, *self.detected())


def table_rate(scan: RasterScan, cycle: float, rate: int) -> tuple[float, int, int]:
    """(table rate [Hz], points per line, points per frame) of ``scan`` at one point every
    ``rate`` servo cycles of ``cycle`` s; :class:`ExperimentInputError` unless a line is a
    whole number of points (a frame then is too)."""
    rate_hz = 1.0 / (cycle * rate)
    n = scan.period * rate_hz
    if abs(n - round(n)) > 1e-6 * n or round(n) < 2:
        raise ExperimentInputError(
            f"a {scan.line_rate:g} Hz line is {n:.6g} points at the controller's {rate_hz:g} Hz "
            "table rate: a line needs a whole number of points (at least 2)"
        )
    n_line = round(n)
    return rate_hz, n_line, round(scan.frame_time * rate_hz)


def check_capacity(
    recorder: ServoRecorder, axes: Sequence[ServoAxis], n_fast: int, n_frame: int
) -> None:
    """Refuse (:class:`ExperimentInputError`) tables longer than the controller's wave tables
    (``WMS?``) or a play longer than its record tables hold with four tables; the recorder is
    left with four tables."""
    for name, axis, n in (("fast", axes[0], n_fast), ("slow", axes[1], n_frame)):
        most = recorder.wave_points(axis.generator)
        if n > most:
            raise ExperimentInputError(
                f"the {name} axis's table is {n} points, wave table {axis.generator} holds "
                f"{most} (WMS?): fewer lines, a faster line rate or a slower table rate"
            )
    recorder.set_tables(2 * len(axes))
    plays = (SETTLE_FRAMES + MEASURED_FRAMES) * n_frame
    if plays > recorder.table_points():
        raise ExperimentInputError(
            f"a play ({SETTLE_FRAMES + MEASURED_FRAMES} frames, {plays} points) does not fit "
            f"a data recorder table of {recorder.table_points()} points: fewer lines, a faster "
            "line rate or a slower table rate"
        )


def servo_raster(
    recorder: ServoRecorder,
    axes: tuple[ServoAxis, ServoAxis],
    scan: RasterScan,
    tables: RasterTables,
    models: tuple[FeedforwardModel, FeedforwardModel],
    rate: int,
    limits: tuple[float, float],
    learn: int = 0,
    per_pixel: int = 1,
    progress: Progress = lambda fraction, text: None,
) -> DetectedRun:
    """``scan`` played on the controller from ``tables`` (fast, slow), learning over at most
    ``learn`` frames (module docstring); every generator stopped and every output ramped to
    max(VMI?, 0 V) after, and on any failure or signal. ``limits``: the amplifier's [V]."""
    rate_hz, _, n_frame = table_rate(scan, recorder.servo_cycle(), rate)
    why = tables.matches(scan, rate_hz)
    if why:
        raise ExperimentInputError(f"feedforward tables: {why}")
    check_capacity(recorder, axes, len(tables.fast), n_frame)
    recorder.configure([(a.amplifier.axis, option) for a in axes for option in RECORD], rate)
    config = LearningConfig(u_min=limits[0], u_max=limits[1], settle_periods=0)
    low = LEARN_LINE_HARMONICS * scan.line_rate
    slow_config = replace(config, cutoff_hz=min(default_cutoff(models[1], rate_hz), low))
    learners = [
        IterativeLearning(table, feedforward_response(model, rate_hz, len(table)), c, model)
        for table, model, c in zip((tables.fast, tables.slow), models, (config, slow_config))
    ]
    n_line = round(scan.period * rate_hz)
    keep = _fast_bins(len(tables.fast), n_line, rate_hz, low)
    t = (SETTLE_FRAMES * n_frame + np.arange(MEASURED_FRAMES * n_frame)) / rate_hz
    (xd, _, _), (yd, _, _) = scan.evaluate(t)
    desired = np.vstack([xd, yd])
    player = _Player(recorder, axes, len(tables.fast), n_frame, scan.frame_time, rate)
    try:
        for axis, learner in zip(axes, learners):
            ramp_to(axis.amplifier, float(learner.table.u[0]))
        player.settle([lrn.table.u for lrn in learners], START_FRAMES)
        history = _learn(player, learners, keep, scan, t, desired, learn, progress)
        record = player.image(IMAGE_FRAMES)
    except BaseException:
        _safe(axes, recorder, limits[0])
        raise
    _safe(axes, recorder, limits[0])
    fast, slow = (learner.table for learner in learners)
    return DetectedRun(
        scan,
        t,
        desired,
        record[1],
        record[0],
        history,
        RasterTables(fast, slow, {"rate_hz": rate_hz, "scan": scan.to_dict()}),
        per_pixel=per_pixel,
        at_limit=(at_limits(fast.u, *limits), at_limits(slow.u, *limits)),
        frame_wall=player.frame_wall,
    )


@dataclass
class _Player:
    """Plays the two tables and reads the recorded frame back."""

    recorder: ServoRecorder
    axes: tuple[ServoAxis, ServoAxis]
    n_fast: int  #: the fast axis's table: a line's points or a frame's
    n_frame: int
    frame_time: float
    rate: int
    frame_wall: float = math.nan

    def settle(self, u: Sequence[NDArray[np.float64]], frames: int) -> None:
        """Play ``frames`` frames of the tables ``u`` and wait for their end (not read)."""
        recorder, generators = self.recorder, [a.generator for a in self.axes]
        lines_per_frame = self.n_frame // self.n_fast
        for axis, table, cycles in zip(self.axes, u, (frames * lines_per_frame, frames)):
            recorder.upload(axis.generator, table)
            recorder.connect(axis.generator, axis.generator, cycles, self.rate, 0.0)
        recorder.start(generators)
        recorder.wait_until_stopped(generators, frames * self.frame_time)

    def play(self, u: Sequence[NDArray[np.float64]]) -> tuple[Array, Array]:
        """Voltages [V] and positions [m] (2, samples) of the recorded frame."""
        frames = SETTLE_FRAMES + MEASURED_FRAMES
        self.settle(u, frames)
        count = self.recorder.recorded()
        if count < frames * self.n_frame:
            raise ExperimentError(
                f"the data recorder holds {count} of the {frames * self.n_frame} points played"
            )
        return self._frame(SETTLE_FRAMES)

    def image(self, frames: int) -> tuple[Array, Array]:
        """Play the tables as they are (uploaded by the last :meth:`play`) for ``frames``
        frames back to back (fewer if a record table holds fewer), reading each frame back
        while the next plays: the last frame's voltages [V] and positions [m];
        :attr:`frame_wall` the wall time per frame from the start to the last read."""
        recorder, generators = self.recorder, [a.generator for a in self.axes]
        frames = max(1, min(frames, recorder.table_points() // self.n_frame))
        lines_per_frame = self.n_frame // self.n_fast
        started = time.monotonic()
        for axis, cycles in zip(self.axes, (frames * lines_per_frame, frames)):
            recorder.connect(axis.generator, axis.generator, cycles, self.rate, 0.0)
        recorder.start(generators)
        for k in range(frames):
            self._wait_recorded((k + 1) * self.n_frame, started + (k + 1) * self.frame_time)
            record = self._frame(k)
        recorder.wait_until_stopped(generators, self.frame_time)
        self.frame_wall = (time.monotonic() - started) / frames
        return record

    def _wait_recorded(self, points: int, due: float) -> None:
        """Until the recorder holds ``points`` (``DRL?``): asked from the monotonic time
        ``due`` on, then every millisecond; :class:`ExperimentError` if it holds fewer a
        frame's time after that plus 10 s."""
        time.sleep(max(0.0, due - time.monotonic()))
        deadline = max(due, time.monotonic()) + self.frame_time + 10.0
        while (count := self.recorder.recorded()) < points:
            if time.monotonic() > deadline:
                raise ExperimentError(
                    f"the data recorder holds {count} of the {points} points played"
                )
            time.sleep(1e-3)

    def _frame(self, k: int) -> tuple[Array, Array]:
        """Voltages [V] and positions [m] (2, samples) of the ``k``-th frame recorded."""
        columns = self.recorder.read_range(4, k * self.n_frame, self.n_frame).columns
        return columns[0::2], columns[1::2] * UM


def _fast_bins(n: int, n_line: int, rate_hz: float, low: float) -> NDArray[np.bool_]:
    """The rfft bins of the fast axis's ``n``-point table it learns: its line harmonics, and
    the frame's up to ``low`` [Hz] (a line table: every bin)."""
    k = np.arange(n // 2 + 1)
    keep: NDArray[np.bool_] = (k % (n // n_line) == 0) | (np.fft.rfftfreq(n, 1.0 / rate_hz) <= low)
    return keep


def _learn(
    player: _Player,
    learners: list[IterativeLearning],
    keep: NDArray[np.bool_],
    scan: RasterScan,
    t: NDArray[np.float64],
    desired: NDArray[np.float64],
    learn: int,
    progress: Progress,
) -> list[tuple[float, float]]:
    """Play, learn from the recorded frame, play again, until both learners stop or ``learn``
    frames: each play's RMS error over the image windows per axis [m]."""
    history: list[tuple[float, float]] = []
    inside = scan.line_index(t)[0] >= 0
    for j in range(learn + 1):
        _, x = player.play([lrn.table.u for lrn in learners])
        e = x - desired
        history.append(
            (
                float(np.sqrt(np.mean(e[0, inside] ** 2))),
                float(np.sqrt(np.mean(e[1, inside] ** 2))),
            )
        )
        rms = ", ".join(f"{100 * h / r:.3g}" for h, r in zip(history[-1], scan.range))
        progress((j + 1) / (learn + 1), f"frame {j}: RMS {rms} % of the range")
        if j == learn or all(lrn.done for lrn in learners):
            return history
        fast = e[0].reshape(-1, player.n_fast).mean(axis=0)
        learners[0].update(np.fft.irfft(np.fft.rfft(fast) * keep, fast.size))
        learners[1].update(e[1])
    raise AssertionError("unreachable")


def _safe(axes: Sequence[ServoAxis], recorder: ServoRecorder, v_min: float) -> None:
    """Every generator stopped, every output ramped to max(VMI?, 0 V), whatever signals come
    before the last axis is safe."""
    with safe_stop():
        for axis in axes:
            safe_state(axis.amplifier, recorder, axis.generator, v_min)


@dataclass(frozen=True)
class ServoSetup:
    """The controller a raster plays on: its recorder, the controller axis of each stage
    axis (by the stage's names), a table point every ``rate`` servo cycles of ``cycle`` s,
    the amplifier's ``limits`` [V]."""

    recorder: ServoRecorder
    axes: dict[str, ServoAxis]
    rate: int
    cycle: float
    limits: tuple[float, float]

    @property
    def rate_hz(self) -> float:
        """The tables' rate [Hz]."""
        return 1.0 / (self.cycle * self.rate)

    def check(self, scan: RasterScan, axes: tuple[str, str]) -> None:
        """Refuse a ``scan`` the controller cannot play on ``axes`` (fast, slow) with tables
        over a frame (:func:`table_rate`, :func:`check_capacity`), before any is computed."""
        _, _, n_frame = table_rate(scan, self.cycle, self.rate)
        check_capacity(self.recorder, (self.axes[axes[0]], self.axes[axes[1]]), n_frame, n_frame)

    def play(
        self,
        scan: RasterScan,
        stage: Stage,
        tables: RasterTables | None,
        axes: tuple[str, str],
        coupling: bool,
        learn: int,
        progress: Progress,
    ) -> DetectedRun:
        """:func:`servo_raster` of ``scan`` on ``axes`` (fast, slow) of ``stage`` (the models),
        from ``tables`` (None: the models', the coupling taken out with ``coupling``)."""
        if tables is None:
            tables = raster_tables(
                scan,
                stage,
                self.rate_hz,
                axes=axes,
                compensate_coupling=coupling,
                fast_over_frame=True,
            )
        models = [FeedforwardModel.from_parameter_set(stage.axis(a).model) for a in axes]
        return servo_raster(
            self.recorder,
            (self.axes[axes[0]], self.axes[axes[1]]),
            scan,
            tables,
            (models[0], models[1]),
            self.rate,
            self.limits,
            learn,
            progress=progress,
        )
