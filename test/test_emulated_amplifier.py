"""The rig emulator's amplifier bandwidth: a Butterworth low-pass between command and stage,
the stage stepped in substeps (batched through SimulatedStage.step_many); the rig's stage is
the scanner's coupling of one axis."""

from __future__ import annotations

import math

import numpy as np
import pytest

from piezo_stage.commands.emulate import load_stage
from piezo_stage.hardware.emulators.amplifier import AmplifierLowPass, substeps_for
from piezo_stage.hardware.emulators.rig import OneAxis
from piezo_stage.hardware.emulators.scanner import ScannerCoupling

pytestmark = pytest.mark.unit


class RigSource:
    """The rig's sensor source: the stage as one axis of a scanner's coupling, its sample 0 at
    server time 0, its amplifier's channel ``1``."""

    def __init__(self, stage, bandwidth_hz: float = 0.0) -> None:
        self.coupling = ScannerCoupling(
            OneAxis(stage), ["1"], 1000.0, 0.0, clock=lambda: 0.0, bandwidth_hz=bandwidth_hz
        )
        self.source = self.coupling.source(0, lambda: 0.0)

    def on_voltage(self, value: float, at: float) -> None:
        self.coupling.on_axis_voltage("1", value, at)

    def __call__(self, times):
        return self.source(np.asarray(times))

    @property
    def applied(self) -> float:
        return float(self.coupling.applied[0])


class StepOnly:
    """The stage seen only through step() (no batched path)."""

    def __init__(self, stage) -> None:
        self.stage = stage
        self.parameter_set = stage.parameter_set  # the same substeps

    def step(self, command: float, dt: float):
        return self.stage.step(command, dt)


@pytest.mark.parametrize("order", [1, 2])
def test_low_pass_passes_dc_and_is_3_db_down_at_its_corner(order):
    fc, h = 1000.0, 1e-5
    lp = AmplifierLowPass(fc, order, h, initial_voltage=50.0)
    assert lp.run(np.full(10, 50.0)) == pytest.approx(50.0, rel=1e-9)  # at rest
    t = np.arange(int(0.02 / h)) * h
    out = lp.run(np.sin(2 * math.pi * fc * t))
    assert np.ptp(out[len(out) // 2 :]) / 2 == pytest.approx(1 / math.sqrt(2), rel=0.02)


def test_substeps_resolve_the_ch11_resonance_at_a_1_khz_sensor():
    stage = load_stage("ch11_rig.yaml")
    ps = stage.parameter_set
    f_n = math.sqrt(ps.bouc_wen.kappa_x / ps.dynamics.m) / (2 * math.pi)  # ~7 kHz
    n = substeps_for(stage, 1000.0, 1000.0)
    assert 1000.0 * n >= 7 * f_n
    assert substeps_for(stage, 1000.0, 0.0) == 1  # an ideal amplifier: one step per sample


def test_batched_substeps_equal_stepping_one_by_one():
    times = np.arange(1, 41) * 1e-3
    outs = []
    for wrap in (lambda s: s, StepOnly):
        c = RigSource(wrap(load_stage("ch11_rig.yaml")), bandwidth_hz=1000.0)
        for k in range(20):  # a 1 kHz staircase, commands between the samples
            c.on_voltage(5.0 * k, at=k * 1e-3 + 3e-4)
        outs.append(np.concatenate([c(times[:7]), c(times[7:])]))  # two batches
    assert outs[0] == pytest.approx(outs[1], rel=1e-12, abs=1e-15)


def test_the_stage_lags_a_step_and_settles_without_ringing_past_it():
    stage = load_stage("ch11_rig.yaml")
    c = RigSource(stage, bandwidth_hz=1000.0)
    c.on_voltage(100.0, at=0.0)
    fine = c(np.array([1e-4]))  # 0.1 ms after the step the filtered voltage is still low
    assert c.applied < 50.0 and fine[0] < 0.5 * 100.0 / 10.35e6
    ideal = RigSource(load_stage("ch11_rig.yaml"))
    ideal.on_voltage(100.0, at=0.0)
    ideal(np.array([1e-4]))
    assert ideal.applied == 100.0
