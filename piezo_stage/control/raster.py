"""A raster scan run on a simulated stage, in pure core: every axis's ch. 11 loop along its
part of a :class:`~.scan.RasterScan`, the feedforward learned line by line.

Each axis's feedforward is a table (:mod:`.learning`): the staircase the model says the sampled
loop needs along the axis's own reference (:func:`~.learning.sampled_feedforward`), over one
line period for the fast axis (it repeats every line) and over one frame for the slow one (a
staircase or ramp repeats every frame). Learning is per line, as a periodic trajectory learns
per period: the fast axis's table from each line's error, the slow axis's through a
correction of one line period added to every line of its frame (:class:`LineCorrection`: the
coupling it sees and its steps repeat every line). With ``compensate_coupling`` each axis's
feedforward follows its own frame (:mod:`.stage_control`). Frames run back to back; the
figures are the last frame's.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar

import numpy as np
from numpy.typing import NDArray

from piezo_stage.model.stage import AmplifierModel, CoupledStage
from piezo_stage.model.stage_file import Stage

from .controller import closed_pid
from .errors import ControlError
from .feedforward import Compensation, FeedforwardModel, check_learning
from .laws import THESIS_GAINS, Gains
from .learning import (
    FeedforwardTable,
    IterativeLearning,
    LearningConfig,
    LearningError,
    LineCorrection,
    feedforward_response,
    read_json,
    sampled_feedforward,
)
from .scan import RasterScan, ScanAxis
from .scan_image import Sample, ScanFigures, ScanImage, scan_figures, scan_image
from .stage_control import (
    SCANNER_VOLTS,
    AxisReference,
    StageController,
    StageReference,
    StageRun,
    simulate_stage,
)
from .trajectory import SetPoint
from .voltage_range import PID_MARGIN

__all__ = [
    "RasterRun",
    "RasterTables",
    "check_voltage_need",
    "learning_history",
    "raster_run",
    "raster_tables",
]

Progress = Callable[[float, str], None]

#: file format of a raster's saved tables
RASTER_TABLES_FORMAT = "piezo_stage raster feedforward tables 1"
#: learning iterations of the slow axis's frame table against the model (a frame is long)
FRAME_ITERATIONS = 3


@dataclass
class RasterRun:
    """A run of :func:`raster_run`: ``desired`` and ``measured`` (2, samples) [m] of the fast
    and slow axes, ``u`` (2, samples) [V]; ``learning`` the RMS error of each learning line's
    image window per axis [m]; ``tables`` the feedforward tables (learned, if it learned).
    """

    scan: RasterScan
    t: NDArray[np.float64]
    desired: NDArray[np.float64]
    measured: NDArray[np.float64]
    u: NDArray[np.float64]
    learning: list[tuple[float, float]] = field(default_factory=list)
    tables: RasterTables | None = None
    #: why the run failed (its loop opened, its record has a gap), None when it did not
    failed: str | None = None
    #: the axes under feedback (False: the feedforward played alone, the command is u_ff)
    closed_loop: ClassVar[bool] = True

    def last_frame(self) -> NDArray[np.bool_]:
        """The samples of the last whole frame the run holds."""
        frame, t = self.scan.frame_time, self.t
        dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
        k = math.floor((t[-1] + dt) / frame + 1e-9) - 1
        keep: NDArray[np.bool_] = (t >= k * frame - 1e-9 * frame) & (t < (k + 1) * frame - 0.5 * dt)
        return keep

    def figures(self, sample: Sample) -> ScanFigures:
        """The last frame's errors and distortion (:func:`~.scan_image.scan_figures`)."""
        keep = self.last_frame()
        return scan_figures(self.scan, sample, self.t[keep], self.measured[:, keep])

    def image(self, sample: Sample) -> ScanImage:
        """The last frame's image of ``sample``."""
        keep = self.last_frame()
        return scan_image(self.scan, sample, self.t[keep], self.measured[:, keep])


def _window_rms(scan: RasterScan, t: NDArray[np.float64], e: NDArray[np.float64]) -> float:
    inside = scan.line_index(t)[0] >= 0
    return float(np.sqrt(np.mean(e[inside] ** 2))) if inside.any() else math.nan


