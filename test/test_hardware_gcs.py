"""PI GCS 2.0 protocol against the GCS emulator (loopback TCP and pty), and PIPython against the
emulator."""

from __future__ import annotations

import subprocess
import sys

import pytest

from piezo_stage.hardware.emulators import EmulatorServer, Faults, GCSDeviceModel
from piezo_stage.hardware.errors import DeviceTimeout, GCSError, ProtocolError
from piezo_stage.hardware.gcs import (
    GCS_ERROR_MESSAGES,
    GCSConnection,
    gcs_error_message,
    gcs_reply_end,
    join_reply,
    parse_item_values,
    split_reply,
)
from piezo_stage.hardware.transport import ReplyBuffer, make_transport

pytestmark = pytest.mark.ros


@pytest.fixture(params=["tcp", "pty"])
def served(request):
    model = GCSDeviceModel(axis="A", v_min=-20.0, v_max=120.0)
    endpoint = {"tcp_port": 0} if request.param == "tcp" else {"pty": True}
    with EmulatorServer(model, **endpoint) as server:
        transport = make_transport(server.url)
        transport.open()
        yield model, GCSConnection(transport, timeout=0.5)
        transport.close()


def test_error_table_has_the_required_codes_with_pipython_texts():
    for code in (1, 2, 5, 15, 17, 66, 79):
        assert code in GCS_ERROR_MESSAGES
    assert gcs_error_message(79) == "Open-loop commands are not allowed when servo is on"
    assert gcs_error_message(2) == "Unknown command"
    assert "9999" in gcs_error_message(9999)


def test_reply_framing_multi_line():
    assert gcs_reply_end(b"1=2.5 \n2=3") == -1
    assert gcs_reply_end(b"1=2.5 \n2=3\nrest") == len(b"1=2.5 \n2=3\n")
    assert split_reply(join_reply(["a", "b", "c"])) == ["a", "b", "c"]
    assert join_reply(["x=1", "y=2"]) == b"x=1 \ny=2\n"
    assert parse_item_values(["1=12.345", "Z = -3"]) == {"1": "12.345", "Z": "-3"}
    with pytest.raises(ProtocolError):
        parse_item_values(["garbage"])


def test_identify_axes_and_open_loop_voltage(served):
    model, conn = served
    assert "E-709" in conn.query("*IDN?")[0]
    assert conn.query("SAI?") == ["A"]
    conn.command("SVO A 0")
    conn.command("SVA A 42.5")
    assert conn.query_float("SVA? A", "A") == 42.5
    assert conn.query_float("VOL? 1", "1") == 42.5
    assert conn.query_float("VMA? 1", "1") == 120.0
    assert conn.query_float("VMI? 1", "1") == -20.0
    assert model.applied_voltage == 42.5


def test_multi_line_reply_is_read_whole(served):
    _, conn = served
    lines = conn.query("HLP?")
    assert len(lines) > 10 and "SVA" in lines and "VOL?" in lines
    assert conn.error_code() == 0  # nothing left over from the multi-line reply


@pytest.mark.parametrize(
    "command, code",
    [
        ("SVA A 10", 79),  # servo still on (real default)
        ("FOO 1", 2),
        ("SVO B 0", 15),
        ("SVO A 7", 17),
        ("SVO A", 1),
        ("MOV A 1", None),  # servo on: accepted (target stored)
    ],
)
def test_setters_latch_error_codes(served, command, code):
    model, conn = served
    if code is None:
        conn.command(command)
        assert model.target == 1.0  # stored: closed-loop motion is not simulated
        assert conn.query_float("MOV? A", "A") == 1.0
        assert conn.error_code() == 0 and model.applied_voltage == 0.0
        return
    with pytest.raises(GCSError) as err:
        conn.command(command)
    assert err.value.code == code
    assert err.value.message == GCS_ERROR_MESSAGES[code]
    assert conn.error_code() == 0  # ERR? cleared it
    assert model.applied_voltage == 0.0


def test_voltage_outside_device_limits_and_move_with_servo_off(served):
    model, conn = served
    conn.command("SVO A 0")
    with pytest.raises(GCSError) as err:
        conn.command("SVA A 500")
    assert err.value.code == 66
    with pytest.raises(GCSError) as err:
        conn.command("MOV A 1")
    assert err.value.code == 5
    assert model.applied_voltage == 0.0


def test_refused_query_raises_gcs_error_not_timeout(served):
    _, conn = served
    with pytest.raises(GCSError) as err:
        conn.query("VOL? 9")
    assert err.value.code == 17


def test_sva_accepted_with_servo_on_when_refusal_disabled():
    model = GCSDeviceModel(refuse_sva_when_servo_on=False)
    with EmulatorServer(model, tcp_port=0) as server:
        with make_transport(server.url) as transport:
            GCSConnection(transport).command("SVA 1 5")
    assert model.applied_voltage == 5.0


