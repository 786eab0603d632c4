"""The E-727-class controller emulator (its servo clock, wave generator and data recorder)
driven by PI's own PIPython over loopback TCP (PISocket -> GCSMessages -> GCSCommands, no
vendor DLL), checked against the simulated stage it is bound to."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from piezo_stage.hardware.emulators import EmulatorServer
from piezo_stage.hardware.emulators.pi_controller import (
    MAX_RECORD_POINTS,
    PIControllerModel,
    wave_segment,
)
from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.model.stage import AmplifierModel, CoupledStage, SensorModel
from piezo_stage.model.stage_file import Stage, StageAxis

NOISE = 2e-9  # m, the position sensors' noise
V_MIN, V_MAX = -30.0, 130.0


def _stage(noise: float = NOISE, axes: int = 3):
    model = shipped_parameter_set("ch11_rig")
    stage = Stage(
        "e727",
        tuple(StageAxis(n, model, str(i + 1)) for i, n in enumerate("xyz"[:axes])),
        np.eye(axes),
    )

    def build() -> CoupledStage:
        return CoupledStage(
            stage,
            [AmplifierModel(V_MIN, V_MAX) for _ in range(axes)],
            [SensorModel(noise_std=noise, seed=i) for i in range(axes)],
        )

    return build


def _model(**kwargs) -> PIControllerModel:
    return PIControllerModel(_stage(), ("1", "2", "3"), v_min=V_MIN, v_max=V_MAX, **kwargs)


@pytest.fixture(scope="module")
def pidevice():
    from pipython.pidevice.gcscommands import GCSCommands
    from pipython.pidevice.gcsmessages import GCSMessages
    from pipython.pidevice.interfaces.pigateway import PIGateway
    from pipython.pidevice.interfaces.pisocket import PISocket

    # PIPython tells every GCSDevice ever made in the process of each new connection (class-level
    # callbacks it never drops): one left by another test module in this worker writes *IDN?
    # to its own closed socket and the new connection fails with a broken pipe
    PIGateway._connection_status_changed_callbacks.clear()
    model = _model()
    with EmulatorServer(model, tcp_port=0) as server:
        gateway = PISocket(host="127.0.0.1", port=server.port)
        messages = GCSMessages(gateway)
        device = GCSCommands(messages)
        try:
            yield model, device
        finally:
            gateway.close()


def _read_array(device, header_call, timeout: float = 30.0):
    header = header_call()
    end = time.monotonic() + timeout
    while device.bufstate is not True:
        assert time.monotonic() < end, "the GCS array did not arrive"
        time.sleep(0.01)
    return header, np.array(device.bufdata)


@pytest.mark.ros
def test_pipython_identifies_and_queries(pidevice):
    model, device = pidevice
    assert "E-727" in device.qIDN()
    assert device.qSAI() == ["1", "2", "3"]
    assert float(device.qCSV()) == 2.0
    assert device.qERR() == 0
    assert "MOV" in device.qHLP() and "DRR?" in device.qHLP()
    hdr = device.qHDR()
    assert "2=Current Position of axis" in hdr and "7=Control Voltage" in hdr
    assert "#TriggerOptions" in hdr
    tmn, tmx = device.qTMN(), device.qTMX()
    assert all(tmn[a] < 0.0 < 10.0 < tmx[a] for a in ("1", "2", "3"))
    assert device.qVMA() == {1: V_MAX, 2: V_MAX, 3: V_MAX}
    assert device.qVMI([1]) == {1: V_MIN}
    assert device.qECO("hello world").strip() == "hello world"
    assert device.qTNR() == 8
    assert device.qSPA("1", 0x0E000200)["1"][0x0E000200] == pytest.approx(50e-6)
    assert device.qSPA("1", 0x16000200)["1"][0x16000200] == MAX_RECORD_POINTS
    assert set(device.qTSP()) == {1, 2, 3}


@pytest.mark.ros
def test_pipython_plays_and_records_a_sine_and_a_point_table(pidevice):
    """Runs before any voltage reaches the stage (file order): the emulated stage then has
    the history of a fresh one, which the check below replays the recorded voltages on."""
    model, device = pidevice
    assert device.qSVO() == {"1": False, "2": False, "3": False}
    assert device.qVOL() == {1: 0.0, 2: 0.0, 3: 0.0}
    n_sine, rate = 400, 2
    device.WAV_SIN_P(
        table=1,
        firstpoint=0,
        numpoints=n_sine,
        append="X",
        center=n_sine // 2,
        amplitude=60.0,
        offset=10.0,
        seglength=n_sine,
    )
    points = [0.0, 20.0, 40.0, 60.0, 40.0, 20.0]
    device.WAV_PNT(table=2, firstpoint=1, numpoints=len(points), append="X", wavepoint=points)
    assert device.qWAV([1, 2], [1, 1]) == {1: {1: n_sine}, 2: {1: len(points)}}
    _, table = _read_array(device, lambda: device.qGWD(2, 1, len(points)))
    assert table[0].tolist() == points
    device.WSL([1, 2], [1, 2])
    assert device.qWSL() == {1: 1, 2: 2, 3: 0}
    device.WTR(1, rate, 0)
    device.WTR(2, 50, 0)
    device.WGC([1, 2], [1, 3])
    device.WOS([1, 2], [0.0, 0.0])
    assert device.qWTR([1])[1] == [rate, 0] or device.qWTR([1])[1] == rate
    device.DRC([1, 2, 3, 4], ["1", "1", "2", "2"], [7, 2, 7, 2])
    assert device.qDRC(1)[1] == ["1", 7]
    device.DRT(0, 0, 0)
    assert device.qDRT(1)[1] == [0, "0"]
    device.RTR(1)
    assert device.qRTR() == 1
    device.WGO([1, 2], [1, 1])
    n = n_sine * rate
    end = time.monotonic() + 30.0
    while device.qDRL(1)[1] < n + 100:
        assert time.monotonic() < end, "the recorder did not fill"
        time.sleep(0.02)
    assert device.qWGO() == {1: 0, 2: 0, 3: 0}  # one cycle of the sine, three of the points
    header, data = _read_array(device, lambda: device.qDRR([1, 2, 3, 4], 1, n + 100))
    assert header["NDATA"] == n + 100 and header["DIM"] == 4
    assert header["SAMPLE_TIME"] == pytest.approx(50e-6)
    sine = wave_segment("SIN_P", [str(n_sine), "60", "10", str(n_sine), "0", str(n_sine // 2)])
    # the recorded voltage is the table played one point per WTR servo cycles, then held
    np.testing.assert_allclose(data[0, :n], np.repeat(sine, rate), atol=1e-6)
    np.testing.assert_allclose(data[0, n:], sine[-1], atol=1e-6)
    assert np.allclose(
        data[2, : 3 * 50 * len(points)], np.tile(np.repeat(points, 50), 3)[: n + 100]
    )
    # the recorded position is what the stage model gives for those voltages (a fresh stage
    # without noise: the emulated one rested at 0 V before), within the sensor noise; a cycle
    # records the sensor it reads before its output acts: point k follows the voltages < k
    volts = np.vstack([data[0], data[2], np.zeros(n + 100)])
    expected = CoupledStage(_stage(noise=0.0)().stage).step_voltages(volts, 50e-6, 1).readings
    expected = np.vstack([np.zeros((1, 3)), expected[:-1]])
    np.testing.assert_allclose(data[1], expected[:, 0] * 1e6, atol=6 * NOISE * 1e6)
    np.testing.assert_allclose(data[3], expected[:, 1] * 1e6, atol=6 * NOISE * 1e6)
    assert np.allclose(model.recorded(2)[: n + 100], data[1])
    assert device.qERR() == 0


@pytest.mark.ros
def test_pipython_open_loop_voltage_and_closed_loop_move(pidevice):
    import pipython

    model, device = pidevice
    device.SVO(["1", "2", "3"], [False, False, False])
    assert device.qSVO() == {"1": False, "2": False, "3": False}
    with pytest.raises(pipython.GCSError) as err:
        device.MOV("1", 3.0)
    assert err.value.val == 5  # move with the servo off
    device.SVA("1", 40.0)
    assert device.qVOL([1])[1] == 40.0
    time.sleep(0.05)  # the stage settles at the controller's own clock
    gain = model.gain[0]
    assert device.qPOS("1")["1"] == pytest.approx(40.0 * gain, rel=0.25)
    device.SVO("2", True)
    with pytest.raises(pipython.GCSError) as err:
        device.SVA("2", 10.0)
    assert err.value.val == 79
    device.MOV("2", 5.0)
    end = time.monotonic() + 10.0
    while not device.qONT("2")["2"]:
        assert time.monotonic() < end, "axis 2 never came on target"
        time.sleep(0.01)
    assert device.qPOS("2")["2"] == pytest.approx(5.0, abs=0.05)
    assert device.qTSP([2])[2] == pytest.approx(5.0, abs=0.05)
    assert device.qVOL([2])[2] == pytest.approx(5.0 / gain, rel=0.3)
    device.SVO("2", False)
    device.SVA(["1", "2"], [0.0, 0.0])
    assert device.qERR() == 0


def _send(sock: socket.socket, line: str, timeout: float = 2.0) -> bytes:
    """One line and its reply (up to a final LF not preceded by a space), b"" on a timeout."""
    sock.sendall(line.encode("ascii") + b"\n")
    sock.settimeout(timeout)
    reply = b""
    try:
        while not (reply.endswith(b"\n") and not reply.endswith(b" \n")):
            chunk = sock.recv(65536)
            if not chunk:
                break
            reply += chunk
    except TimeoutError:
        pass
    return reply


QUERIES = (
    "*IDN?",
    "CSV?",
    "ERR?",
    "HLP?",
    "HDR?",
    "HPA?",
    "SAI?",
    "SAI? ALL",
    "SVO?",
    "SVA?",
    "MOV?",
    "POS?",
    "ONT?",
    "TSP?",
    "TMN?",
    "TMX?",
    "VOL?",
    "VMA?",
    "VMI?",
    "ECO? x",
    "SPA?",
    "SPA? 1 0x0E000200",
    "TNR?",
    "DRC?",
    "DRT?",
    "RTR?",
    "DRL?",
    "DRR? 1 4 1",
    "TWG?",
    "WSL?",
    "WGC?",
    "WTR?",
    "WOS?",
    "WGO?",
    "WAV? 1 1",
    "GWD? 1 2 1",
    "ONL?",
)


@pytest.mark.ros
def test_every_query_answers_and_unknown_commands_latch_error_2():
    model = _model()
    model.execute("WAV 1 X PNT 1 3 1 2 3")
    with EmulatorServer(model, tcp_port=0) as server:
        with socket.create_connection(("127.0.0.1", server.port), timeout=5) as sock:
            for query in QUERIES:
                reply = _send(sock, query)
                assert reply.endswith(b"\n") and len(reply) > 1, query
            assert _send(sock, "ERR?") == b"0\n"
            assert _send(sock, "XYZ 1 2", timeout=0.2) == b""
            assert _send(sock, "ERR?") == b"2\n"
            assert _send(sock, "XYZ?", timeout=0.2) == b""  # a real controller answers nothing
            assert _send(sock, "ERR?") == b"2\n"


@pytest.mark.unit
def test_the_servo_clock_records_a_point_every_rtr_cycles_until_the_tables_are_full():
    model = _model(start=0.0)
    model.execute("SPA 1 0x16000300 4", now=0.0)  # 4 tables: 65536 points each
    model.execute("RTR 3", now=0.0)
    model.execute("DRT 0 1 0", now=0.0)
    model.execute("SVA 1 10", now=1e-3)  # trigger: a position-changing command at cycle 20
    assert model.execute("DRL? 1", now=1e-3 + 300 * 50e-6) == b"1=100\n"
    assert model.recorded(1, now=1e-3 + 300 * 50e-6).size == 100
    assert model.cycle == 20 + 300
    capacity = MAX_RECORD_POINTS // 4
    model.advance_to(1e-3 + 3 * capacity * 50e-6 + 1.0)
    full = [b"%d=%d" % (t, capacity) for t in (1, 2, 3, 4)]
    assert model.execute("DRL? 1 2 3 4", now=50.0).split() == full
    assert model.recorder.active is False
    assert model.execute("ERR?") == b"0\n"


@pytest.mark.unit
def test_a_drr_fault_cuts_the_reply_or_garbles_a_row():
    model = _model(start=0.0)
    model.execute("WGO 1 0", now=0.0)
    model.execute("DRT 0 2 0", now=0.0)
    model.execute("SVA 1 1", now=0.0)  # the next command triggers
    model.inject_drr_fault("cut")
    cut = model.execute("DRR? 1 10 1", now=0.01)
    assert cut.endswith(b" \n") and cut.count(b"\n") == 9 + 5  # 9 header lines, 5 of 10 rows
    model.inject_drr_fault("malformed")
    assert b"#garbled" in model.execute("DRR? 1 10 1", now=0.01)
    assert b"#garbled" not in model.execute("DRR? 1 10 1", now=0.01)
