"""Identification at a PI controller's servo rate, against the E-727 emulator on loopback TCP:
the T-wave pair played by its wave generator, recorded by its data recorder, read back (in
segments when a run is longer than a table), written to a bag that identifies to the same
numbers, and every failure one line, exit 2, with the generator stopped and the output safe."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from piezo_stage.cli import main
from piezo_stage.commands.emulate import emulated_controller
from piezo_stage.experiments.servo_identification import TWaveExcitation, record_t_waves
from piezo_stage.hardware.amplifier import GCSAmplifier
from piezo_stage.hardware.emulators import EmulatorServer, pi_controller
from piezo_stage.hardware.emulators.pi_controller import PIControllerModel, gcs_array
from piezo_stage.hardware.errors import DeviceTimeout, ProtocolError
from piezo_stage.hardware.pi_recorder import ServoRecorder, parse_gcs_array
from piezo_stage.hardware.transport import make_transport
from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.model.stage_file import Stage, StageAxis

pytestmark = pytest.mark.ros

V_MIN, V_MAX = -30.0, 130.0
PATCH = shipped_parameter_set("ch10_patch").bouc_wen
#: a short excitation: T = 0.5 s at 4 kHz (record rate 5), 3 + 2 periods per run (5 s)
FAST = ["--period", "0.5", "--record-rate", "5", "--periods", "3,2"]
RECORDED = "recorded 20000 points at 4 kHz"  # 2 runs x 5 periods x 2000 points


def _controller(
    noise: float = 2e-9, name: str = "ch11_rig", v_min: float = V_MIN, v_max: float = V_MAX
) -> PIControllerModel:
    model = shipped_parameter_set(name)
    stage = Stage(
        "e727", tuple(StageAxis(n, model, str(i + 1)) for i, n in enumerate("xyz")), np.eye(3)
    )
    return emulated_controller(stage, v_min=v_min, v_max=v_max, sensor_noise=noise)


@pytest.fixture()
def controller():
    model = _controller()
    with EmulatorServer(model, tcp_port=0) as server:
        yield model, f"tcp://127.0.0.1:{server.port}"


def _left_safe(model: PIControllerModel) -> None:
    """The generators stopped and every output at 0 V (max(VMI?, 0))."""
    model.advance_to()
    assert not any(g.mode for g in model.generators)
    assert np.allclose(list(model.voltages.values()), 0.0, atol=1e-9), model.voltages


@pytest.mark.slow
def test_the_t_waves_recorded_in_the_controller_identify_its_stage(tmp_path, capsys):
    """The ch. 10 patch (static form, voltage -> displacement, 0-400 V) on the emulator: the
    parameters come back from the data recorder's record, and its bag identifies to the same
    numbers."""
    model = _controller(noise=2e-9, name="ch10_patch", v_min=0.0, v_max=400.0)
    bag = tmp_path / "servo"
    with EmulatorServer(model, tcp_port=0) as server:
        url = f"tcp://127.0.0.1:{server.port}"
        args = ["identify", "--device", url, "--axis", "2", "--degree", "2"]
        excitation = ["--voltage", "0,300", "--offset", "100", *FAST]
        assert main([*args, *excitation, "--json", "--bag", str(bag), "--no-plot"]) == 0
        out, err = capsys.readouterr()
        _left_safe(model)
    got = json.loads(out)
    assert got["method"] == "analytic" and got["input_name"] == "voltage"
    assert RECORDED in err
    for name in ("kappa_w", "rho", "sigma", "n"):
        assert got[name] == pytest.approx(getattr(PATCH, name), rel=0.02), name
    assert got["kappa"] == pytest.approx(list(PATCH.kappa), rel=0.02)
    assert got["input_sign"] == PATCH.input_sign
    # the bag holds the record on the controller's clock: identifying it gives the same
    # numbers (its stamps are integer ns, the record's float seconds: the refinement, which
    # stops at its own tolerance, sees inputs equal to ~1e-16 and ends equal to ~1e-9)
    offline = ["identify", str(bag), "--degree", "2", "--steady-periods", "2"]
    assert main([*offline, "--method", "analytic", "--json", "--no-plot"]) == 0
    again = json.loads(capsys.readouterr().out)
    for name in ("y0", "kappa_w", "rho", "sigma", "n"):
        assert again[name] == pytest.approx(got[name], rel=1e-7), name


@pytest.mark.slow
def test_the_ch11_form_pairs_each_position_with_its_two_voltages_mean(tmp_path, capsys):
    """The ch. 11 form (displacement -> voltage) of the rig: its measured input is delayed by
    half a sample (the mean of the voltages held before and after each reading), and the
    bag identified with ``--lag 0.5`` gives the same numbers; without it, other ones."""
    model = _controller(noise=2e-9)
    bag = tmp_path / "servo11"
    with EmulatorServer(model, tcp_port=0) as server:
        url = f"tcp://127.0.0.1:{server.port}"
        args = ["identify", "--device", url, "--axis", "1", "--model-input", "displacement"]
        fast = ["--period", "0.05", "--periods", "14,2"]  # 20 kHz: 1000 points a period
        assert main([*args, *fast, "--json", "--bag", str(bag), "--no-plot"]) == 0
        got = json.loads(capsys.readouterr().out)
        _left_safe(model)
    assert got["input_name"] == "displacement" and got["delay"] == pytest.approx(0.5 / 20e3)
    offline = ["identify", str(bag), "--input-topic", "/piezo/displacement"]
    offline += ["--output-topic", "/piezo/voltage", "--steady-periods", "2", "--json"]
    assert main([*offline, "--lag", "0.5", "--method", "analytic", "--no-plot"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert main([*offline, "--method", "analytic", "--no-plot"]) == 0
    held = json.loads(capsys.readouterr().out)
    # the bag's stamps are the record's to a nanosecond, not bit for bit; the fit (kappa_w and
    # rho correlated to -0.999) turns that into ~1e-7: the tolerance stays 100x below what the
    # pairing moves
    for name in ("kappa_w", "rho", "sigma", "n"):
        assert again[name] == pytest.approx(got[name], rel=1e-5), name
    assert abs(held["kappa_w"] / got["kappa_w"] - 1) > 1e-3  # the pairing matters


@pytest.mark.slow
def test_the_ch11_form_with_m_and_c_is_a_model_the_tables_learn_from(tmp_path, capsys):
    """identify --device --model-input displacement --m --c --output writes the dynamic model
    (11.1): the identified Φ, the offset as a displacement (-y0/κx), the given m and c; played
    as a learned table on the same controller, it tracks a 100 Hz triangle."""
    from piezo_stage.model.parameter_set import load_parameter_set

    rig = shipped_parameter_set("ch11_rig")
    model = _controller(noise=2e-9)
    out = tmp_path / "axis1.yaml"
    with EmulatorServer(model, tcp_port=0) as server:
        url = f"tcp://127.0.0.1:{server.port}"
        args = ["identify", "--device", url, "--axis", "1", "--model-input", "displacement"]
        args += ["--period", "0.05", "--periods", "14,2", "--output", str(out), "--json"]
        m, c = rig.dynamics.m, rig.dynamics.c
        assert main([*args, "--m", str(m), "--c", str(c), "--no-plot"]) == 0
        got = json.loads(capsys.readouterr().out)
        ps = load_parameter_set(out)
        assert ps.form == "dynamic" and (ps.dynamics.m, ps.dynamics.c) == (m, c)
        assert ps.input_name == "voltage" and ps.output_name == "displacement"
        assert ps.bouc_wen.kappa_w == got["kappa_w"] and ps.bouc_wen.rho == got["rho"]
        assert ps.bouc_wen.y0 == pytest.approx(-got["y0"] / got["kappa"][0], rel=1e-12)
        track = ["experiment", "tracking", "--graph", "pi_servo", "--device", url, "--axis", "1"]
        track += ["--trajectory", "triangle", "--frequency", "100", "--amplitude", "5e-6"]
        track += ["--offset", "5e-6", "--model", str(out), "--learn", "3", "--json"]
        assert main(track) == 0
        tracked = json.loads(capsys.readouterr().out)
    assert tracked["rms_relative"] < 2e-3 and tracked["at_limit_points"] == 0
    _left_safe(model)


@pytest.mark.parametrize(
    "extra, why",
    [
        (["--m", "5e-3"], "--m and --c go together"),
        (["--m", "0", "--c", "13"], "need --m > 0 and --c >= 0"),
        (["--m", "5e-3", "--c", "nan"], "need --m > 0 and --c >= 0"),
        (["--m", "5e-3", "--c", "13", "--model-input", "voltage"], "need the ch. 11 form"),
        (["--m", "5e-3", "--c", "13", "--no-output"], "give --output"),
    ],
)
def test_m_and_c_that_cannot_shape_a_model_are_one_line_exit_2(tmp_path, capsys, extra, why):
    """Refused before anything is played: no controller is even reached."""
    args = ["identify", "--device", "tcp://127.0.0.1:9", "--model-input", "displacement"]
    if "--no-output" in extra:
        extra = [e for e in extra if e != "--no-output"]
    else:
        args += ["--output", str(tmp_path / "m.yaml")]
    code = main([*args, *extra, "--no-plot"])
    err = capsys.readouterr().err
    assert code == 2 and why in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "m.yaml").exists()


@pytest.mark.parametrize("lag", ["nan", "inf", "65", "-100"])
def test_a_lag_that_is_no_number_of_samples_is_refused(tmp_path, capsys, lag):
    assert main(["identify", str(tmp_path / "bag"), "--lag", lag]) == 2
    err = capsys.readouterr().err
    assert "--lag must be within ±64 samples" in err and len(err.strip().splitlines()) == 1


def test_a_run_longer_than_a_table_is_joined_without_a_gap(controller, monkeypatch):
    """A recorder of 2 x 2500 points: each run of 12 periods of 1000 points is played in parts
    of two periods, read back each time, and joined on the controller's clock."""
    model, url = controller
    monkeypatch.setattr(pi_controller, "MAX_RECORD_POINTS", 5000)
    amplifier = GCSAmplifier(make_transport(url), axis="1")
    info = amplifier.open()
    try:
        excitation = TWaveExcitation(0.0, 60.0, 20.0, 0.05, 10, 2, rate=1)  # 1000 points
        record = record_t_waves(
            amplifier, ServoRecorder(amplifier.conn), excitation, 1, (info.v_min, info.v_max)
        )
    finally:
        amplifier.close()
    assert record.segments == [2000] * 12  # 6 parts of 2 periods per run
    dt = record.cycle * excitation.rate
    for run in record.recordings():
        steps = np.diff(run.t)
        assert np.allclose(steps, dt, rtol=1e-9, atol=1e-12)  # no gap inside a run
        assert np.ptp(run.input) == pytest.approx(60.0, abs=1e-6)
    # the input is the triangle the table holds, continuous across the joins
    v = record.voltage[: 12 * 1000]
    assert np.allclose(v, np.tile(excitation.table(record.cycle), 12), atol=1e-6)
    # each position is paired with the voltage its cycle read it under: the one before (the
    # stamps are whole servo cycles, so a rounding never pairs it with an older one)
    for run in record.recordings():
        k = np.searchsorted(record.t, run.t)
        assert np.array_equal(record.t[k], run.t)
        assert np.array_equal(run.input, record.voltage[k - 1])


