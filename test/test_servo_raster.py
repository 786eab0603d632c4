"""The raster played by a PI controller (`experiment raster --graph pi_servo`), against the
E-727 emulator on loopback TCP serving a coupled XY stage written here (not a shipped one):
both tables learned from the data recorder's frames, the image from a detector clock of its
own, the tables read back by PI's own PIPython equal to what was computed, and every refusal
one line, exit 2, nothing moved."""

from __future__ import annotations

import json
import time
from dataclasses import replace

import numpy as np
import pytest

from piezo_stage.cli import main
from piezo_stage.control.raster import RasterTables
from piezo_stage.hardware.emulators import EmulatorServer
from piezo_stage.hardware.emulators.pi_controller import MAX_WAVE_POINTS, PIControllerModel
from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.model.stage import AmplifierModel, CoupledStage, SensorModel
from piezo_stage.model.stage_file import Stage, StageAxis, save_stage

pytestmark = pytest.mark.ros

#: 8 um per axis about 5 um: within the ch. 11 rig's reach at -30..130 V (-2.5..12 um)
SCAN = ["--lines", "32", "--pixels", "256", "--range", "8e-6,8e-6", "--centre", "5e-6,5e-6"]
COUPLING = np.array([[1.0, 0.015], [0.025, 1.0]])
NOISE = 8e-9  # m: 1e-3 of the image's span


def _stage(name: str, kappa_w: float = 1.0, rho: float = 1.0, kappa: float = 1.0) -> Stage:
    """The ch. 11 rig on x and y, κ, κw and ρ scaled, coupled."""
    ps = shipped_parameter_set("ch11_rig")
    bw = replace(
        ps.bouc_wen,
        kappa=tuple(k * kappa for k in ps.bouc_wen.kappa),
        kappa_w=ps.bouc_wen.kappa_w * kappa_w,
        rho=ps.bouc_wen.rho * rho,
    )
    model = replace(ps, name=name, bouc_wen=bw)
    return Stage(name, (StageAxis("x", model, "1"), StageAxis("y", model, "2")), COUPLING.copy())


@pytest.fixture()
def controller(tmp_path):
    """(the emulated controller, its URL, the stage file of what it drives)."""
    stage = _stage("xy_here")
    path = tmp_path / "xy_here.yaml"
    save_stage(stage, path)

    def build() -> CoupledStage:
        return CoupledStage(
            stage,
            [AmplifierModel(-30.0, 130.0) for _ in range(2)],
            [SensorModel(noise_std=NOISE, seed=i) for i in range(2)],
        )

    device = PIControllerModel(build, ("1", "2"), v_min=-30.0, v_max=130.0)
    with EmulatorServer(device, tcp_port=0) as server:
        yield device, f"tcp://127.0.0.1:{server.port}", path


def _raster(url: str, stage, *extra: str, capsys) -> tuple[int, dict, str]:
    args = ["experiment", "raster", "--graph", "pi_servo", "--device", url, "--stage", str(stage)]
    code = main([*args, *SCAN, *extra, "--json"])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if code == 0 else {}), err


def _left_safe(device: PIControllerModel) -> None:
    device.advance_to()
    assert not any(g.mode for g in device.generators)
    assert np.allclose(list(device.voltages.values()), 0.0, atol=1e-9), device.voltages


def _percent(summary: dict, axis: str) -> float:
    a = summary["axes"][axis]
    return 100.0 * a["rms_error"] / a["range"]