def test_slow_replies_time_out():
    with EmulatorServer(GCSDeviceModel(), tcp_port=0, faults=Faults(reply_delay=0.5)) as server:
        with make_transport(server.url) as transport:
            with pytest.raises(DeviceTimeout):
                GCSConnection(transport, timeout=0.1).query("*IDN?")


def test_pipython_drives_the_emulator_over_tcp():
    """PI's own Python library (pure-Python PISocket gateway, no vendor DLL) on the emulator."""
    import gc

    import pipython
    from pipython import GCSDevice
    from pipython.pidevice.interfaces.pisocket import PISocket

    model = GCSDeviceModel(axis="1", v_min=0.0, v_max=100.0)
    with EmulatorServer(model, tcp_port=0) as server:
        device = GCSDevice(gateway=PISocket(host="127.0.0.1", port=server.port))
        try:
            assert "E-709" in device.qIDN()
            axis = device.axes[0]
            assert axis == "1"
            with pytest.raises(
                pipython.GCSError
            ) as err:  # servo on: SVA refused, PIPython reads ERR?
                device.SVA(axis, 12.5)
            assert err.value.val == 79
            device.SVO(axis, False)
            assert device.qSVO()[axis] is False
            device.SVA(axis, 12.5)
            assert device.qSVA()[axis] == 12.5
            assert device.qVOL()[1] == 12.5
            assert device.qVMA()[1] == 100.0 and device.qVMI()[1] == 0.0
            with pytest.raises(pipython.GCSError) as err:
                device.SVA(axis, 150.0)
            assert err.value.val == 66
            assert device.qERR() == 0
            assert len(device.qHLP().splitlines()) > 10
        finally:
            del device  # PIPython closes its socket in __del__ (closing twice raises EBADF there)
            gc.collect()
    assert model.applied_voltage == 12.5


def test_pipelined_setters_are_checked_as_their_replies_arrive(served):
    """command_pipelined: no wait per setter, at most ``pipeline`` ERR? replies outstanding, a
    refusal raised at a later setter or before the next query, the order of the device's
    replies kept."""
    model, conn = served
    conn.pipeline = 3
    conn.command("SVO A 0")
    for k in range(20):
        conn.command_pipelined(f"SVA A {k}")
        assert len(conn._pending) <= 3
    assert conn.query_float("SVA? A", "A") == 19.0  # the query waited for the ERR? replies
    assert not conn._pending
    with pytest.raises(GCSError) as err:
        # outside the device's range: error 66, raised at this setter when its reply is already
        # in by the poll that follows the send, else at a later one
        conn.command_pipelined("SVA A 500")
        for k in range(5):
            conn.command_pipelined(f"SVA A {k}")
    assert err.value.code == 66 and err.value.command == "SVA A 500"
    conn.settle()  # the replies of the setters sent after the refused one (if any) are fine
    conn.command_pipelined("SVA A 3.5")
    conn.settle()
    assert model.applied_voltage == 3.5


class ScriptedTransport:
    """What a device sends, one chunk per read; nothing once the script ends."""

    url = "scripted"

    def __init__(self, chunks: list[bytes]) -> None:
        self.chunks = list(chunks)
        self.reads = 0

    def read(self, timeout: float) -> bytes:
        assert timeout == 0.0  # poll never waits
        self.reads += 1
        return self.chunks.pop(0) if self.chunks else b""


def test_poll_returns_a_reply_only_once_it_is_complete_and_keeps_what_follows():
    """ReplyBuffer.poll: one read per call, None until the reply's end arrived (a reply split
    across reads, as TCP may split it), the bytes after it kept for the next poll."""
    transport = ScriptedTransport([b"", b"0", b"\n1", b"5\n"])
    replies = ReplyBuffer(transport)
    assert replies.poll(gcs_reply_end) is None  # nothing there
    assert replies.poll(gcs_reply_end) is None  # "0" without its end
    assert replies.poll(gcs_reply_end) == b"0\n"  # "1" stays buffered
    assert replies.poll(gcs_reply_end) == b"15\n"
    assert replies.poll(gcs_reply_end) is None and transport.reads == 5


def test_a_full_pipeline_waits_for_the_oldest_reply_and_times_out_on_a_silent_device():
    """Replies 0.5 s late, timeout 0.2 s, pipeline 2: two setters go out without waiting, the
    third waits for the oldest ERR? reply and times out."""
    with EmulatorServer(GCSDeviceModel(), tcp_port=0, faults=Faults(reply_delay=0.5)) as server:
        with make_transport(server.url) as transport:
            conn = GCSConnection(transport, timeout=0.2, pipeline=2)
            sent = 0
            with pytest.raises(DeviceTimeout, match="ERR\\?"):
                for k in range(3):
                    conn.command_pipelined(f"SVA 1 {k}")
                    sent += 1
            assert sent == 2


