"""The README's shell commands as a new user types them: relative paths from the folder the user
stands in, the gains command without --k2/--k0, `emulate rig` without --params, one-line
errors (busy ports, a wrong graph or node name, an existing recording), Ctrl-C on `commission`,
a `sim_closed_loop` that visibly regulates, and the help's summaries."""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from piezo_stage.cli import COMMANDS, main
from piezo_stage.config_path import ConfigNotFoundError, find_config, find_user_file

ROOT = Path(__file__).resolve().parents[1]


def one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


# --- paths: relative to where the user stands -------------------------------------------------
@pytest.mark.unit
def test_a_user_file_is_found_where_the_user_stands_first(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "model.yaml").write_text("x")
    assert find_user_file("model.yaml") == tmp_path / "model.yaml"
    assert find_user_file("./model.yaml").is_absolute()
    # a bare shipped name still falls back to the shipped config ...
    assert find_user_file("ch11_rig.yaml") == find_config("ch11_rig.yaml")
    # ... unless the user has a file of that name here
    (tmp_path / "ch11_rig.yaml").write_text("mine")
    assert find_user_file("ch11_rig.yaml") == tmp_path / "ch11_rig.yaml"
    with pytest.raises(ConfigNotFoundError) as err:
        find_user_file("other_rig.yaml")
    assert str(tmp_path / "other_rig.yaml") in str(err.value)


@pytest.fixture()
def in_folder_with_model(tmp_path, monkeypatch):
    """The user's folder, holding model.yaml (a dynamic parameter set) and other_rig.yaml."""
    monkeypatch.chdir(tmp_path)
    rig = find_config("ch11_rig.yaml").read_text()
    (tmp_path / "model.yaml").write_text(rig)
    (tmp_path / "other_rig.yaml").write_text(rig)
    return tmp_path


@pytest.mark.unit
@pytest.mark.parametrize("model", ["model.yaml", "./model.yaml"])
def test_tracking_reads_a_relative_model(in_folder_with_model, model, capsys):
    """`--model model.yaml` is read from the current folder: the run gets as far as the
    sampled-loop check (refused at 10 kHz, before any graph starts), not "not found"."""
    code = main(["experiment", "tracking", "--rate-hz", "10000", "--model", model])
    err = capsys.readouterr().err
    assert code == 2 and "not found" not in err
    assert "unstable sampled at 10000 Hz" in one_error_line(err)


@pytest.mark.unit
def test_tracking_resolves_every_user_path_at_the_door(in_folder_with_model):
    """The graph's processes may run elsewhere: what they get is absolute."""
    from piezo_stage.commands.experiment import _user_paths

    here = in_folder_with_model
    args = argparse.Namespace(
        model="model.yaml",
        plant_model="other_rig.yaml",
        trajectory="scan.csv",
        table="scan.json",
        table_out="out.json",
        png="plots",
        bag="bag",
        identify_model="identified.yaml",
    )
    _user_paths(args)
    assert args.model == str(here / "model.yaml")
    assert args.plant_model == str(here / "other_rig.yaml")
    assert args.identify_model == str(here / "identified.yaml")
    assert args.trajectory == str(here / "scan.csv") and args.table_out == str(here / "out.json")
    shipped = argparse.Namespace(**{**vars(args), "plant_model": "ch11_rig.yaml"})
    shipped.trajectory = "triangle"
    _user_paths(shipped)
    assert shipped.plant_model == str(find_config("ch11_rig.yaml"))
    assert shipped.trajectory == "triangle"


@pytest.mark.unit
@pytest.mark.parametrize("out", ["no_such_folder/model.yaml", "."])
def test_identify_model_refuses_an_unwritable_output_before_identifying(
    in_folder_with_model, out, capsys
):
    with pytest.raises(SystemExit, match="^2$"):  # refused as the command line is parsed
        main(["experiment", "tracking", "--identify-model", out])
    line = one_error_line(capsys.readouterr().err)  # no progress line: nothing was recorded
    assert "--identify-model" in line