def test_the_raster_learns_in_the_controller_and_plays_its_tables_again(
    controller, tmp_path, capsys
):
    device, url, _ = controller
    off = save_stage(_stage("off", kappa_w=1.2, rho=0.9), tmp_path / "off.yaml")
    tables = tmp_path / "raster_tables.json"
    code, got, err = _raster(
        url, off, "--line-rate", "200", "--learn", "20", "--table-out", str(tables), capsys=capsys
    )
    assert code == 0, err
    assert got["graph"] == "pi_servo" and got["rate_hz"] == 20000.0
    first, last = got["learning"][0], got["learning"][-1]
    # from a model 20 % off in κw and 10 % in ρ to the sensor's noise (8 nm, 0.1 % of the range)
    assert first["x"] > 3 * last["x"] and first["y"] > 3 * last["y"], got["learning"]
    assert _percent(got, "x") < 0.2 and _percent(got, "y") < 0.2, got["axes"]
    # the crossings are found on the sensor's noisy positions: 8 nm is 0.26 px of 31 nm, the
    # largest of ~4 000 crossings several times that
    image = got["image"]
    assert image["distortion_px_rms"] < 0.25 and image["distortion_px_max"] < 1.5, image
    assert image["edges"] > 1000
    assert len(got["learning"]) <= 21
    assert "amplifier's limits" not in err
    _left_safe(device)
    saved = RasterTables.load(tables)
    assert len(saved.fast) == len(saved.slow) == round(33 / 200 * 20000)  # a frame each

    code, again, err = _raster(
        url, off, "--line-rate", "200", "--table", str(tables), capsys=capsys
    )
    assert code == 0, err
    assert len(again["learning"]) == 1  # played, not learned
    assert _percent(again, "x") < 0.2 and _percent(again, "y") < 0.2, again["axes"]
    _left_safe(device)


def test_without_the_coupling_taken_out_the_slow_axis_carries_it(controller, capsys):
    """The fast axis's motion, 2.5 % of it on the slow axis's sensor: taken out by the tables
    (the coupling of the stage file), it is gone; left in, it is the slow axis's error."""
    device, url, stage = controller
    code, with_it, err = _raster(url, stage, "--line-rate", "100", capsys=capsys)
    assert code == 0, err
    code, without, err = _raster(
        url, stage, "--line-rate", "100", "--no-coupling-compensation", capsys=capsys
    )
    assert code == 0, err
    assert _percent(without, "y") > 10 * _percent(with_it, "y"), (with_it, without)
    _left_safe(device)


def test_tables_at_the_amplifiers_limits_are_counted_and_said(controller, tmp_path, capsys):
    """A model that asks 15 % less than the stage gives passes the check of its own tables;
    near the top of the range the learned tables then reach 130 V, and the run says so."""
    device, url, _ = controller
    low = save_stage(_stage("low", kappa=0.85), tmp_path / "low.yaml")
    near_top = ["--centre", "8.3e-6,8.3e-6", "--line-rate", "100", "--learn", "3"]
    code, got, err = _raster(url, low, *near_top, capsys=capsys)
    assert code == 0, err
    at_limit = got["at_limit_points"]
    assert at_limit["x"] > 0, got
    said = [line for line in err.splitlines() if "at the amplifier's limits" in line]
    assert said[0].startswith(f"warning: axis x: {at_limit['x']} of the table's "), err
    assert len(said) == sum(1 for n in at_limit.values() if n), err
    _left_safe(device)


def test_pipython_reads_back_the_tables_that_were_computed(controller, tmp_path, capsys):
    from pipython.pidevice.gcscommands import GCSCommands
    from pipython.pidevice.gcsmessages import GCSMessages
    from pipython.pidevice.interfaces.pigateway import PIGateway
    from pipython.pidevice.interfaces.pisocket import PISocket

    device, url, stage = controller
    tables = tmp_path / "t.json"
    code, _, err = _raster(
        url, stage, "--line-rate", "250", "--lines", "8", "--table-out", str(tables),
        capsys=capsys,
    )  # fmt: skip
    assert code == 0, err
    saved = RasterTables.load(tables)
    PIGateway._connection_status_changed_callbacks.clear()  # see test_pi_controller_pipython
    host, port = url.removeprefix("tcp://").split(":")
    gateway = PISocket(host=host, port=int(port))
    try:
        pi = GCSCommands(GCSMessages(gateway))
        assert pi.qWMS([1, 2]) == {1: MAX_WAVE_POINTS, 2: MAX_WAVE_POINTS}
        for table, want in ((1, saved.fast.u), (2, saved.slow.u)):
            pi.qGWD(table, 1, len(want))
            end = time.monotonic() + 30.0
            while pi.bufstate is not True:
                assert time.monotonic() < end, "the GCS array did not arrive"
                time.sleep(0.01)
            got = np.array(pi.bufdata)[0]
            # the uploaded text keeps the values to the GCS format's digits (< 1 uV here)
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    finally:
        gateway.close()


