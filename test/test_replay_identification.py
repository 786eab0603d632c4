"""Replaying the sample bags through the identifier node reproduces the offline
`piezo-stage identify` result on the same bag: the shipped graph
config/graphs/replay_identification.yaml (player -> identifier, separate processes, real DDS)
run by `piezo-stage launch`, ending by itself once the identifier has its result."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from std_srvs.srv import Trigger

from piezo_stage.cli import main
from piezo_stage.model.parameter_set import load_parameter_set
from piezo_stage.nodes.qos import LATCHED_QOS

from ros_support import spin_until

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
NAMES = ("y0", "kappa_w", "rho", "sigma", "n")


NS = "/piezo"  # the probe node's namespace (conftest)


def _offline(bag: str, degree: int, capsys, method: str = "auto") -> dict:
    assert (
        main(["identify", str(ROOT / bag), "--degree", str(degree), "--method", method, "--json"])
        == 0
    )
    return json.loads(capsys.readouterr().out)


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
    from piezo_stage_msgs.msg import BoucWenParameters

    offline = _offline(bag, degree, capsys, method)
    assert offline["method"] == ("fit" if method == "fit" else "analytic")
    out_file = tmp_path / "replayed.yaml"
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
        future = resume.call_async(Trigger.Request())
        assert spin_until(node, future.done, 30.0) and future.result().success
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