def learning_history(
    scan: RasterScan, t: NDArray[np.float64], error: NDArray[np.float64], lines: int
) -> list[tuple[float, float]]:
    """The RMS error (2, samples) [m] of each of the first ``lines`` line periods' image
    windows, per axis (NaN for a period without one: a fly-back).
    """
    out = []
    for j in range(lines):
        now = (t >= j * scan.period) & (t < (j + 1) * scan.period)
        out.append(
            (_window_rms(scan, t[now], error[0, now]), _window_rms(scan, t[now], error[1, now]))
        )
    return out


@dataclass(eq=False)
class RasterTables:
    """The feedforward of a scan: the fast axis's over one line period, the slow axis's over
    one frame (saved together, with the scan they were made for in ``meta``).
    """

    fast: FeedforwardTable
    slow: FeedforwardTable
    meta: dict[str, Any] = field(default_factory=dict)

    def matches(self, scan: RasterScan, rate_hz: float) -> str:
        """'' when the tables serve ``scan`` at ``rate_hz``, else why not (the fast axis's
        table may be a frame's, as :func:`raster_tables` makes it with ``fast_over_frame``).
        """
        frame = int(round(scan.frame_time * rate_hz))
        fast = scan.frame_time if len(self.fast) == frame else scan.period
        for name, table, seconds in (
            ("fast", self.fast, fast),
            ("slow", self.slow, scan.frame_time),
        ):
            why = table.matches(rate_hz, int(round(seconds * rate_hz)))
            if why:
                return f"{name} axis: {why}"
        return ""

    def save(self, path: str | Path) -> Path:
        """Write both tables as one JSON file."""
        path = Path(path)
        data = {"format": RASTER_TABLES_FORMAT, "meta": self.meta}
        data.update(fast=self.fast.to_dict(), slow=self.slow.to_dict())
        path.write_text(json.dumps(data, indent=1))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "RasterTables":
        """Read what :meth:`save` wrote; :class:`~.learning.LearningError` when it cannot."""
        data = read_json(path, "raster feedforward tables")
        if not isinstance(data, dict) or data.get("format") != RASTER_TABLES_FORMAT:
            raise LearningError(f"{path} is not a raster's tables ({RASTER_TABLES_FORMAT!r})")
        return cls(
            FeedforwardTable.from_dict(data.get("fast"), path),
            FeedforwardTable.from_dict(data.get("slow"), path),
            dict(data.get("meta", {})),
        )


def _tables(
    scan: RasterScan,
    reference: StageReference,
    models: list[FeedforwardModel],
    fast: int,
    slow: int,
    rate_hz: float,
    fast_over_frame: bool = False,
) -> RasterTables:
    """What the models say each axis needs along its own reference: a line of the fast axis
    (``fast_over_frame``: a frame, which holds what the slow axis's coupling asks of it line by
    line), a frame of the slow one, both in the periodic steady state (a frame after the first).
    """
    n_line = int(round(scan.period * rate_hz))
    n_frame = int(round(scan.frame_time * rate_hz))
    t_line = scan.flyback_lines * scan.period + np.arange(n_line) / rate_hz
    t_frame = scan.frame_time + np.arange(n_frame) / rate_hz
    t_fast = t_frame if fast_over_frame else t_line
    return RasterTables(
        sampled_feedforward(models[fast], reference.own(t_fast)[0][fast], rate_hz),
        sampled_feedforward(
            models[slow], reference.own(t_frame)[0][slow], rate_hz, iterations=FRAME_ITERATIONS
        ),
    )


def raster_tables(
    scan: RasterScan,
    model_stage: Stage,
    rate_hz: float,
    *,
    axes: tuple[str, str] = ("x", "y"),
    compensate_coupling: bool = True,
    fast_over_frame: bool = False,
) -> RasterTables:
    """The feedforward tables the models say ``scan`` needs at ``rate_hz`` (what
    :func:`raster_run` starts from; ``fast_over_frame``: the fast axis's over a frame).
    """
    fast, slow = _scan_axes(model_stage, axes)
    _line_samples(scan, rate_hz)
    reference = StageReference(
        model_stage, _references(scan, model_stage, fast, slow), compensate_coupling
    )
    models = [FeedforwardModel.from_parameter_set(a.model) for a in model_stage.axes]
    return _tables(scan, reference, models, fast, slow, rate_hz, fast_over_frame)