def test_a_three_axis_controller_writes_every_axis_in_one_command():
    """E-727 class: SAI? lists three axes; ``SVA 1 a 2 b 3 c`` sets all three at once, and a
    pair that is refused leaves every axis where it was."""
    seen = []
    model = GCSDeviceModel(
        axes=("1", "2", "3"), v_min=0.0, v_max=100.0, on_axis_voltage=lambda *a: seen.append(a[:2])
    )
    with EmulatorServer(model, tcp_port=0) as server, make_transport(server.url) as transport:
        conn = GCSConnection(transport, timeout=0.5)
        assert conn.query("SAI?") == ["1", "2", "3"]
        assert "E-727" in conn.query("*IDN?")[0]
        conn.command("SVO 1 0 2 0 3 0")
        assert conn.query_items("SVO?") == {"1": "0", "2": "0", "3": "0"}
        conn.command("SVA 1 10 2 20.5 3 30")
        assert conn.query_items("VOL? 1 2 3") == {"1": "10", "2": "20.5", "3": "30"}
        assert seen == [("1", 10.0), ("2", 20.5), ("3", 30.0)]
        for bad, code in (("SVA 1 11 2 200", 66), ("SVA 1 11 4 5", 15), ("SVA 1 11 2", 1)):
            with pytest.raises(GCSError) as err:
                conn.command(bad)
            assert err.value.code == code
        assert model.applied_voltages() == {"1": 10.0, "2": 20.5, "3": 30.0}
        conn.command("SVO 2 1")  # one axis back in closed loop: open-loop writes to it refused
        with pytest.raises(GCSError) as err:
            conn.command("SVA 1 12 2 12")
        assert err.value.code == 79
        conn.command("SVA 3 31")
        assert conn.query_float("VOL? 3", "3") == 31.0
        assert conn.query_items("VMA? 1 2 3") == {"1": "100", "2": "100", "3": "100"}
        with pytest.raises(GCSError) as err:
            conn.query("VOL? 4")
        assert err.value.code == 17


def test_pipython_sees_three_axes_and_writes_them_together():
    """PIPython in a fresh interpreter: its gateways share class-level connection callbacks, so
    a second GCSDevice in a process whose first one was closed gets a broken socket."""
    script = (
        "import sys\n"
        "from pipython import GCSDevice\n"
        "from pipython.pidevice.interfaces.pisocket import PISocket\n"
        "device = GCSDevice(gateway=PISocket(host='127.0.0.1', port=int(sys.argv[1])))\n"
        "assert device.axes == ['1', '2', '3'], device.axes\n"
        "device.SVO(['1', '2', '3'], [False, False, False])\n"
        "device.SVA(['1', '2', '3'], [5.0, 6.0, 7.0])\n"
        "assert device.qSVA() == {'1': 5.0, '2': 6.0, '3': 7.0}, device.qSVA()\n"
        "assert device.qVOL([1, 2, 3]) == {1: 5.0, 2: 6.0, 3: 7.0}, device.qVOL([1, 2, 3])\n"
        "print('ok')\n"
    )
    model = GCSDeviceModel(axes=("1", "2", "3"), v_min=0.0, v_max=100.0)
    with EmulatorServer(model, tcp_port=0) as server:
        done = subprocess.run(
            [sys.executable, "-c", script, str(server.port)],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]
    writes = [c.split() for c in model.commands if c.startswith("SVA ")]
    assert [w[1::2] for w in writes] == [["1", "2", "3"]]  # one line for the three axes


def test_a_sibling_axis_shares_the_link_and_drives_its_own_channel():
    """Axes 2 and 3 of an E-727 reached from axis 1's open amplifier: the same connection, each
    writing its own output (``SVA``) with its servo switched off; an axis the controller does
    not list is refused with the list."""
    from piezo_stage.commands.emulate import emulated_controller
    from piezo_stage.hardware.amplifier import GCSAmplifier
    from piezo_stage.hardware.errors import ConfigError

    model = emulated_controller(servo_on=True)
    with EmulatorServer(model, tcp_port=0) as server:
        first = GCSAmplifier(make_transport(server.url), axis="1")
        first.open()
        try:
            second, third = first.sibling("2"), first.sibling("3")
            assert (second.channel, third.channel) == (2, 3)
            assert second.conn is first.conn and first.axis == "1" and first.channel == 1
            assert not model.servo["2"] and not model.servo["3"]
            for amplifier, volts in ((first, 10.0), (second, 20.0), (third, 30.0)):
                amplifier.write_voltage(volts)
            assert [third.read_voltage(), second.read_voltage(), first.read_voltage()] == (
                pytest.approx([30.0, 20.0, 10.0], abs=1e-6)
            )
            with pytest.raises(ConfigError, match=r"axis '4' not on controller \(SAI\? lists"):
                first.sibling("4")
        finally:
            first.close()
