"""The ch. 11 experiments through the ROS graph (lockstep plant + controller nodes), mode by mode.

Simulated durations are kept short for the test time (a few hundred lockstep steps per wall
second on this machine); the figures asserted are the thesis's qualitative results at those
durations (see each test).
"""

from __future__ import annotations

import json

import pytest

from piezo_stage.bag.reader import read_messages
from piezo_stage.experiments import ExperimentError, UnknownExperimentError, make_plan, run_experiment

REG = 0.03  # simulated seconds of the regulation runs
PERT = 0.035  # simulated seconds of the perturbation runs (loop open 5-15 ms)


def test_plan_picks_a_stable_rate_and_rejects_bad_input():
    plan = make_plan("regulation", "pid")
    assert plan.rate_hz == 100e3 and plan.spectral_radius < 1  # 5-50 kHz are unstable (DESIGN §7)
    with pytest.raises(UnknownExperimentError):
        make_plan("nonsense", "pid")
    with pytest.raises(UnknownExperimentError):
        make_plan("regulation", "pi")
    with pytest.raises(ExperimentError, match="duration"):
        make_plan("perturbation", "pid", duration=0.01)


@pytest.fixture(scope="module")
def regulation():
    runs = {}

    def get(mode, A=None, **kwargs):
        key = (mode, A)
        if key not in runs:
            runs[key] = run_experiment("regulation", mode, duration=REG, gains={"A": A} if A else None, **kwargs)
        return runs[key]
    return get


def test_regulation_pid_regulates_with_nonzero_final_u(regulation, tmp_path):
    r = regulation("pid", bag=tmp_path / "bag", png_dir=tmp_path / "png")
    assert r["lost_samples"] <= 0 and r["samples"] >= int(REG * r["rate_hz"]) - 1
    assert r["final_abs_x1"] < 0.1 * r["max_abs_x1"]
    assert abs(r["final_u"]) > 5.0  # Fig. 11.5: u(∞) = κw·w(∞) ≠ 0
    msgs = list(read_messages(tmp_path / "bag"))
    assert len(msgs) == r["samples"]
    assert (tmp_path / "png" / "regulation_pid.png").stat().st_size > 10_000


def test_regulation_pid_sine_oscillation_shrinks_with_A(regulation):
    big, small = regulation("pid_sine", 15.0), regulation("pid_sine", 5.0)
    assert big["final_abs_x1"] < 0.2 * big["max_abs_x1"]
    assert small["oscillation_u"] < big["oscillation_u"]
    assert small["oscillation_x1"] < big["oscillation_x1"]


def test_regulation_pid_tv_regulates(regulation):
    r = regulation("pid_tv")
    assert r["final_abs_x1"] < 0.2 * r["max_abs_x1"] and r["final_abs_x2"] < 0.01


@pytest.fixture(scope="module")
def perturbation():
    return {mode: run_experiment("perturbation", mode, duration=PERT) for mode in ("pid", "pid_tv")}


def test_perturbation_opens_for_10_ms_at_72_V(perturbation):
    for r in perturbation.values():
        assert r["u_before"] == pytest.approx(200.0, abs=0.5)
        assert r["open_for"] == pytest.approx(0.010, abs=1e-3)  # services: a few steps of slip
        assert r["max_abs_error"] > 5e-6  # the 128 V drop moved the stage


def test_perturbation_pid_moves_the_equilibrium_pid_tv_less(perturbation):
    pid, tv = perturbation["pid"], perturbation["pid_tv"]
    assert abs(pid["u_change_relative"]) > 0.05  # Fig. 11.9: u after far from u before
    assert abs(tv["u_change"]) < abs(pid["u_change"])  # Fig. 11.11 trend (1 % needs ~0.2 s simulated)


def test_command_json(capsys):
    from piezo_stage.cli import main

    assert main(["experiment", "regulation", "--mode", "pid", "--duration", "0.005", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["mode"] == "pid" and out["samples"] >= 499
    assert main(["experiment", "perturbation", "--mode", "pid", "--duration", "0.01"]) == 2
