"""`piezo-stage experiment raster` on the simulated scanner: a small frame learned and its
image, JSON, PNGs and tables; scans it cannot run refused before anything moves."""

from __future__ import annotations

import json

import pytest

from piezo_stage.cli import main

pytestmark = pytest.mark.unit

SMALL = ["--lines", "4", "--pixels", "16", "--line-rate", "20", "--rate-hz", "1000"]


def raster(*extra: str) -> list[str]:
    return ["experiment", "raster", *SMALL, *extra]


def test_a_learned_frame_gives_its_figures_pngs_and_tables(tmp_path, capsys):
    table = tmp_path / "tables.json"
    argv = raster("--learn", "10", "--table-out", str(table), "--png", str(tmp_path), "--json")
    assert main(argv) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert "NaN" not in out  # strict JSON: a learning line without an image window is null
    summary = json.loads(out)
    assert set(summary["axes"]) == {"x", "y"} and len(summary["learning"]) == 10
    assert summary["learning"][0] == {"x": None, "y": None}  # the first frame's fly-back
    x, y = summary["axes"]["x"], summary["axes"]["y"]
    assert x["range"] == 20e-6 and y["range"] == 10e-6
    # the model is the plant here: learned, both axes far under 0.2 % of their range
    assert x["rms_error"] < 0.002 * x["range"] and y["rms_error"] < 0.002 * y["range"]
    assert summary["image"]["distortion_px_max"] < 0.5
    assert all(
        p.endswith(".png") and (tmp_path / p.rsplit("/", 1)[-1]).stat().st_size > 1000
        for p in summary["png"]
    )
    assert table.exists()
    # the saved tables replay on the same scan, and are refused on another
    assert main(raster("--table", str(table), "--json")) == 0
    replay = json.loads(capsys.readouterr().out)
    assert replay["axes"]["x"]["rms_error"] < 0.002 * x["range"]
    assert main(raster("--table", str(table), "--line-rate", "10")) == 2
    assert "the table holds 50 samples" in capsys.readouterr().err


def test_a_sample_without_edges_has_no_distortion_figure(tmp_path, capsys):
    """A smooth height map (a ramp): the image and errors, the distortion null in the JSON."""
    ramp = tmp_path / "ramp.csv"
    ramp.write_text("\n".join(",".join(f"{1e-9 * (i + j):g}" for j in range(8)) for i in range(4)))
    assert main(raster("--sample", str(ramp), "--json")) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    summary = json.loads(out)
    assert "NaN" not in out and summary["image"]["edges"] == 0
    assert summary["image"]["distortion_px_max"] is None
    assert main(raster("--sample", str(ramp))) == 0
    assert "no edges to measure the distortion on" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--pixels", "64"], "64 pixels per line at a 1000 Hz loop"),
        (["--line-rate", "200"], "samples per image line"),
        (["--range", "400e-6,10e-6"], "the fast axis needs"),
        (["--range", "20e-6"], "expected X,Y"),
        (["--sample", "no_such.png"], "no_such.png"),
        (["--lines", "0"], "lines must be"),
        (["--compensation", "feedback", "--learn", "3"], "--learn needs a feedforward"),
    ],
)
def test_a_scan_it_cannot_run_is_one_line_and_exit_2(extra, message, capsys):
    try:
        code = main(raster(*extra))
    except SystemExit as exc:  # argparse's own refusal
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1], err


def test_the_run_is_recorded_to_a_bag_each_axis_loop_samples(tmp_path, capsys):
    """--bag: every sample of both axes, as the loop graph records them (read back with the
    package's reader); an existing bag folder is refused before anything runs."""
    import numpy as np

    from piezo_stage.bag.reader import read_loop_samples

    bag = tmp_path / "scan_bag"
    assert main(raster("--bag", str(bag), "--json")) == 0, capsys.readouterr().err
    summary = json.loads(capsys.readouterr().out)
    assert summary["bag"] == str(bag)
    frame = summary["frame_time"]
    for axis in ("x", "y"):
        columns = read_loop_samples(bag, f"/raster/{axis}/loop_samples")
        # two frames at 1 kHz, every sample once, in order
        assert columns["stamp"].size == round(2 * frame * 1000)
        assert np.all(np.diff(columns["stamp"]) == 1_000_000)
        error = columns["displacement"] - columns["reference"]
        # the plant starts at rest at 0, the scan where it starts: after the first frame, the
        # errors the summary reports (largest over the image windows, turnarounds larger)
        later = error[columns["stamp"] >= frame * 1e9]
        assert (
            np.all(np.isfinite(error)) and summary["axes"][axis]["max_error"] <= np.abs(later).max()
        )
        assert np.abs(later).max() < 0.05 * summary["axes"][axis]["range"]
    with pytest.raises(SystemExit, match="^2$"):  # refused as the command line is parsed
        main(raster("--bag", str(bag)))
    assert "already exists" in capsys.readouterr().err