@pytest.mark.parametrize(
    "extra, why",
    [
        (["--axis", "9"], "axis '9' not on controller"),
        (["--voltage", "0,120", "--offset", "40"], "outside the controller's output range"),
        (["--period", "10", "--record-rate", "1"], "does not fit a data recorder table"),
        (["--period", "5", "--record-rate", "1"], "wave table 1 refused points"),
        (["--periods", "10"], "--periods needs two comma-separated values"),
    ],
)
def test_what_the_controller_cannot_do_is_one_line_exit_2_and_safe(controller, capsys, extra, why):
    model, url = controller
    code = main(["identify", "--device", url, *extra, "--no-plot"])
    err = capsys.readouterr().err
    assert code == 2 and why in err, err
    assert err.strip().splitlines()[-1].startswith("piezo-stage identify: error:")
    _left_safe(model)


def test_a_garbled_readback_is_refused_and_leaves_the_controller_safe(controller, capsys):
    model, url = controller
    model.inject_drr_fault("malformed")
    code = main(["identify", "--device", url, "--axis", "1", *FAST, "--no-plot"])
    err = capsys.readouterr().err
    assert code == 2 and "array reply" in err, err
    _left_safe(model)


def test_a_cut_readback_times_out_and_leaves_the_controller_safe(controller):
    model, url = controller
    amplifier = GCSAmplifier(make_transport(url), axis="1")
    info = amplifier.open()
    model.inject_drr_fault("cut")
    try:
        with pytest.raises(DeviceTimeout):
            record_t_waves(
                amplifier,
                ServoRecorder(amplifier.conn, read_timeout=2.0),
                TWaveExcitation(0.0, 60.0, 20.0, period=0.05, settle_periods=0),
                1,
                (info.v_min, info.v_max),
            )
    finally:
        amplifier.close()
    _left_safe(model)


