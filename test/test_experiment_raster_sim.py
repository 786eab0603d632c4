"""`piezo-stage experiment raster --graph sim_scanner`: the simulated scanner's plant node in
lockstep under a controller node per axis, over real DDS, checked against the core loop
(``--graph core``: the same scanner, law and tables stepped in one process).

The nodes step the same mathematics as the core: without learning every figure agrees to far
below the scan's nanometre errors; the run is the same on every run (lockstep: no host timing
enters it), and both axes' tables learn through their controllers as they do in the core.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from piezo_stage.bag.reader import read_loop_samples
from piezo_stage.config_path import find_config
from piezo_stage.control.raster import RasterTables, raster_tables
from piezo_stage.control.scan import RasterScan
from piezo_stage.experiments.raster import RasterSpec, run_raster
from piezo_stage.model.stage_file import load_stage

pytestmark = [pytest.mark.ros, pytest.mark.slow]

#: 4 lines of 32 pixels at 4 Hz, a 1 kHz loop: two 1.25 s frames
SCAN = ["--lines", "4", "--pixels", "32", "--line-rate", "4", "--rate-hz", "1000"]
#: [m] the agreement asked of the nodes and the core: a thousandth of the scan's errors (nm)
SAME = 1e-12
STAGE = find_config("xy_scanner.yaml")
SCAN_4 = RasterScan(4, 32, 4.0, (20e-6, 10e-6), (20e-6, 10e-6))


def _raster(*extra: str) -> dict:
    argv = ["experiment", "raster", "--graph", "sim_scanner", *SCAN, "--json", *extra]
    proc = subprocess.run(
        [sys.executable, "-m", "piezo_stage.cli", *argv],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


def _same(nodes: dict, core: dict) -> None:
    for axis in ("x", "y"):
        for figure in ("rms_error", "max_error"):
            assert nodes["axes"][axis][figure] == pytest.approx(
                core["axes"][axis][figure], abs=SAME
            ), (axis, figure)
    np.testing.assert_allclose(nodes["line_rms"], core["line_rms"], rtol=0, atol=SAME)
    assert nodes["image"]["edges"] == core["image"]["edges"]


def test_the_nodes_scan_as_the_core_does_and_record_every_sample(tmp_path):
    bag = tmp_path / "bag"
    nodes = _raster("--bag", str(bag))
    core = run_raster(RasterSpec(STAGE, lines=4, pixels=32, line_rate=4.0, rate_hz=1000.0))
    assert nodes["graph"] == "sim_scanner" and "failed" not in nodes
    _same(nodes, core)
    # the bag: each axis's every sample, as a device graph's run is recorded
    for axis in ("x", "y"):
        columns = read_loop_samples(bag, f"/raster/{axis}/loop_samples")
        assert columns["stamp"].size >= 2500  # two 1.25 s frames, no sample missing:
        assert np.all(np.diff(columns["stamp"]) == 1_000_000)
        assert np.all(np.isfinite(columns["displacement"]))


def test_a_lockstep_raster_learns_as_the_core_does_the_same_on_every_run(tmp_path):
    """10 learning lines: the fast axis's table learns from each, the slow axis's line
    correction from lines 4 and 9 (past the fly-back's settling; the first a settling period),
    in the controller nodes as in the core: the same figures and the same tables."""
    tables, core_tables = tmp_path / "tables.json", tmp_path / "core.json"
    runs = [_raster("--learn", "10", "--table-out", str(tables)), _raster("--learn", "10")]
    for run in runs:
        run.pop("wall_time")
        run.pop("table_out", None)
    assert runs[0] == runs[1]
    spec = RasterSpec(STAGE, lines=4, pixels=32, line_rate=4.0, rate_hz=1000.0)
    core = run_raster(replace(spec, learn=10, table_out=core_tables))
    _same(runs[0], core)
    for nodes_line, core_line in zip(runs[0]["learning"], core["learning"], strict=True):
        for axis in ("x", "y"):
            assert nodes_line[axis] == pytest.approx(core_line[axis], abs=SAME, nan_ok=True)
    unlearned = run_raster(spec)
    assert runs[0]["axes"]["x"]["rms_error"] < 0.8 * unlearned["axes"]["x"]["rms_error"]
    saved, core_saved = RasterTables.load(tables), RasterTables.load(core_tables)
    model = raster_tables(SCAN_4, load_stage(STAGE), 1000.0)
    # both learned (by 0.2 V and 0.02 V here), as the core's: to 10 µV, far below a DAC's
    # step (0.1 mV for 20 bits over 130 V); the positions agree to 1e-15 m, a millionth of
    # the nanometre errors the tables learn from, and that millionth is what is left (1 µV)
    for name in ("fast", "slow"):
        learned, reference = getattr(saved, name).u, getattr(core_saved, name).u
        assert not np.allclose(learned, getattr(model, name).u, rtol=0, atol=1e-3), name
        np.testing.assert_allclose(learned, reference, rtol=0, atol=1e-5, err_msg=name)