def check_voltage_need(
    tables: RasterTables, u_limits: tuple[float, float], margin: float = PID_MARGIN
) -> None:
    """Refuse (:class:`~.errors.ControlError`) a scan whose feedforward leaves the amplifier's
    range less ``margin`` of its span at either end (the PID's share).
    """
    lo, hi = u_limits
    room = margin * (hi - lo)
    for name, table in (("fast", tables.fast), ("slow", tables.slow)):
        need = (float(table.u.min()), float(table.u.max()))
        if need[0] < lo + room or need[1] > hi - room:
            raise ControlError(
                f"the {name} axis needs {need[0]:.4g} to {need[1]:.4g} V, the amplifier gives "
                f"{lo:g} to {hi:g} V (less {100 * margin:g} % for the PID): a smaller range "
                "or another centre"
            )


def _references(scan: RasterScan, stage: Stage, fast: int, slow: int) -> list[AxisReference]:
    refs: list[AxisReference] = [SetPoint(float(r)) for r in stage.rest_outputs()]
    refs[fast], refs[slow] = ScanAxis(scan, 0), ScanAxis(scan, 1)
    return refs


def raster_run(
    scan: RasterScan,
    model_stage: Stage,
    plant_stage: Stage,
    rate_hz: float,
    *,
    axes: tuple[str, str] = ("x", "y"),
    compensation: Compensation | str = Compensation.BOTH,
    compensate_coupling: bool = True,
    learn_lines: int = 0,
    tables: RasterTables | None = None,
    frames: int = 2,
    gains: Gains = THESIS_GAINS,
    u_limits: tuple[float, float] = SCANNER_VOLTS,
    progress: Progress | None = None,
    watch: Callable[[RasterRun], None] | None = None,
) -> RasterRun:
    """``frames`` frames (more if the learning lasts: the last is a whole frame after it) of
    ``scan`` on the simulated ``plant_stage`` (fast, slow = ``axes``;
    any other axis holds its rest position), controlled with ``model_stage`` (the identified
    one) under ``compensation``, the plant at rest at the scan's start. ``learn_lines`` N:
    both tables learn over the first N line periods (the slow one from those that are image
    lines), then stay; ``tables``: learned ones replayed. ``watch`` is given each stretch of
    the run as it is computed (a line while learning, then frames) as a :class:`RasterRun` of
    the scan's axes (``learning`` empty, ``tables`` None).
    """
    compensation = Compensation(compensation)
    fast, slow = _scan_axes(model_stage, axes)
    n_line = _line_samples(scan, rate_hz)
    reference = StageReference(
        model_stage, _references(scan, model_stage, fast, slow), compensate_coupling
    )
    uses_ff = compensation.feeds_forward
    models = [FeedforwardModel.from_parameter_set(a.model) for a in model_stage.axes]
    check_learning(compensation, learn_lines > 0, "learn_lines")
    if tables is not None and tables.matches(scan, rate_hz):
        raise ControlError(f"feedforward tables: {tables.matches(scan, rate_hz)}")
    if uses_ff:
        tables = tables or _tables(scan, reference, models, fast, slow, rate_hz)
    by_axis = {fast: tables.fast, slow: tables.slow} if uses_ff and tables else {}
    pids = [
        closed_pid(gains, *u_limits, compensation, model if uses_ff else None, by_axis.get(i))
        for i, model in enumerate(models)
    ]
    loop = _Loop(
        scan,
        StageController(model_stage, pids, compensate_coupling),
        CoupledStage(plant_stage, amplifiers=[AmplifierModel(*u_limits) for _ in plant_stage.axes]),
        reference,
        rate_hz,
        progress or (lambda fraction, text: None),
        None if watch is None else lambda part: watch(_scan_part(scan, part, (fast, slow))),
    )
    history: list[tuple[float, float]] = []
    if learn_lines > 0:
        assert tables is not None  # refused above
        feedback = None if compensation is Compensation.FEEDFORWARD else gains
        config = LearningConfig(u_min=u_limits[0], u_max=u_limits[1])
        responses = [
            feedforward_response(models[i], rate_hz, n_line, gains=feedback) for i in (fast, slow)
        ]
        learners = (
            IterativeLearning(tables.fast, responses[0], config, models[fast]),
            LineCorrection(
                tables.slow, n_line, scan.flyback_lines, responses[1], config, models[slow]
            ),
        )
        history = loop.learn(learn_lines, learners, (fast, slow))
    loop.run_frames(frames)
    pick = [fast, slow]

    def stack(name: str) -> NDArray[np.float64]:
        return np.concatenate([getattr(c, name)[:, pick] for c in loop.chunks]).T.copy()

    return RasterRun(
        scan,
        np.concatenate([c.t for c in loop.chunks]),
        stack("reference"),
        stack("measured"),
        stack("u"),
        history,
        tables,
    )