# ------------------------------------------------------------------ the GCS array format


def test_an_array_reply_is_read_with_its_header():
    columns = np.array([[1.0, 2.5, -3.0], [4.0, 5.0, 6.25]])
    got = parse_gcs_array(gcs_array(["Piezo Voltage 1", "Position 1"], columns, 5e-5), 2)
    assert np.array_equal(got.columns, columns)
    assert got.sample_time == pytest.approx(5e-5) and got.header["NAME1"] == "Position 1"


@pytest.mark.parametrize(
    "lines, why",
    [
        (["# NDATA = 1", "# DIM = 2"], "without # END_HEADER"),
        (["# NDATA = 2", "# END_HEADER", "1 2"], "NDATA = 2 but 1 rows"),
        (["# END_HEADER", "1 2", "3"], "rows of 2 values"),
        (["# END_HEADER", "1 nan"], "not finite"),
        (["# END_HEADER", "1 #garbled"], "not 2 numbers"),
        (["# END_HEADER", "0.5 #garbled"], "not 2 numbers"),
        (["1 2", "# END_HEADER"], "before # END_HEADER"),
    ],
)
def test_a_bad_array_reply_is_refused(lines, why):
    with pytest.raises(ProtocolError, match=why):
        parse_gcs_array(lines, 2)


@given(text=st.text(alphabet=st.sampled_from(list("0123456789.-e #=ENDHAR_\n")), max_size=200))
@example(text="# END_HEADER\n1 2")
@pytest.mark.hypothesis
def test_any_reply_is_data_of_the_asked_width_or_refused(text):
    """Whatever arrives: ProtocolError, or finite data with one row per table asked for."""
    try:
        got = parse_gcs_array(text.split("\n"), 2)
    except ProtocolError:
        return
    assert got.columns.shape[0] == 2 and np.all(np.isfinite(got.columns))