@pytest.mark.unit
def test_tracking_json_progress_goes_to_stderr(in_folder_with_model, monkeypatch, capsys):
    import piezo_stage.commands.experiment as experiment

    def fake(args, progress):
        progress(0.5, "half way")
        return {"rms_error": 1e-9}

    monkeypatch.setattr(experiment, "_run_tracking", fake)
    assert main(["experiment", "tracking", "--model", "model.yaml", "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == {"rms_error": 1e-9} and "half way" in err


# --- gains as the README writes it -------------------------------------------------------------
@pytest.mark.unit
def test_gains_designs_k2_and_k0_then_checks_the_sampled_loop(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "my_rig_bounds.yaml").write_text(find_config("thesis_rig_bounds.yaml").read_text())
    readme = "--bounds my_rig_bounds.yaml --k1 5e6 --rate-hz 20000 --delay-samples 1 --json"
    code = main(["gains", *readme.split()])
    out = json.loads(capsys.readouterr().out)
    assert out["designed"] == ["k2", "k0"] and out["valid"] is True
    assert out["k2"] == pytest.approx(1.1 * out["k2_min"]) and 0 < out["k0"] < out["k0_max"]
    assert out["k0"] == pytest.approx(0.9 * out["k0_max"])
    # the thesis-like gains are unstable sampled at 20 kHz (README: 5-50 kHz): exit 1, said so
    assert out["discrete"]["rate_hz"] == 20000 and out["discrete"]["stable"] is False
    assert code == 1
    assert main(["gains", "--k1", "5e6", "--rate-hz", "1000"]) == 0  # stable at 1 kHz
    assert "k0 designed" in capsys.readouterr().out


# --- emulate ----------------------------------------------------------------------------------
@pytest.mark.unit
def test_emulate_rig_defaults_to_the_ch11_rig():
    from piezo_stage.commands import emulate

    parser = argparse.ArgumentParser()
    emulate.add_arguments(parser)
    args = parser.parse_args(["rig"])
    assert args.params == "ch11_rig.yaml"
    assert emulate.load_stage(args.params).parameter_set.dynamics is not None


@pytest.mark.ros
@pytest.mark.parametrize("device", ["gcs", "rig"])
def test_emulate_on_a_busy_port_is_one_line(device, capsys):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = str(busy.getsockname()[1])
        argv = ["emulate", "gcs", "--tcp", port] if device == "gcs" else ["emulate", "rig"]
        if device == "rig":
            argv += ["--amp-tcp", port]
        code = main(argv)
    line = one_error_line(capsys.readouterr().err)
    assert code == 2 and "cannot listen" in line and port in line


# --- launch -----------------------------------------------------------------------------------
@pytest.mark.unit
def test_a_wrong_graph_name_lists_the_shipped_graphs(capsys):
    assert main(["launch", "nosuch"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "sim_closed_loop" in line and "emulated_rig" in line and "tried" not in line
    assert main(["launch", "sim_closed_lop"]) == 2
    assert "did you mean 'sim_closed_loop'" in capsys.readouterr().err


@pytest.mark.unit
def test_a_misspelt_node_name_in_an_override_gets_a_suggestion(capsys):
    assert main(["launch", "sim_closed_loop", "--param", "controler.mode:=pid", "--dry-run"]) == 2
    assert "did you mean 'controller.mode'" in one_error_line(capsys.readouterr().err)


@pytest.mark.ros
def test_the_emulated_rig_graph_takes_a_free_port_of_its_own():
    """The emulator's port, the driver's URL and the sensor link agree; a second launch while
    the first one's emulator listens gets another port."""
    from piezo_stage.launch.graph import load_graph

    def endpoints(graph):
        rig = graph.node("rig").command
        port = int(rig[len(rig) - 1 - rig[::-1].index("--amp-tcp") + 1])
        link = rig[len(rig) - 1 - rig[::-1].index("--sensor-link") + 1]
        return (
            port,
            link,
            graph.node("voltage_driver").overrides["url"],
            graph.node("laser_reader").overrides["url"],
        )

    port, link, url, reader = endpoints(load_graph("emulated_rig"))
    assert url == f"tcp://127.0.0.1:{port}" and reader == link == f"run:rig_sensor_{port}"
    with socket.socket() as first:  # the first launch's emulator
        first.bind(("127.0.0.1", port))
        first.listen(1)
        second = endpoints(load_graph("emulated_rig"))
    assert second[0] != port and second[2] == f"tcp://127.0.0.1:{second[0]}"


# --- record -----------------------------------------------------------------------------------
@pytest.mark.unit
def test_record_onto_an_existing_folder_is_bad_input(tmp_path, capsys):
    (tmp_path / "my_run").mkdir()
    (tmp_path / "my_run" / "x").write_text("x")
    with pytest.raises(SystemExit, match="^2$"):  # refused as the command line is parsed
        main(["record", "-o", str(tmp_path / "my_run")])
    assert "already exists" in one_error_line(capsys.readouterr().err)


# --- validate ---------------------------------------------------------------------------------
@pytest.mark.unit
def test_validate_prints_no_empty_unit(tmp_path, capsys):
    from piezo_stage.identification.synthetic import CH10_PATCH
    from piezo_stage.model.bouc_wen import BoucWenParameters, model_output

    t = np.linspace(0.0, 20.0, 2001)
    v = 200.0 + 200.0 * np.sin(2 * math.pi * 0.2 * t)
    y = model_output(BoucWenParameters(**CH10_PATCH), v, w0=0.0)
    data = tmp_path / "sine_run.csv"  # no units in the header
    data.write_text("time,input,output\n" + "".join(f"{a},{b},{c}\n" for a, b, c in zip(t, v, y)))
    params = str(find_config("ch10_patch.yaml"))
    assert main(["validate", params, str(data), "--no-plot"]) == 0
    out = capsys.readouterr().out
    assert " ," not in out and " (" not in out.split("span")[1].split(",")[0]
    assert "names no unit" in out


# --- help -------------------------------------------------------------------------------------
@pytest.mark.unit
def test_every_help_summary_is_a_whole_sentence(capsys):
    """`piezo-stage --help` shows the first line of each command's docstring: that line must be
    its whole first paragraph (not cut mid-sentence)."""
    for name, module in COMMANDS.items():
        doc = importlib.import_module(f"piezo_stage.commands.{module}").__doc__ or ""
        first = doc.strip().split("\n\n")[0]
        assert "\n" not in first, name
        assert first.rstrip().endswith((".", ")")), name
    assert main(["--help"]) == 0
    assert all(
        line.rstrip().endswith((".", ")")) for line in capsys.readouterr().out.splitlines()[3:]
    )


# --- commission: Ctrl-C -----------------------------------------------------------------------
@pytest.mark.ros
@pytest.mark.slow
def test_ctrl_c_during_the_commissioning_sweep_is_one_line_and_130(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "piezo_stage.cli", "commission", str(tmp_path / "out")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env={
            **os.environ,
            "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        },
    )
    seen: list[str] = []
    try:
        deadline = time.monotonic() + 300  # generous: a loaded host starts the graph slowly
        while time.monotonic() < deadline:
            line = proc.stderr.readline()
            if not line:
                break
            seen.append(line)
            if "] graph: " in line:  # the sweep's graph is running
                break
        assert any("] graph: " in line for line in seen), "".join(seen)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    assert [line for line in err.splitlines() if "interrupted" in line] == [
        err.strip().splitlines()[-1]
    ]
    assert not (tmp_path / "out" / "report.md").exists()


# --- sim_closed_loop: a visible default ------------------------------------------------------
@pytest.mark.ros
@pytest.mark.slow
def test_sim_closed_loop_moves_the_stage_to_its_default_set_point(node):
    """As shipped, the loop takes the stage from x(0) = 0 to the graph's set point, 10 µm,
    and holds it there (before: set point 0, nothing moved)."""
    from piezo_stage.launch import Launcher
    from piezo_stage.nodes.qos import SENSOR_QOS
    from piezo_stage_msgs.msg import ControllerState

    ns = f"/as_written_{os.getpid()}"
    states: list = []
    node.create_subscription(ControllerState, f"{ns}/controller_state", states.append, SENSOR_QOS)
    import rclpy

    def x(state) -> float:
        return state.x1 + state.reference

    with Launcher("sim_closed_loop", namespace=ns, timeout=120.0, sink=lambda *a: None):
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and not (
            len(states) > 500 and abs(x(states[-1]) - 10e-6) < 0.1e-6
        ):
            rclpy.spin_once(node, timeout_sec=0.1)
    assert states, "no controller_state"
    assert states[-1].reference == pytest.approx(10e-6) and states[-1].loop_closed
    assert abs(x(states[-1]) - 10e-6) < 0.1e-6, x(states[-1])
    # it moved there: the plant starts at rest at its initial voltage (about 19 um at 200 V), and
    # the loop now holds 10 um with some 100 V. (The first states, on the way, can be gone before
    # this probe's best-effort subscription is matched: the lockstep graph runs fast.)
    graph = yaml.safe_load((ROOT / "config/graphs/sim_closed_loop.yaml").read_text())
    plant = next(n for n in graph["nodes"] if n["executable"] == "plant")["overrides"]
    assert abs(states[-1].u - plant["initial_voltage"]) > 50.0, (states[-1].u, plant)


@pytest.mark.unit
def test_launched_nodes_log_a_clock_time_not_epoch_seconds():
    """rcutils' default stamp is seconds since 1970 (`[INFO] [1795644374.78]`): the launch
    gives its nodes the time of day unless the user's or the graph's environment sets a format."""
    from piezo_stage.launch.commandline import process_env
    from piezo_stage.launch.graph import load_graph

    graph = load_graph("sim_closed_loop")
    env = process_env(graph.node("plant"), graph, base={})
    assert "{date_time_with_ms}" in env["RCUTILS_CONSOLE_OUTPUT_FORMAT"]
    mine = {"RCUTILS_CONSOLE_OUTPUT_FORMAT": "{message}"}
    assert process_env(graph.node("plant"), graph, base=mine)["RCUTILS_CONSOLE_OUTPUT_FORMAT"] == (
        "{message}"
    )
