"""Loading runs (CSV, bags) and the `piezo-stage identify` / `validate` commands."""

from __future__ import annotations

import json

import numpy as np
import pytest

from piezo_stage.cli import main
from piezo_stage.identification.errors import DataFormatError, SaturatedOutputError
from piezo_stage.identification.io import load_bag, load_csv, parse_column
from piezo_stage.identification.recording import Recording
from piezo_stage.identification.synthetic import CH9_EXAMPLE, CH10_PATCH, triangle_pair
from piezo_stage.model.bouc_wen import BoucWenParameters, model_output
from piezo_stage.model.parameter_set import load_parameter_set
from piezo_stage.model.signals import sine

pytestmark = pytest.mark.unit

CH9 = BoucWenParameters(**CH9_EXAMPLE)
PATCH = BoucWenParameters(**CH10_PATCH)


@pytest.fixture(scope="module")
def patch_runs():
    return triangle_pair(PATCH, 0.0, 300.0, 100.0, period=10.0, samples_per_branch=600, periods=3)


def write_csv(
    path,
    rec: Recording,
    header="time,input,output",
    scale=(1.0, 1.0, 1.0),
    preamble="",
    bom=False,
    sep=",",
):
    rows = np.column_stack(
        (rec.t * scale[0], rec.input * scale[1], rec.output * scale[2], np.zeros(len(rec)))
    )
    text = (
        preamble + header + "\n" + "\n".join(sep.join(f"{v:.17g}" for v in r) for r in rows) + "\n"
    )
    path.write_text(("\ufeff" if bom else "") + text, encoding="utf-8")
    return path


# ------------------------------------------------------------------ CSV


def test_parse_column_names_and_units():
    assert parse_column(" Output [µm] ") == ("output", "µm")
    assert parse_column('"time (ms)"') == ("time", "ms")
    assert parse_column("INPUT") == ("input", "")


def test_oscilloscope_style_csv(tmp_path, patch_runs):
    rec = patch_runs[0]
    path = write_csv(
        tmp_path / "scope.csv",
        rec,
        header="Time [ms]; Input (V) ;Output[um]; CH3 [V]",
        scale=(1e3, 1.0, 1e6),
        preamble="TDS 3014\nRecord Length;10000\n",
        bom=True,
        sep=";",
    )
    loaded = load_csv(path)
    assert np.allclose(loaded.t, rec.t) and np.allclose(loaded.output, rec.output, rtol=1e-12)
    assert loaded.input_unit == "V" and loaded.output_unit == "m"