def _scan_part(scan: RasterScan, run: StageRun, axes: tuple[int, int]) -> RasterRun:
    """The scan's axes of a stretch of a run."""
    pick = list(axes)
    return RasterRun(
        scan, run.t, run.reference[:, pick].T, run.measured[:, pick].T, run.u[:, pick].T
    )


def _scan_axes(stage: Stage, axes: tuple[str, str]) -> tuple[int, int]:
    names = [a.name for a in stage.axes]
    if len(set(axes)) != 2 or not set(axes) <= set(names):
        raise ControlError(f"scan axes {axes} must be two different axes of the stage {names}")
    return names.index(axes[0]), names.index(axes[1])


def _line_samples(scan: RasterScan, rate_hz: float) -> int:
    n = scan.period * rate_hz
    if abs(n - round(n)) > 1e-6 * n:
        raise ControlError(
            f"a line ({scan.period:g} s) is {n:.6g} samples at {rate_hz:g} Hz: the "
            "feedforward tables need a whole number"
        )
    return round(n)


@dataclass
class _Loop:
    """The simulated loop of a raster, run in chunks that continue one another."""

    scan: RasterScan
    controller: StageController
    plant: CoupledStage
    reference: StageReference
    rate_hz: float
    say: Progress
    watch: Callable[[StageRun], None] | None = None
    chunks: list[StageRun] = field(default_factory=list)

    @property
    def n(self) -> int:
        """Samples run so far."""
        return sum(len(c.t) for c in self.chunks)

    def step(self, samples: int) -> StageRun:
        """Run on for ``samples`` samples."""
        run = simulate_stage(
            self.controller,
            self.plant,
            self.reference,
            self.rate_hz,
            samples / self.rate_hz,
            self.n / self.rate_hz,
        )
        self.chunks.append(run)
        if self.watch is not None:
            self.watch(run)
        return run

    def learn(
        self,
        lines: int,
        learners: tuple[IterativeLearning, LineCorrection],
        axes: tuple[int, int],
    ) -> list[tuple[float, float]]:
        """``lines`` line periods, each axis's learner fed its error (the slow one only on
        the frame's image lines); the RMS error of each line's image window per axis.
        """
        scan, history = self.scan, []
        n_line = round(scan.period * self.rate_hz)
        for j in range(lines):
            run = self.step(n_line)
            self.say((j + 1) / lines, f"learning: {j + 1}/{lines} lines")
            e = run.measured - run.reference
            history.append(
                (_window_rms(scan, run.t, e[:, axes[0]]), _window_rms(scan, run.t, e[:, axes[1]]))
            )
            learners[0].update(e[:, axes[0]])
            if learners[1].learns(j):
                learners[1].update(e[:, axes[1]])
        return history

    def run_frames(self, frames: int) -> None:
        """On to at least ``frames`` frames from the start, and a whole frame after now."""
        n_frame = round(self.scan.frame_time * self.rate_hz)
        count = max(frames, -(-self.n // n_frame) + 1)  # ceil(n / n_frame) + 1
        start = self.n  # a stage of its own: its bar from 0 to 100 %
        while self.n < count * n_frame:
            self.step(n_frame - self.n % n_frame)
            done = (self.n - start) / (count * n_frame - start)
            self.say(done, f"frames: {self.n // n_frame}/{count}")
