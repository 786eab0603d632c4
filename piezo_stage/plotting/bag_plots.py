"""Choose and draw the figures a bag supports (see :func:`plot_bag`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from piezo_stage.errors import PiezoStageError

from . import figures

if TYPE_CHECKING:
    from piezo_stage.identification.recording import Recording
    from piezo_stage.model.bouc_wen import BoucWenParameters

VOLTAGE = "piezo_stage_msgs/msg/Voltage"
DISPLACEMENT = "piezo_stage_msgs/msg/Displacement"
EXCITATION = "piezo_stage_msgs/msg/ExcitationInfo"
PARAMETERS = "piezo_stage_msgs/msg/BoucWenParameters"
CONTROLLER = "piezo_stage_msgs/msg/ControllerState"


class PlotError(PiezoStageError, ValueError):
    """The bag holds nothing that can be plotted (or the topics asked for are missing)."""


@dataclass(frozen=True)
class BagTopics:
    """The topics a bag's figures are drawn from (None: absent)."""

    voltage: str | None
    displacement: str | None
    excitation: str | None
    parameters: str | None
    controller_state: str | None


def _pick(types: dict[str, str], type_name: str, base: str) -> str | None:
    """The topic of that type named ``.../base`` (else the only topic of that type)."""
    found = sorted(t for t, ty in types.items() if ty == type_name)
    named = [t for t in found if t.rsplit("/", 1)[-1] == base]
    if named:
        return named[0]
    return found[0] if len(found) == 1 else None


def find_topics(bag: str | Path) -> BagTopics:
    """Find the voltage, displacement, excitation, parameter and controller-state topics."""
    from piezo_stage.bag.reader import topic_types

    types = topic_types(bag)
    return BagTopics(
        voltage=_pick(types, VOLTAGE, "voltage"),
        displacement=_pick(types, DISPLACEMENT, "displacement"),
        excitation=_pick(types, EXCITATION, "excitation"),
        parameters=_pick(types, PARAMETERS, "bouc_wen_parameters"),
        controller_state=_pick(types, CONTROLLER, "controller_state"),
    )


def _runs(bag: Path, topics: BagTopics) -> list[Recording]:
    """Recordings per excitation run (the identification's own run cutting) of a bag with
    voltage and displacement topics."""
    from piezo_stage.identification.io import load_bag

    assert topics.voltage and topics.displacement  # plot_bag asks only then
    if topics.excitation:
        return load_bag(bag, topics.voltage, topics.displacement, topics.excitation)
    return load_bag(bag, topics.voltage, topics.displacement)


def _steady_mask(bag: Path, topic: str, t: np.ndarray) -> np.ndarray:
    """True where the latest ExcitationInfo at or before each time says ``steady``."""
    from piezo_stage.bag.reader import read_messages
    from piezo_stage.bag.types import stamp_seconds

    marks = sorted(
        (stamp_seconds(m.header.stamp), bool(m.steady)) for _, _, m in read_messages(bag, [topic])
    )
    if not marks:
        return np.zeros(len(t), dtype=bool)
    times = np.array([m[0] for m in marks])
    flags = np.array([m[1] for m in marks])
    index = np.searchsorted(times, np.asarray(t), side="right") - 1
    return np.where(index >= 0, flags[np.clip(index, 0, None)], False)


def _loops(
    bag: Path,
    excitation: str | None,
    runs: list[Recording],
    voltage: tuple[np.ndarray, np.ndarray],
    displacement: tuple[np.ndarray, np.ndarray],
) -> tuple[list[tuple[str, np.ndarray, np.ndarray]], list[np.ndarray] | None]:
    """The hysteresis loops, one per run with the samples its excitation marked steady; without
    runs, the whole record (the voltage held at each displacement sample) and no marks."""
    if runs and excitation:
        loops = [(f"run {i}", r.input, r.output) for i, r in enumerate(runs)]
        return loops, [_steady_mask(bag, excitation, r.t) for r in runs]
    (t_v, v), (t_y, y) = voltage, displacement
    held = np.clip(np.searchsorted(t_v, t_y, side="right") - 1, 0, len(v) - 1)
    return [("recorded", v[held], y)], None


def _last_parameters(bag: Path, topic: str) -> BoucWenParameters | None:
    from piezo_stage.bag.reader import read_messages
    from piezo_stage.model.bouc_wen import BoucWenParameters

    last = None
    for _, _, msg in read_messages(bag, [topic]):
        last = msg
    if last is None:
        return None
    return BoucWenParameters(
        kappa=tuple(float(k) for k in last.kappa),
        kappa_w=last.kappa_w,
        rho=last.rho,
        sigma=last.sigma,
        n=last.n,
        y0=last.y0,
        input_sign=int(last.input_sign) or 1,
    )


