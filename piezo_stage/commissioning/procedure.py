"""The commissioning procedure of thesis ch. 11 as resumable steps (no rclpy here).

Steps (:class:`Step`): sweep → dynamics → bounds → gains → acceptance → report. Each step's
result is kept in ``DIR/state.json`` as soon as it is done (with the MCAP bag it recorded under
``DIR/bags/``); a rerun with the same options skips the steps already done. A step that fails
is recorded with its reason and the procedure stops there: the files the nodes load (parameter
set, bounds, controller parameters) stay in ``DIR/pending/`` until acceptance has passed and
only the report step moves them to ``DIR/`` (a failed run leaves ``DIR/FAILED.md``, no report).

The graph is a :class:`Rig` (``commissioning.graphs`` runs it over ROS); the maths is in
:mod:`.sweep`, :mod:`.design` and :mod:`piezo_stage.identification.dynamics`.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from piezo_stage.identification.dynamics import (
    DynamicsError,
    fit_step_response,
    predicted_response,
)
from piezo_stage.model.bouc_wen import BoucWenParameters
from piezo_stage.model.excitation import ExcitationPlan

from . import design, sweep
from .errors import CommissioningError
from .sweep import Series, SweepError, SweepSettings

Progress = Callable[[str, str], None]


class Step(str, Enum):
    SWEEP = "sweep"
    DYNAMICS = "dynamics"
    BOUNDS = "bounds"
    GAINS = "gains"
    ACCEPTANCE = "acceptance"
    REPORT = "report"


STEPS = tuple(Step)
STATE_FILE = "state.json"
FILES = {
    "parameter_set": "identified_rig.yaml",
    "bounds": "rig_bounds.yaml",
    "controller": "controller.yaml",
}


class StepFailed(CommissioningError):
    def __init__(self, step: Step, reason: str) -> None:
        super().__init__(f"{step.value}: {reason}")
        self.step, self.reason = step, reason


class OtherCommissioningError(CommissioningError, ValueError):
    """The output folder holds a commissioning with other options (nothing is touched)."""


class RigError(CommissioningError):
    """The graph did not deliver what a step needs (no sensor, a node died, a timeout)."""


class Rig(Protocol):
    """A graph the procedure can drive."""

    name: str
    rate_hz: float  #: sensor sample rate
    delay_samples: int  #: output delay of a loop on this graph
    v_min: float
    v_max: float

    @property
    def loop_rates(self) -> tuple[float, ...]:
        """Loop rates the graph can run (the lowest stable is used)."""
        ...

    @property
    def attempts(self) -> int:
        """Runs of a sweep frequency before its identification counts as failed."""
        ...

    def excite(self, plan: ExcitationPlan, bag: Path, label: str) -> Series: ...

    def accept(self, run: dict[str, Any], bag: Path, png_dir: Path) -> dict[str, Any]: ...


@dataclass
class Options:
    sweep: SweepSettings = field(default_factory=SweepSettings)
    step_low: float = 0.0  #: [V] rest voltage before the step
    step_size: float = 50.0  #: [V]
    step_duration: float = 0.01  #: [s] recorded after the step
    margin: float = 0.2
    gain_margin: float = 0.1
    k1: float | None = None
    f: float = design.THESIS_F
    rate_hz: float | None = None  #: loop rate (None: the lowest stable candidate)
    m: float | None = None  #: physical data instead of the step fit (as §11.2.1)
    c: float | None = None
    m_std: float = 0.0  #: [V s^2/m] standard uncertainty of the physical m (the bounds widen by it)
    c_std: float = 0.0  #: [V s/m]
    acceptance_duration: float = 0.4

    def to_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in self.__dict__.items() if k != "sweep"}
        out["sweep"] = self.sweep.to_dict()
        return out


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


class Commissioning:
    """Run (or resume) the procedure in ``out_dir`` on ``rig``."""

    def __init__(
        self, out_dir: Path, rig: Rig, options: Options, progress: Progress | None = None
    ) -> None:
        self.dir = Path(out_dir)
        self.rig = rig
        self.options = options
        self.progress = progress or (lambda step, text: None)
        self.state: dict[str, Any] = {}
        self.timings: dict[str, float] = {}

    # ------------------------------------------------------------------ state
    @property
    def _state_path(self) -> Path:
        return self.dir / STATE_FILE

    def _load_state(self) -> None:
        key = {
            "graph": self.rig.name,
            "rate_hz": self.rig.rate_hz,
            "options": _jsonable(self.options.to_dict()),
        }
        if self._state_path.exists():
            state = json.loads(self._state_path.read_text())
            if state.get("key") != key:
                raise OtherCommissioningError(
                    f"{self.dir} holds a commissioning with other options or graph; "
                    "use another folder or --restart"
                )
            self.state = state
        else:
            self.state = {"key": key, "steps": {}}
        self.state["steps"] = {k: v for k, v in self.state["steps"].items() if v.get("ok")}
        self.state.pop("failed", None)

    def _save(self) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)
        tmp = self._state_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(_jsonable(self.state), indent=1))
        tmp.replace(self._state_path)

    def result(self, step: Step) -> dict[str, Any]:
        result: dict[str, Any] = self.state["steps"][step.value]
        return result

    # ------------------------------------------------------------------ run
    def run(self) -> dict[str, Any]:
        """Run every step not yet done; return the summary. Raises StepFailed (recorded)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        self._load_state()
        (self.dir / "FAILED.md").unlink(missing_ok=True)
        for step in STEPS:
            if step.value in self.state["steps"]:
                self.progress(step.value, "done before (resumed)")
                continue
            started = time.monotonic()
            self.progress(step.value, "starting")
            try:
                result = getattr(self, f"_{step.value}")()
            except StepFailed as exc:
                self._fail(exc)
                raise
            except (SweepError, DynamicsError, design.DesignError, RigError) as exc:
                failed = StepFailed(step, str(exc))
                self._fail(failed)
                raise failed from exc
            result["ok"] = True
            result["wall_time"] = time.monotonic() - started
            self.state["steps"][step.value] = result
            self._save()
            self.progress(step.value, f"done in {result['wall_time']:.1f} s")
        return self.summary()

    def _fail(self, exc: StepFailed) -> None:
        self.state["failed"] = {"step": exc.step.value, "reason": exc.reason}
        self._save()
        done = ", ".join(self.state["steps"]) or "none"
        (self.dir / "FAILED.md").write_text(
            f"# Commissioning stopped at step `{exc.step.value}`\n\n{exc.reason}\n\nSteps "
            f"done: {done}. "
            "No gains were released: nothing in this folder is a complete commissioning.\n"
        )

    # ------------------------------------------------------------------ steps
    def _bag(self, name: str) -> Path:
        path = self.dir / "bags" / name
        if path.exists():
            shutil.rmtree(path)  # a step interrupted before it was recorded as done
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def _sweep(self) -> dict[str, Any]:
        settings = self.options.sweep
        settings.check(self.rig.rate_hz, self.rig.v_min, self.rig.v_max)
        done = self.state.get("sweep_partial", {})
        results = []
        for i, f in enumerate(settings.frequencies):
            key = f"{f:g}"
            if key in done:
                results.append(sweep.FrequencyResult(**done[key]))
                continue
            plan = settings.plan(f)
            self.progress(
                "sweep",
                f"{i + 1}/{len(settings.frequencies)}: {f:g} Hz ({plan.duration:.3g} s of "
                "excitation)",
            )
            attempts = max(1, int(getattr(self.rig, "attempts", 1)))
            for attempt in range(attempts):
                name = f"sweep_{key}Hz" + (f"_retry{attempt}" if attempt else "")
                series = self.rig.excite(plan, self._bag(name), f"sweep {f:g} Hz")
                sweep.check_clipping(series, plan, self.rig.v_min, self.rig.v_max)
                try:
                    res = sweep.identify_frequency(series, plan)
                    break
                except SweepError as exc:
                    if attempt + 1 == attempts:
                        raise SweepError(f"{exc} (after {attempts} runs)") from exc
                    # a real-time rig: a host that stalled the command stream for tens of ms
                    # bends one period; the run is repeated, the failure said
                    self.progress("sweep", f"{exc}; run again ({attempt + 2}/{attempts})")
            results.append(res)
            done[key] = res.to_dict()
            self.state["sweep_partial"] = done
            self._save()
        self.state.pop("sweep_partial", None)
        return {"frequencies": [r.to_dict() for r in results], "table": sweep.table(results)}

    def _bouc_wen(self) -> BoucWenParameters:
        tab = self.result(Step.SWEEP)["table"]
        y0 = float(np.mean([r["y0"] for r in self.result(Step.SWEEP)["frequencies"]]))
        return BoucWenParameters(
            kappa=(tab["kappa_x"]["mean"],),
            kappa_w=tab["kappa_w"]["mean"],
            rho=tab["rho"]["mean"],
            sigma=tab["sigma"]["mean"],
            n=tab["n"]["mean"],
            y0=y0,
            input_sign=1,
        )

    def _dynamics(self) -> dict[str, Any]:
        o = self.options
        if o.m is not None and o.c is not None:
            return {
                "source": "physical data (--m, --c)",
                "m": o.m,
                "c": o.c,
                "m_std": o.m_std,
                "c_std": o.c_std,
            }
        half = max(o.step_duration, 20.0 / self.rig.rate_hz)
        plan = ExcitationPlan(
            waveform="step",
            period=2.0 * half,
            low=o.step_low,
            amplitude=o.step_size,
            offsets=(0.0,),
            settle_periods=0,
            record_periods=1,
            hold="last",
        )
        series = self.rig.excite(plan, self._bag("dynamics_step"), "step response")
        sweep.check_clipping(series, plan, self.rig.v_min, self.rig.v_max)
        t, x = series.t_x, series.x
        if series.marks:
            t0 = min(m[0] for m in series.marks)
            keep = (t >= t0) & (t < t0 + plan.duration)
            t, x = t[keep], x[keep]
        idx = np.searchsorted(series.t_v, t, side="right") - 1
        u = series.v[np.clip(idx, 0, None)]
        bw = self._bouc_wen()
        try:
            fit = fit_step_response(t, u, x, bw, voltage_offset=bw.y0)
        except DynamicsError as exc:  # e.g. UnresolvedResonanceError: a 1 kHz sensor, 7 kHz
            raise DynamicsError(
                f"{exc}; give m and c from the stage's physical data (--m, --c, with --m-std, "
                "--c-std), as thesis §11.2.1 did"
            ) from exc
        t_fit, x_fit = predicted_response(fit, bw, t, u, voltage_offset=bw.y0)
        return {
            "source": f"{o.step_low:g} -> {o.step_low + o.step_size:g} V",
            **fit.to_dict(),
            "t": t.tolist(),
            "u": u.tolist(),
            "x": x.tolist(),
            "t_fit": t_fit.tolist(),
            "x_fit": x_fit.tolist(),
        }

    def _bounds(self) -> dict[str, Any]:
        tab = self.result(Step.SWEEP)["table"]
        dyn = self.result(Step.DYNAMICS)
        bounds = design.assumption2_bounds(
            tab, dyn["m"], dyn["m_std"], dyn["c"], dyn["c_std"], self.options.margin
        )
        nominal = design.nominal_plant(tab, dyn["m"], dyn["c"])
        pending = self.dir / "pending"
        pending.mkdir(exist_ok=True)
        design.write_bounds(
            pending / FILES["bounds"],
            bounds,
            nominal,
            self.options.margin,
            f"graph {self.rig.name}, {len(self.options.sweep.frequencies)} frequencies",
        )
        self._write_parameter_set(pending / FILES["parameter_set"], dyn)
        return {
            "bounds": bounds.to_dict(),
            "nominal": nominal.to_dict(),
            "margin": self.options.margin,
        }

    def _write_parameter_set(self, path: Path, dyn: dict[str, Any]) -> None:
        from dataclasses import replace

        from piezo_stage.model.parameter_set import Dynamics, ParameterSet, save_parameter_set

        bw = replace(self._bouc_wen(), y0=0.0)  # the dynamic form's y0 is a displacement offset
        save_parameter_set(
            ParameterSet(
                name=f"commissioned_{self.rig.name}",
                form="dynamic",
                bouc_wen=bw,
                dynamics=Dynamics(m=dyn["m"], c=dyn["c"]),
                notes="piezo-stage commission: sweep means, step-fitted m and c",
            ),
            path,
        )

    def _gains(self) -> dict[str, Any]:
        from piezo_stage.control.bounds import Bounds, NominalPlant

        b = self.result(Step.BOUNDS)
        o = self.options
        d = design.design_gains(
            Bounds.from_dict(b["bounds"]),
            NominalPlant.from_dict(b["nominal"]),
            k1=o.k1,
            gain_margin=o.gain_margin,
            f=o.f,
            rate_hz=o.rate_hz,
            delay_samples=self.rig.delay_samples,
            candidates=self.rig.loop_rates,
        )
        design.write_controller_params(
            self.dir / "pending" / FILES["controller"],
            d,
            (self.dir / FILES["bounds"]).resolve(),
            "sample",  # one step per sensor sample: the loop runs at the sensor's rate
        )
        return d.to_dict()

    def _acceptance(self) -> dict[str, Any]:
        # the controller runs on the files written: its parameter file, the pending bounds file
        params = design.read_controller_params(self.dir / "pending" / FILES["controller"])
        run = {
            "gains": {k: params[k] for k in ("k0", "k1", "k2", "kA", "f")},
            "rate_hz": params["rate_hz"],
            "delay_samples": params["delay_samples"],
            "bounds_file": str((self.dir / "pending" / FILES["bounds"]).resolve()),
            "kappa_x": self.result(Step.SWEEP)["table"]["kappa_x"]["mean"],
            "duration": self.options.acceptance_duration,
        }
        png = self.dir / "figures"
        png.mkdir(exist_ok=True)
        summary = self.rig.accept(run, self._bag("acceptance"), png)
        u_before = abs(summary["u_before"])  # 0: nothing held before opening, a failed run
        rel = abs(summary["u_after"] - summary["u_before"]) / u_before if u_before else math.inf
        summary["u_change_relative"] = rel
        if not rel <= 0.01:
            raise StepFailed(
                Step.ACCEPTANCE,
                f"u after the perturbation {summary['u_after']:.4g} V differs from u "
                f"before {summary['u_before']:.4g} V by {100 * rel:.3g} % (> 1 %)",
            )
        return summary

    def _report(self) -> dict[str, Any]:
        from .report import write_report

        for name in FILES.values():
            shutil.copy2(self.dir / "pending" / name, self.dir / name)
        # the controller file names the released bounds file (written at the gains step)
        paths = {k: str((self.dir / v).resolve()) for k, v in FILES.items()}
        report = write_report(self.dir, self.state, paths)
        return {"files": {**paths, "report": str(report)}}

    # ------------------------------------------------------------------ summary
    def summary(self) -> dict[str, Any]:
        s = self.state["steps"]
        tab = s["sweep"]["table"]
        ident = {k: tab[k]["mean"] for k in sweep.PARAMETERS}
        ident.update(
            m=s["dynamics"]["m"],
            c=s["dynamics"]["c"],
            m_std=s["dynamics"]["m_std"],
            c_std=s["dynamics"]["c_std"],
        )
        acc = s["acceptance"]
        summary: dict[str, Any] = _jsonable(
            {
                "graph": self.rig.name,
                "identified": ident,
                "table": tab,
                "bounds": s["bounds"]["bounds"],
                "margin": s["bounds"]["margin"],
                "gains": s["gains"]["gains"],
                "rate_hz": s["gains"]["rate_hz"],
                "delay_samples": s["gains"]["delay_samples"],
                "spectral_radius": s["gains"]["spectral_radius"],
                "k2_min": s["gains"]["k2_min"],
                "k0_max": s["gains"]["k0_max"],
                "closed_loop": {
                    k: acc.get(k)
                    for k in ("u_before", "u_after", "u_change_relative", "settling_time")
                },
                "files": s["report"]["files"],
                "wall_time": {k: v["wall_time"] for k, v in s.items()},
            }
        )
        return summary
