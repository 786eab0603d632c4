"""Replaying the sample bags through the identifier node reproduces the offline
`piezo-stage identify` result on the same bag: the shipped graph
config/graphs/replay_identification.yaml (player -> identifier, separate processes, real DDS)
run by `piezo-stage launch`, ending by itself once the identifier has its result."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from std_srvs.srv import Trigger

from piezo_stage.cli import main
from piezo_stage.model.parameter_set import load_parameter_set
from piezo_stage.nodes.qos import LATCHED_QOS

from ros_support import call_idempotent, spin_until

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
NAMES = ("y0", "kappa_w", "rho", "sigma", "n")


NS = "/piezo"  # the probe node's namespace (conftest)


def _launch(cwd: Path, *args: str, timeout: float) -> subprocess.CompletedProcess:
    """``piezo-stage launch replay_identification ARGS`` run from ``cwd``, output merged."""
    cmd = [sys.executable, "-m", "piezo_stage.cli", "launch", "replay_identification"]
    return subprocess.run(
        [*cmd, "--color", "never", *args],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=timeout,
    )


def _offline(bag: str, degree: int, capsys, method: str = "auto") -> dict:
    assert (
        main(["identify", str(ROOT / bag), "--degree", str(degree), "--method", method, "--json"])
        == 0
    )
    return json.loads(capsys.readouterr().out)


def _replay(node, params: list[str], out_file: Path) -> list:
    """Launch replay_identification with ``params`` (the identifier writing ``out_file``), play
    once the probe is matched with the identifier, wait for its exit 0: the latched
    BoucWenParameters messages the probe got."""
    from piezo_stage_msgs.msg import BoucWenParameters

    got: list = []
    node.create_subscription(BoucWenParameters, "bouc_wen_parameters", got.append, LATCHED_QOS)
    cmd = [
        sys.executable,
        "-m",
        "piezo_stage.cli",
        "launch",
        "replay_identification",
        "--color",
        "never",
        "--param",
        "player.rate:=0.0",
        "--param",
        "player.start_paused:=true",
        "--param",
        f"identifier.output_file:={out_file}",
        *params,
    ]
    proc = subprocess.Popen(
        cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    try:
        # the identifier leaves once its matched subscribers have the latched result: play only
        # when this probe is matched with it (else, under load, a fast replay could end first)
        topic = "/piezo/bouc_wen_parameters"
        assert spin_until(
            node, lambda: node.count_publishers(topic) >= 1 or proc.poll() is not None, 120.0
        )
        spin_until(node, lambda: False, 1.0)
        resume = node.create_client(Trigger, "/piezo/player/resume")
        assert resume.wait_for_service(timeout_sec=60.0), "the player's ~/resume did not appear"
        # resuming twice is resuming: sent again until answered (Fast DDS drops a response
        # whose reader has not matched yet)
        # (a lost answer whose request did resume the player: it plays the bag and the launch
        # ends before a resend reaches it; its exit and log are checked below)
        answer = call_idempotent(
            node, resume, Trigger.Request(), timeout=60.0, gone=lambda: proc.poll() is not None
        )
        if answer is None and proc.poll() is None:  # say what the graph did meanwhile
            proc.terminate()
            log = proc.communicate(timeout=60)[0]
            raise AssertionError(f"~/resume unanswered for 60 s; the launch said:\n{log[-4000:]}")
        assert answer is None or answer.success
        spin_until(node, lambda: proc.poll() is not None, 240.0)
        if proc.poll() is None:
            proc.terminate()
        log = proc.communicate(timeout=60)[0]
        assert proc.returncode == 0, log[-4000:]  # the identifier (required) left with success
        assert "identifier exited with code 0" in log, log[-4000:]
        spin_until(node, lambda: bool(got), 5.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return got


@pytest.mark.parametrize(
    "bag, degree, params, method",
    [
        ("bags/ch10_identification", 2, [], "auto"),  # the graph as shipped (its bag and degree)
        (
            "bags/ch9_identification",
            1,
            ["--param", "player.bag:=bags/ch9_identification", "--param", "identifier.degree:=1"],
            "auto",
        ),
        # the fit by simulation error over the whole runs, as `identify --method fit`
        (
            "bags/ch9_identification",
            1,
            [
                "--param",
                "player.bag:=bags/ch9_identification",
                "--param",
                "identifier.degree:=1",
                "--param",
                "identifier.method:=fit",
            ],
            "fit",
        ),
    ],
)
@pytest.mark.slow
def test_replaying_a_sample_bag_through_the_identifier_gives_the_offline_result(
    node, bag, degree, params, method, tmp_path, capsys
):
    offline = _offline(bag, degree, capsys, method)
    assert offline["method"] == ("fit" if method == "fit" else "analytic")
    out_file = tmp_path / "replayed.yaml"
    got = _replay(node, params, out_file)
    replayed = load_parameter_set(out_file)
    p = replayed.bouc_wen
    assert list(p.kappa) == pytest.approx(offline["kappa"], rel=1e-9)
    for name in NAMES:
        assert getattr(p, name) == pytest.approx(offline[name], rel=1e-9, abs=1e-300), name
    assert p.input_sign == offline["input_sign"]
    assert replayed.w0 == pytest.approx(offline["w0"], rel=1e-9, abs=1e-12)
    assert f"identified from {offline['samples']} samples" in replayed.notes

    assert len(got) == 1, "the latched bouc_wen_parameters did not reach the probe"
    msg = got[0]
    assert list(msg.kappa) == pytest.approx(offline["kappa"], rel=1e-9)
    for name in NAMES:
        assert getattr(msg, name) == pytest.approx(offline[name], rel=1e-9, abs=1e-300), name
    assert msg.samples == offline["samples"] and msg.input_name == "voltage"
    assert msg.rms_error == pytest.approx(offline["rms_error"], rel=1e-6)


@pytest.mark.slow
def test_a_servo_record_replayed_with_its_lag_gives_the_offline_result(node, tmp_path, capsys):
    """The ch. 11 form recorded by a PI data recorder (`identify --device --bag`: position ->
    voltage, each reading paired with its two voltages' mean) replayed through the identifier
    with lag_samples 0.5 gives what `identify BAG --lag 0.5` gives; without, the held pairing's
    other numbers."""
    import numpy as np

    from piezo_stage.commands.emulate import emulated_controller
    from piezo_stage.hardware.emulators import EmulatorServer
    from piezo_stage.model.parameter_set import shipped_parameter_set
    from piezo_stage.model.stage_file import Stage, StageAxis

    rig = shipped_parameter_set("ch11_rig")
    stage = Stage("e727", (StageAxis("x", rig, "1"),), np.eye(1))
    bag = tmp_path / "servo11"
    with EmulatorServer(
        emulated_controller(stage, v_min=-30.0, v_max=130.0, sensor_noise=2e-9), tcp_port=0
    ) as server:
        args = ["identify", "--device", f"tcp://127.0.0.1:{server.port}", "--axis", "1"]
        args += ["--model-input", "displacement", "--period", "0.05", "--periods", "14,2"]
        assert main([*args, "--bag", str(bag), "--no-plot"]) == 0
    capsys.readouterr()
    offline = ["identify", str(bag), "--input-topic", "/piezo/displacement"]
    offline += ["--output-topic", "/piezo/voltage", "--steady-periods", "2", "--method", "analytic"]
    assert main([*offline, "--lag", "0.5", "--json", "--no-plot"]) == 0
    expected = json.loads(capsys.readouterr().out)
    out_file = tmp_path / "replayed.yaml"
    params = [f"player.bag:={bag}", "identifier.input:=displacement", "identifier.degree:=1"]
    params += ["identifier.steady_periods:=2", "identifier.method:=analytic"]
    params += ["identifier.lag_samples:=0.5"]
    got = _replay(node, [a for p in params for a in ("--param", p)], out_file)
    p = load_parameter_set(out_file).bouc_wen
    for name in ("kappa_w", "rho", "sigma", "n"):
        assert getattr(p, name) == pytest.approx(expected[name], rel=1e-9), name
    assert got and got[0].input_name == "displacement"
    assert main([*offline, "--json", "--no-plot"]) == 0
    held = json.loads(capsys.readouterr().out)
    assert abs(held["kappa_w"] / p.kappa_w - 1) > 1e-3  # what the node paired without the lag


def test_a_replay_whose_identification_fails_ends_the_launch_with_the_failure(tmp_path, capsys):
    """A fit the offline command refuses (residual above a tightened max_rms) is refused by the
    replayed identifier too: no parameter file, and the launch exits 1 with the reason logged."""
    bag = ROOT / "bags" / "ch10_identification"
    assert main(["identify", str(bag), "--degree", "2", "--max-rms", "1e-9"]) == 1
    assert "bad fit" in capsys.readouterr().err
    out_file = tmp_path / "replayed.yaml"
    cmd = [
        sys.executable,
        "-m",
        "piezo_stage.cli",
        "launch",
        "replay_identification",
        "--color",
        "never",
        "--param",
        "player.rate:=0.0",
        "--param",
        f"identifier.output_file:={out_file}",
        "--param",
        "identifier.max_rms:=1e-9",
    ]
    proc = subprocess.run(
        cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=240
    )
    assert proc.returncode == 1, proc.stdout[-4000:]
    assert "identification failed" in proc.stdout and "bad fit" in proc.stdout, proc.stdout[-4000:]
    assert "identifier exited with code 1" in proc.stdout
    assert not out_file.exists()


def test_runs_end_at_the_next_run_or_at_their_plan_done_mark():
    """The cut both the node and the offline command use: a run ends at the next run's first
    mark or at its first non-steady mark after a steady one (what follows the plan is no run)."""
    from piezo_stage.identification.io import intervals_from_marks

    marks = [
        (0.0, 0, False),
        (1.0, 0, True),
        (2.0, 1, False),
        (3.0, 1, True),
        (4.0, 1, False),
        (4.1, 1, False),
    ]
    assert intervals_from_marks(marks) == [(0, 0.0, 2.0), (1, 2.0, 4.0)]
    assert intervals_from_marks([m[:2] for m in marks]) == [
        (0, 0.0, 2.0),
        (1, 2.0, float("inf")),
    ]  # no flags
    assert intervals_from_marks(marks[:4]) == [
        (0, 0.0, 2.0),
        (1, 2.0, float("inf")),
    ]  # run 1 still going


@pytest.mark.slow
def test_the_graph_as_shipped_plays_the_whole_bag_and_gives_the_offline_result(tmp_path, capsys):
    """The default (player rate 5, from a folder outside the repository: the sample bag is found
    in the repository's bags/). The bag has 64 s of receive time without samples (75.6 s to
    140.02 s, its last burst); played at rate 5 that is 13 wall seconds, more than the
    identifier's settle_time: it took the stretch for silence and fitted what it had (rho=0.0047
    from 4825 samples, fit method), and the launch then stopped the player at 10 886-12 885 of
    its 15 287 messages without a word. Now the player's /clock moving is activity: the bag is
    played to its end and the analytic result is the offline one, to the last digit."""
    from piezo_stage.bag import bag_info

    offline = _offline("bags/ch10_identification", 2, capsys)
    topics = bag_info(ROOT / "bags" / "ch10_identification")["topics"]
    total = sum(topics[f"/piezo/{t}"]["count"] for t in ("voltage", "displacement", "excitation"))
    proc = _launch(tmp_path, timeout=900)
    log = proc.stdout
    assert proc.returncode == 0, log[-4000:]
    assert f"played {total} of {total} messages" in log, log[-4000:]
    assert "identifier exited with code 0" in log and "stopped after" not in log, log[-4000:]
    replayed = load_parameter_set(tmp_path / "identified_replay.yaml")  # relative: in the cwd
    p = replayed.bouc_wen
    assert list(p.kappa) == pytest.approx(offline["kappa"], rel=1e-9)
    for name in NAMES:
        assert getattr(p, name) == pytest.approx(offline[name], rel=1e-9, abs=1e-300), name
    assert f"identified from {offline['samples']} samples (analytic method)" in replayed.notes


def test_a_bag_the_player_cannot_find_ends_the_launch_with_exit_2_and_one_line(tmp_path):
    """A relative bag is looked for where the launch runs, then in the repository; found in
    neither, the player refuses it in one line and the launch ends with 2 instead of leaving
    the identifier waiting for ever."""
    proc = _launch(tmp_path, "--param", "player.bag:=no_such_bag", timeout=300)
    log = proc.stdout
    assert proc.returncode == 2, log[-4000:]
    errors = [line for line in log.splitlines() if "no bag at" in line]
    assert len(errors) == 1 and str(tmp_path / "no_such_bag") in errors[0], log[-4000:]
    assert "player exited with code 2" in log and "Traceback" not in log, log[-4000:]


def test_a_player_stopped_before_the_end_says_how_much_was_not_played(tmp_path):
    bag = ROOT / "bags" / "ch10_identification"
    cmd = [sys.executable, "-m", "piezo_stage.nodes.player", "--ros-args"]
    cmd += ["-r", "__ns:=/shortfall", "-p", f"bag:={bag}", "-p", "rate:=1.0"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        for line in proc.stderr:  # started: playing
            if "playing" in line:
                break
        proc.send_signal(signal.SIGINT)
        err = proc.communicate(timeout=60)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err[-3000:]  # a requested stop is no failure
    said = re.findall(
        r"stopped after (\d+) of 15290 messages, at \S+ s of 140.06 s: the rest of "
        + re.escape(str(bag))
        + " was not played",
        err,
    )
    assert len(said) == 1 and int(said[0]) < 15290, err[-3000:]


def test_a_moving_source_clock_is_no_silence():
    """A replay crossing a stretch of its bag without samples: the player's /clock moves, so the
    streams are not silent however long it lasts in wall time; once the clock stands still too
    (the bag played), silence comes as before."""
    from piezo_stage.identification.run_tracker import RunTracker

    tracker = RunTracker()
    tracker.mark(0.0, 0, False)
    tracker.mark(1.0, 0, True)
    tracker.mark(3.0, 1, False)
    tracker.poll(50, latest=2.0, now=0.0, settle_time=1.0, clock=2.0)
    for k in range(1, 40):  # 4 wall seconds, no sample, the clock advancing
        moving = tracker.poll(50, latest=2.0, now=0.1 * k, settle_time=1.0, clock=2.0 + 0.5 * k)
        assert not moving.silent and not moving.stalled
    tracker.poll(50, latest=2.0, now=5.2, settle_time=1.0, clock=21.5)  # clock now still
    assert tracker.poll(50, latest=2.0, now=5.3, settle_time=1.0, clock=21.5).stalled
