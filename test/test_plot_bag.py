"""piezo-stage plot: the PNGs follow what a bag holds, and are real, non-trivial images."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest

from piezo_stage.bag import BagWriter, header, message_class, serialize
from piezo_stage.cli import main
from piezo_stage.model.bouc_wen import model_output
from piezo_stage.model.parameter_set import shipped_parameter_set

pytestmark = pytest.mark.unit

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
NS = "/piezo"


def _msg(type_name: str, **fields):
    return serialize(
        message_class(f"piezo_stage_msgs/msg/{type_name}")(**fields),
        f"piezo_stage_msgs/msg/{type_name}",
    )


def _identification_bag(path: Path, with_parameters: bool) -> None:
    """Two runs of the ch. 10 patch (0-300 V, 100-400 V triangles, 200 samples a period)."""
    p = shipped_parameter_set("ch10_patch").bouc_wen
    t = np.arange(0.0, 40.0, 0.05)
    run = (t >= 20.0).astype(int)
    v = 300.0 * (1 - np.abs(((t / 10.0) % 1.0) * 2 - 1)) + 100.0 * run
    y = model_output(p, v)
    with BagWriter(path, compression="zstd") as w:
        for name, ty in (
            ("voltage", "Voltage"),
            ("displacement", "Displacement"),
            ("excitation", "ExcitationInfo"),
        ):
            w.add_topic(f"{NS}/{name}", f"piezo_stage_msgs/msg/{ty}")
        for k, (ti, vi, yi, ri) in enumerate(zip(t, v, y, run)):
            ns = int(round(ti * 1e9))
            w.write(f"{NS}/voltage", _msg("Voltage", header=header(ns), voltage=float(vi)), ns)
            w.write(
                f"{NS}/displacement",
                _msg("Displacement", header=header(ns), displacement=float(yi), status=0),
                ns,
            )
            if k % 10 == 0:
                w.write(
                    f"{NS}/excitation",
                    _msg(
                        "ExcitationInfo",
                        header=header(ns),
                        waveform="triangle",
                        period=10.0,
                        amplitude=300.0,
                        offset=100.0 * ri,
                        run=int(ri),
                        steady=True,
                    ),
                    ns,
                )
        if with_parameters:
            w.add_topic(f"{NS}/bouc_wen_parameters", "piezo_stage_msgs/msg/BoucWenParameters")
            ns = int(40e9)
            w.write(
                f"{NS}/bouc_wen_parameters",
                _msg(
                    "BoucWenParameters",
                    header=header(ns),
                    kappa=np.array(p.kappa),
                    y0=p.y0,
                    kappa_w=p.kappa_w,
                    rho=p.rho,
                    sigma=p.sigma,
                    n=p.n,
                    input_sign=p.input_sign,
                    input_name="voltage",
                    rms_error=0.0,
                    samples=400,
                ),
                ns,
            )


def _closed_loop_bag(path: Path) -> None:
    t = np.arange(0.0, 0.2, 1e-3)
    closed = t >= 0.05
    x1 = np.where(closed, 2e-6 * np.exp(-(t - 0.05) / 0.02), 2e-6)
    with BagWriter(path) as w:
        w.add_topic(f"{NS}/controller_state", "piezo_stage_msgs/msg/ControllerState")
        for ti, ci, xi in zip(t, closed, x1):
            ns = int(round(ti * 1e9))
            u_exc = 5.0 * math.sin(2 * math.pi * 100 * ti) if ci else 0.0
            w.write(
                f"{NS}/controller_state",
                _msg(
                    "ControllerState",
                    header=header(ns),
                    mode="pid_tv",
                    loop_closed=bool(ci),
                    saturated=False,
                    reference=1e-5,
                    x0=0.0,
                    x1=float(xi),
                    x2=float(-xi / 0.02),
                    u=float(-5e6 * xi + u_exc),
                    u_pid=float(-5e6 * xi),
                    u_excitation=u_exc,
                    u_ff=0.0,
                ),
                ns,
            )


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path} is not a PNG"
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def _assert_nontrivial(path: Path) -> None:
    import matplotlib.image as mpimg

    w, h = _png_size(path)
    assert w > 400 and h > 300
    img = mpimg.imread(path)
    assert img.std() > 0.05, f"{path} looks blank"
    colours = np.unique((img[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 20, f"{path} has only {len(colours)} colours"


def test_identification_bag_gives_loops_time_series_and_model(tmp_path, capsys):
    bag = tmp_path / "ident"
    _identification_bag(bag, with_parameters=True)
    assert main(["plot", str(bag), "--out", str(tmp_path / "png")]) == 0
    printed = capsys.readouterr().out.split()
    names = sorted(Path(p).name for p in printed)
    assert names == ["ident_hysteresis.png", "ident_model.png", "ident_timeseries.png"]
    for p in printed:
        _assert_nontrivial(Path(p))


def test_without_parameters_no_model_figure(tmp_path, capsys):
    bag = tmp_path / "raw"
    _identification_bag(bag, with_parameters=False)
    assert main(["plot", str(bag), "--out", str(tmp_path / "png")]) == 0
    names = sorted(Path(p).name for p in capsys.readouterr().out.split())
    assert names == ["raw_hysteresis.png", "raw_timeseries.png"]


def test_controller_state_gives_closed_loop_figure(tmp_path, capsys):
    bag = tmp_path / "loop"
    _closed_loop_bag(bag)
    assert main(["plot", str(bag), "--out", str(tmp_path / "png")]) == 0
    printed = capsys.readouterr().out.split()
    assert [Path(p).name for p in printed] == ["loop_closed_loop.png"]
    _assert_nontrivial(Path(printed[0]))


def test_bag_with_nothing_to_plot_is_an_error(tmp_path, capsys):
    bag = tmp_path / "empty"
    with BagWriter(bag) as w:
        w.add_topic(f"{NS}/excitation", "piezo_stage_msgs/msg/ExcitationInfo")
    assert main(["plot", str(bag), "--out", str(tmp_path / "png")]) == 1
    assert "nothing to plot" in capsys.readouterr().err
    assert not (tmp_path / "png").exists()


def test_steady_cycles_are_the_samples_the_excitation_marked_steady():
    """The hysteresis plot draws bold what the identification uses: in the shipped ch. 10 bag
    (7 periods per run, the last 2 recorded) the steady part is the end of each run."""
    from piezo_stage.plotting.bag_plots import _runs, _steady_mask, find_topics

    bag = Path(__file__).resolve().parents[1] / "bags" / "ch10_identification"
    topics = find_topics(bag)
    runs = _runs(bag, topics)
    assert len(runs) == 2
    for r in runs:
        mask = _steady_mask(bag, topics.excitation, r.t)
        assert not mask[0] and mask[-2]
        steady_span = r.t[mask][-1] - r.t[mask][0]
        assert 15.0 < steady_span <= 20.0 + 1e-6  # two 10 s periods, minus the run's last sample
        assert np.all(np.diff(mask.astype(int)) >= 0)  # settling first, then steady to the end
