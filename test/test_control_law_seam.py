"""A control law behind the seam: a law registered here, and nowhere else, is a ``mode`` of the
controller, of its node's parameter table, of ``experiment --mode`` and of ``gains --law``; one
named in ``PIEZO_STAGE_LAWS`` runs in the controller node of a graph's own process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from piezo_stage.bag.reader import read_messages
from piezo_stage.cli import main
from piezo_stage.control import laws
from piezo_stage.control.controller import ControllerConfig, TimeVaryingPID
from piezo_stage.control.discrete import check_sampled_loop
from piezo_stage.control.errors import ControllerConfigError, GainError
from piezo_stage.control.laws import (
    LAW_NAMES,
    PID,
    THESIS_GAINS,
    Gains,
    LinearGains,
    register,
    unregister,
)
from piezo_stage.control.theorem4 import GainReport
from piezo_stage.errors import PiezoStageError
from piezo_stage.experiments import make_plan
from piezo_stage.nodes.controller import PARAMETERS

from ros_support import ROOT

NAME = "pd_only"

#: the law, as a user's module would hold it (also written to a file for the graph's processes)
LAW_MODULE = f'''
from piezo_stage.control.laws import register
from piezo_stage.control.theorem4 import GainReport


class Proportional:
    """u = -k1 x1 - k2 x2: no integral."""

    name = "{NAME}"
    equation = "{NAME}: u = -k1 x1 - k2 x2"
    gains = ("k1", "k2")

    def split(self, gains, t, x0, x1, x2):
        u = -gains.k1 * x1 - gains.k2 * x2
        return u, 0.0 * u

    def x0_coefficient(self, gains, t):
        return 0.0

    def check(self, gains):
        return None

    def theorem4(self, bounds, gains):
        return GainReport(gains.k1, None, None, None, None, 0.0, None, None, None, True)

    def sampled_gains(self, gains, rate_hz, most):
        return [(0.0, gains.k1, gains.k2)]

    def design(self, bounds, gains, margin, loop, given):
        return {{}}


LAW = register(Proportional())
'''


class Proportional:
    """The law of :data:`LAW_MODULE`, typed."""

    name = NAME
    equation = f"{NAME}: u = -k1 x1 - k2 x2"
    gains = ("k1", "k2")

    def split(self, gains: Gains, t, x0, x1, x2):  # type: ignore[no-untyped-def]
        u = -gains.k1 * x1 - gains.k2 * x2
        return u, 0.0 * u

    def x0_coefficient(self, gains: Gains, t: float) -> float:
        return 0.0

    def check(self, gains: Gains) -> None:
        return None

    def theorem4(self, bounds, gains: Gains) -> GainReport:  # type: ignore[no-untyped-def]
        return GainReport(gains.k1, None, None, None, None, 0.0, None, None, None, True)

    def sampled_gains(self, gains: Gains, rate_hz: float, most: int) -> list[LinearGains]:
        return [(0.0, gains.k1, gains.k2)]

    def design(self, bounds, gains, margin, loop, given) -> dict[str, float]:  # type: ignore[no-untyped-def]
        return {}


@pytest.fixture()
def pd_only():
    law = register(Proportional())
    try:
        yield law
    finally:
        unregister(NAME)


@pytest.mark.unit
def test_before_it_is_registered_no_door_takes_the_name(capsys):
    assert NAME not in LAW_NAMES
    with pytest.raises(GainError, match="expected one of pid, pid_sine, pid_tv"):
        ControllerConfig(mode=NAME)
    assert any(NAME in p for p in PARAMETERS.problems({"mode": NAME}))
    with pytest.raises(SystemExit) as refused:  # argparse: one line, exit 2
        main(["gains", "--k1", "5e6", "--law", NAME])
    assert refused.value.code == 2
    assert f"invalid choice: '{NAME}'" in capsys.readouterr().err


@pytest.mark.unit
def test_a_registered_law_is_what_the_controller_runs(pd_only):
    config = ControllerConfig(mode=NAME, gains=THESIS_GAINS, on_close="reset")
    assert config.law is pd_only
    pid = TimeVaryingPID(config, closed=True)
    for k, x in enumerate((1e-6, 2e-6, -3e-6)):
        out = pid.update(k * 1e-3, x, yr=0.0)
        assert out.mode == NAME
        u = -THESIS_GAINS.k1 * out.x1 - THESIS_GAINS.k2 * out.x2
        assert out.u == pytest.approx(u, rel=1e-12) and out.x1 == x  # no x0 term
        assert out.u_excitation == 0.0
    # a law whose u does not depend on x0 cannot close bumplessly: said at the door
    with pytest.raises(ControllerConfigError, match="depend on x0"):
        ControllerConfig(mode=NAME, on_close="bumpless").validate()


class _Counter:
    """A law's state that counts the samples it is fed and adds 1 mV per sample to u."""

    def __init__(self) -> None:
        self.fed, self.rebased = 0, []

    def configure(self, gains: Gains) -> None:
        return None

    def rebase(self, yr: float) -> None:
        self.rebased.append(yr)

    def term(self, yr: float) -> float:
        return 1e-3 * self.fed

    def adapt(self, x1: float, x2: float, yr: float, dt: float) -> None:
        self.fed += 1