def _model_curve(params: BoucWenParameters, rec: Recording) -> np.ndarray:
    """(10.15) simulated on the recorded input, w(0) from (10.18) clipped to [-1, 1]."""
    from piezo_stage.identification.analytic import initial_w
    from piezo_stage.model.bouc_wen import model_output

    w0 = initial_w(
        params.kappa, params.kappa_w, params.y0, float(rec.input[0]), float(rec.output[0])
    )
    return model_output(params, rec.input, w0=float(np.clip(w0, -1.0, 1.0)))


def _controller_series(bag: Path, topic: str) -> tuple[dict[str, np.ndarray], str] | None:
    """The controller state's series by field (and ``t``), and its last mode."""
    from piezo_stage.bag.reader import read_messages
    from piezo_stage.bag.types import stamp_seconds

    fields = ("x1", "x2", "u", "u_pid", "u_excitation", "loop_closed")
    rows: dict[str, list[float]] = {f: [] for f in fields}
    t: list[float] = []
    mode = ""
    for _, log_time, msg in read_messages(bag, [topic]):
        stamp = stamp_seconds(msg.header.stamp)
        t.append(stamp if stamp > 0 else 1e-9 * log_time)
        for f in fields:
            rows[f].append(getattr(msg, f))
        mode = msg.mode or mode
    if not t:
        return None
    out = {f: np.asarray(v, dtype=bool if f == "loop_closed" else float) for f, v in rows.items()}
    out["t"] = np.asarray(t)
    return out, mode


def plot_bag(
    bag: str | Path, out_dir: str | Path | None = None, *, stem: str | None = None
) -> list[Path]:
    """Write the PNGs a bag supports into ``out_dir`` (default: the bag's folder's parent
    ``<bag>_plots``) and return their paths:

    - ``<stem>_timeseries.png`` and ``<stem>_hysteresis.png`` when it has voltage and displacement
      (loops coloured by the excitation's run);
    - ``<stem>_model.png`` when it also has ``bouc_wen_parameters`` (model (10.15) vs data);
    - ``<stem>_closed_loop.png`` when it has ``controller_state``.
    """
    from piezo_stage.bag.reader import read_series

    bag = Path(bag)
    stem = stem or bag.name.removesuffix(".mcap")
    out = Path(out_dir) if out_dir is not None else bag.parent / f"{stem}_plots"
    topics = find_topics(bag)
    written: list[Path] = []
    if topics.voltage and topics.displacement:
        t_v, v, _ = read_series(bag, topics.voltage)
        t_y, y, status = read_series(bag, topics.displacement)
        if status is not None:
            ok = status == 0
            t_y, y = t_y[ok], y[ok]
        if len(t_v) > 1 and len(t_y) > 1:
            runs = _runs(bag, topics) if topics.excitation else []
            shaded = [(r.name, float(r.t[0]), float(r.t[-1])) for r in runs]
            written.append(
                figures.timeseries_figure(
                    out / f"{stem}_timeseries.png",
                    t_v,
                    v,
                    t_y,
                    y,
                    runs=shaded,
                    title=f"{stem}: voltage and displacement",
                )
            )
            loops, steady = _loops(bag, topics.excitation, runs, (t_v, v), (t_y, y))
            written.append(
                figures.hysteresis_figure(
                    out / f"{stem}_hysteresis.png",
                    loops,
                    steady=steady,
                    title=f"{stem}: hysteresis loops",
                )
            )
            params = _last_parameters(bag, topics.parameters) if topics.parameters else None
            if params is not None and runs:
                rec = runs[-1]
                written.append(
                    figures.model_figure(
                        out / f"{stem}_model.png",
                        rec.t,
                        rec.input,
                        rec.output,
                        _model_curve(params, rec),
                    )
                )
    if topics.controller_state:
        found = _controller_series(bag, topics.controller_state)
        if found is not None:
            s, mode = found
            written.append(
                figures.closed_loop_figure(
                    out / f"{stem}_closed_loop.png",
                    s["t"],
                    s["x1"],
                    s["x2"],
                    s["u"],
                    s["u_pid"],
                    s["u_excitation"],
                    s["loop_closed"],
                    mode=mode,
                    title=f"{stem}: closed loop ({mode})" if mode else "",
                )
            )
    if not written:
        raise PlotError(
            f"{bag}: nothing to plot (no voltage+displacement pair and no controller_state; "
            f"topics found: {topics})"
        )
    return written