@pytest.mark.parametrize(
    ("extra", "why"),
    [
        (["--line-rate", "300"], "whole number"),
        (["--line-rate", "10", "--lines", "256"], "wave table 1 holds"),
        (["--line-rate", "100", "--lines", "200"], "data recorder table"),
        (["--line-rate", "200", "--range", "14e-6,8e-6"], "the amplifier gives"),
        (["--line-rate", "200", "--compensation", "feedback"], "feedforward"),
        (["--line-rate", "200", "--rate-hz", "40000"], "servo runs at 20000 Hz"),
    ],
)
def test_what_cannot_be_played_is_one_line_exit_2_and_nothing_moves(controller, capsys, extra, why):
    device, url, stage = controller
    code, _, err = _raster(url, stage, *extra, capsys=capsys)
    assert code == 2, err
    assert why in err and len(err.strip().splitlines()) == 1, err
    assert device.waves == {} or not any(g.mode for g in device.generators)
    _left_safe(device)
    assert device.recorder.count == 0  # nothing played, nothing recorded


def test_an_axis_the_controller_does_not_list_is_refused(controller, tmp_path, capsys):
    device, url, _ = controller
    model = shipped_parameter_set("ch11_rig")
    other = Stage("xz", (StageAxis("x", model, "1"), StageAxis("z", model, "3")), np.eye(2))
    path = tmp_path / "xz.yaml"
    save_stage(other, path)
    code, _, err = _raster(url, path, "--line-rate", "200", capsys=capsys)
    assert code == 2 and "'3'" in err and "SAI?" in err, err
    _left_safe(device)


def test_a_raster_on_pi_servo_needs_a_device(capsys):
    code = main(["experiment", "raster", "--graph", "pi_servo", *SCAN, "--json"])
    err = capsys.readouterr().err
    assert code == 2 and "--device" in err, err


def test_the_frame_goes_to_a_bag_and_the_images_to_png(controller, tmp_path, capsys):
    """--bag: the recorded frame of both axes as LoopSamples (the controller's clock, the
    loop open, the command the feedforward); --png: the images before and after learning."""
    from piezo_stage.bag.reader import read_loop_samples

    device, url, stage = controller
    bag, png = tmp_path / "scan_bag", tmp_path / "png"
    extra = ["--line-rate", "250", "--lines", "8", "--learn", "2"]
    code, got, err = _raster(
        url, stage, *extra, "--bag", str(bag), "--png", str(png), capsys=capsys
    )
    assert code == 0, err
    assert sorted(p.name for p in png.iterdir()) == ["raster_images.png", "raster_lines.png"]
    n = round(got["frame_time"] * got["rate_hz"])
    for axis in ("x", "y"):
        columns = read_loop_samples(bag, f"/raster/{axis}/loop_samples")
        assert columns["stamp"].size == n
        assert np.all(np.diff(columns["stamp"]) == 50_000)  # 20 kHz, no gap
        assert not columns["loop_closed"].any()
        assert np.array_equal(columns["u_ff"], columns["u"])
        error = columns["displacement"] - columns["reference"]
        assert np.sqrt(np.mean(error**2)) < 0.01 * got["axes"][axis]["range"]
    _left_safe(device)