class Counting(Proportional):
    """The PD law with a state of its own (the ``AdaptingLaw`` protocol)."""

    name = "pd_counting"

    def estimate(self, gains: Gains) -> _Counter:
        return _Counter()


@pytest.mark.unit
def test_a_registered_law_with_a_state_gets_one_per_controller_fed_each_closed_sample():
    register(Counting())
    try:
        config = ControllerConfig(mode="pd_counting", gains=THESIS_GAINS, on_close="reset")
        one, two = TimeVaryingPID(config, closed=True), TimeVaryingPID(config, closed=True)
        assert isinstance(one.law_state, _Counter) and one.law_state is not two.law_state
        outs = [one.update(k * 1e-3, 1e-6, yr=2e-6) for k in range(4)]
        # rebased at the first closed sample; fed from the second (the first has no Δt)
        assert one.law_state.rebased == [2e-6] and one.law_state.fed == 3
        pd = -THESIS_GAINS.k1 * outs[-1].x1 - THESIS_GAINS.k2 * outs[-1].x2
        assert outs[-1].u_excitation == pytest.approx(2e-3)  # the term before this update
        assert outs[-1].u == pytest.approx(pd + 2e-3, rel=1e-12)
        one.open_loop(0.0)
        one.update(4e-3, 1e-6, yr=3e-6)
        assert one.law_state.fed == 3  # open: not fed
        one.close_loop()
        one.update(5e-3, 1e-6, yr=3e-6)
        assert one.law_state.rebased == [2e-6, 3e-6]
        assert two.law_state.fed == 0
    finally:
        unregister("pd_counting")
    assert TimeVaryingPID(ControllerConfig(mode=PID.name)).law_state is None


@pytest.mark.unit
def test_a_registered_law_is_a_choice_of_the_node_of_experiment_and_of_gains(pd_only, capsys):
    assert not PARAMETERS.problems({"mode": NAME})
    assert NAME in PARAMETERS["mode"].full_description()
    assert make_plan("regulation", NAME).mode == NAME
    # the CLI's choices are the registry's: an unknown name lists the new one
    with pytest.raises(SystemExit) as refused:
        main(["experiment", "regulation", "--mode", "nonsense"])
    assert refused.value.code == 2
    assert f"'{NAME}'" in capsys.readouterr().err
    # gains: its sampled loop is the law's own (the PID's matrices with k0 = 0)
    args = ["gains", "--k1", "5e6", "--k2", "600", "--k0", "1e9", "--rate-hz", "20000"]
    code = main([*args, "--law", NAME, "--json"])
    got = json.loads(capsys.readouterr().out)
    assert code in (0, 1) and got["discrete"]["law"] == NAME, got
    from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT

    pd_alone = Gains(k0=0.0, k1=5e6, k2=600.0)
    expected = check_sampled_loop(THESIS_NOMINAL_PLANT, pd_alone, 20000.0, 0, "pid")
    assert got["discrete"]["spectral_radius"] == pytest.approx(expected.spectral_radius, rel=1e-12)
    pid = check_sampled_loop(THESIS_NOMINAL_PLANT, Gains(1e9, 5e6, 600.0), 20000.0, 0, "pid")
    assert got["discrete"]["spectral_radius"] != pytest.approx(pid.spectral_radius)


@pytest.mark.unit
def test_a_name_taken_is_refused(pd_only):
    with pytest.raises(ValueError, match="registered already"):
        register(Proportional())


@pytest.mark.unit
def test_a_law_module_that_does_not_load_is_said_with_its_name(monkeypatch, capsys):
    monkeypatch.setenv("PIEZO_STAGE_LAWS", "no_such_law_module")
    monkeypatch.setattr(laws, "_modules_loaded", False)  # as in a fresh process
    with pytest.raises(GainError, match="PIEZO_STAGE_LAWS: module 'no_such_law_module' does not"):
        laws.law_named("pid")
    assert issubclass(GainError, PiezoStageError)  # the commands' one line, exit 2


@pytest.mark.ros
def test_a_law_from_a_users_module_runs_in_the_graphs_controller(tmp_path):
    """The module named in PIEZO_STAGE_LAWS is imported by the CLI and by the graph's process
    (which inherits the environment): the controller node steps the law, as its states say."""
    (tmp_path / "user_laws.py").write_text(textwrap.dedent(LAW_MODULE))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(ROOT), env.get("PYTHONPATH", "")])
    env["PIEZO_STAGE_LAWS"] = "user_laws"
    bag = tmp_path / "bag"
    args = ["experiment", "regulation", "--mode", NAME, "--duration", "0.01"]
    out = subprocess.run(
        [sys.executable, "-m", "piezo_stage.cli", *args, "--bag", str(bag), "--json"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert summary["mode"] == NAME
    states = [m for _, _, m in read_messages(bag)]
    closed = [s for s in states if s.loop_closed]
    assert len(closed) > 100
    for s in closed:
        assert s.mode == NAME
        u = -THESIS_GAINS.k1 * s.x1 - THESIS_GAINS.k2 * s.x2
        assert s.u_pid == pytest.approx(u, rel=1e-9, abs=1e-9)
        assert s.u_excitation == 0.0