def test_csv_errors(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,v,y\n0,1,2\n")
    with pytest.raises(DataFormatError, match="no header line"):
        load_csv(bad)
    bad.write_text("time,input,output\n0,1,2\n1,x,3\n")
    with pytest.raises(DataFormatError, match=":3: cannot read a number"):
        load_csv(bad)


# ------------------------------------------------------------------ identify command


def test_identify_json(tmp_path, patch_runs, capsys):
    a = write_csv(tmp_path / "a.csv", patch_runs[0])
    b = write_csv(tmp_path / "b.csv", patch_runs[1])
    out = tmp_path / "params.yaml"
    assert main(["identify", str(a), str(b), "--degree", "2", "--json", "--output", str(out)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["input_sign"] == -1 and len(d["kappa"]) == 2
    assert d["rho"] == pytest.approx(PATCH.rho, rel=1e-6)
    assert d["analytic"]["n"] == pytest.approx(PATCH.n, rel=1e-4)
    assert d["samples"] == 2 * 3 * 1200
    ps = load_parameter_set(out)
    assert ps.bouc_wen.sigma == pytest.approx(d["sigma"]) and ps.form == "static"


def test_identify_text_and_no_refine(tmp_path, patch_runs, capsys):
    a = write_csv(tmp_path / "a.csv", patch_runs[0])
    b = write_csv(tmp_path / "b.csv", patch_runs[1])
    assert main(["identify", str(a), str(b), "-N", "2", "--no-refine"]) == 0
    text = capsys.readouterr().out
    assert "kappa_2" in text and "input_sign -1" in text and "q = 100" in text


def test_identify_reports_errors_without_numbers(tmp_path, patch_runs, capsys):
    a = write_csv(tmp_path / "a.csv", patch_runs[0])
    clipped = Recording(
        patch_runs[1].t,
        patch_runs[1].input,
        np.minimum(patch_runs[1].output, np.percentile(patch_runs[1].output, 85)),
    )
    b = write_csv(tmp_path / "b.csv", clipped)
    assert main(["identify", str(a), str(b), "--json"]) == 2  # unusable input
    captured = capsys.readouterr()
    assert captured.out == "" and "saturated" in captured.err
    assert main(["identify", str(a), str(tmp_path / "missing.csv")]) == 2
    assert "cannot read" in capsys.readouterr().err
    assert main(["identify", str(a), "--method", "analytic"]) == 1
    assert "two runs" in capsys.readouterr().err


def test_identify_bad_fit_exit(tmp_path, patch_runs, capsys):
    a = write_csv(tmp_path / "a.csv", patch_runs[0])
    b = write_csv(tmp_path / "b.csv", patch_runs[1])
    assert main(["identify", str(a), str(b), "--degree", "1", "--no-refine", "--json"]) == 1
    captured = capsys.readouterr()
    assert captured.out == "" and "bad fit" in captured.err


# ------------------------------------------------------------------ bags


def write_bag(path, runs: list[Recording], status_fail: int | None = None):
    from piezo_stage.bag.types import header, message_class, serialize
    from piezo_stage.bag.writer import BagWriter

    V = message_class("piezo_stage_msgs/msg/Voltage")
    D = message_class("piezo_stage_msgs/msg/Displacement")
    E = message_class("piezo_stage_msgs/msg/ExcitationInfo")
    with BagWriter(path) as w:
        w.add_topic("/piezo/voltage", "piezo_stage_msgs/msg/Voltage")
        w.add_topic("/piezo/displacement", "piezo_stage_msgs/msg/Displacement")
        w.add_topic("/piezo/excitation", "piezo_stage_msgs/msg/ExcitationInfo")
        t_offset = 1.0
        for k, rec in enumerate(runs):
            start = int((t_offset + rec.t[0]) * 1e9)
            w.write(
                "/piezo/excitation",
                serialize(
                    E(
                        header=header(start),
                        waveform="triangle",
                        period=10.0,
                        amplitude=300.0,
                        offset=100.0 * k,
                        run=k,
                        steady=False,
                    )
                ),
                start,
            )
            for i, (t, v, y) in enumerate(zip(rec.t, rec.input, rec.output)):
                ns = int(round((t_offset + t) * 1e9))
                w.write("/piezo/voltage", serialize(V(header=header(ns), voltage=float(v))), ns)
                status = 3 if status_fail is not None and i == status_fail and k == 1 else 0
                w.write(
                    "/piezo/displacement",
                    serialize(D(header=header(ns + 1000), displacement=float(y), status=status)),
                    ns + 1000,
                )
            t_offset += rec.t[-1] + 1.0


def test_one_bag_holding_both_runs(tmp_path, patch_runs, capsys):
    bag = tmp_path / "ident_bag"
    write_bag(bag, list(patch_runs))
    runs = load_bag(bag)
    assert len(runs) == 2 and runs[0].input_unit == "V"
    assert np.allclose(runs[1].output, patch_runs[1].output[: len(runs[1])], rtol=0, atol=1e-14)
    assert main(["identify", str(bag), "--degree", "2", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["kappa_w"] == pytest.approx(PATCH.kappa_w, rel=1e-4)


def test_bag_with_invalid_sensor_samples(tmp_path, patch_runs):
    bag = tmp_path / "bad_bag"
    write_bag(bag, list(patch_runs), status_fail=100)
    with pytest.raises(SaturatedOutputError, match="TOO_FAR"):
        load_bag(bag)


# ------------------------------------------------------------------ validate command


def test_validate_on_a_sine(tmp_path, patch_runs, capsys):
    a = write_csv(tmp_path / "a.csv", patch_runs[0])
    b = write_csv(tmp_path / "b.csv", patch_runs[1])
    params = tmp_path / "p.yaml"
    assert main(["identify", str(a), str(b), "-N", "2", "--output", str(params)]) == 0
    capsys.readouterr()
    t = np.linspace(0.0, 20.0, 4001)
    v = sine(t, 0.2, 200.0, offset=200.0)  # 0..400 V, §10.3.3
    rec = Recording(t, v, model_output(PATCH, v, w0=0.1))
    data = write_csv(tmp_path / "sine.csv", rec, header="time [s],input [V],output [m]")
    out = tmp_path / "plots"
    assert main(["validate", str(params), str(data), "--out", str(out), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["rms_percent"] < 1e-4 and d["w0"] == pytest.approx(0.1, abs=1e-5)
    pngs = sorted(p.name for p in out.iterdir())
    assert pngs == ["sine_loop.png", "sine_timeseries.png"]
    assert all((out / p).stat().st_size > 10_000 for p in pngs)
    # a wrong model is visibly wrong
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text(params.read_text().replace("input_sign: -1", "input_sign: 1"))
    assert main(["validate", str(wrong), str(data), "--no-plot"]) == 0
    line = capsys.readouterr().out
    rms_percent = float(line.split("(")[1].split(" %")[0])
    assert rms_percent > 1.0


def test_validate_errors(tmp_path, capsys):
    assert main(["validate", str(tmp_path / "none.yaml"), str(tmp_path / "none.csv")]) == 2
    assert "error" in capsys.readouterr().err
