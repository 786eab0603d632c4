"""Thorlabs MDT69x ASCII protocol against the MDT emulator over a pty."""

from __future__ import annotations

import pytest

from piezo_stage.hardware.emulators import EmulatorServer, MDTDeviceModel
from piezo_stage.hardware.errors import ConfigError, DeviceError, ProtocolError
from piezo_stage.hardware.mdt69x import MDTConnection, mdt_reply_end, parse_bracketed, reply_body
from piezo_stage.hardware.transport import make_transport

pytestmark = pytest.mark.ros


@pytest.fixture(params=[True, False], ids=["echo", "no-echo"])
def served(request):
    model = MDTDeviceModel("MDT693B", vlimit=100.0, echo=request.param)
    with EmulatorServer(model, pty=True) as server:
        with make_transport(server.url, 115200) as transport:
            yield model, MDTConnection(transport, timeout=0.5)


def test_reply_parsing():
    assert mdt_reply_end(b"xvoltage?\r[ 12.34]\r") == -1
    assert mdt_reply_end(b"xvoltage?\r[ 12.34]\r>") == len(b"xvoltage?\r[ 12.34]\r>")
    assert reply_body(b"xvoltage?\r[ 12.34]\r>", "xvoltage?") == "[ 12.34]"
    assert reply_body(b"[ 12.34]\r>", "xvoltage?") == "[ 12.34]"
    assert parse_bracketed("[ 12.34]", "q") == 12.34
    assert parse_bracketed("150V", "vlimit?") == 150.0
    with pytest.raises(ProtocolError):
        parse_bracketed("[ ]", "q")


def test_set_and_read_voltage_and_limits(served):
    model, conn = served
    assert "MDT693B" in conn.exchange("id?")
    assert conn.query_float("vlimit?") == 100.0
    assert conn.exchange("xvoltage=37.5") == ""
    assert conn.query_float("xvoltage?") == 37.5
    assert conn.exchange("YVOLTAGE=12") == ""  # case-insensitive
    assert model.voltage == {"x": 37.5, "y": 12.0, "z": 0.0}
    assert conn.query_float("xmax?") == 100.0


def test_device_clamps_to_soft_limits(served):
    model, conn = served
    conn.exchange("xmax=50")
    conn.exchange("xvoltage=80")
    assert conn.query_float("xvoltage?") == 50.0


@pytest.mark.parametrize("command", ["foo?", "qvoltage=1", "xvoltage=abc", "xvoltage=500"])
def test_undefined_commands_raise(served, command):
    model, conn = served
    with pytest.raises(DeviceError) as err:
        conn.exchange(command)
    assert err.value.code == "CMD_NOT_DEFINED"
    assert model.voltage["x"] == 0.0
    assert conn.query_float("xvoltage?") == 0.0  # the link is still in step after the error


def test_single_channel_model_has_only_x():
    model = MDTDeviceModel("MDT694B")
    assert model.axes == ("x",)
    assert model.execute("yvoltage=1").endswith(b"CMD_NOT_DEFINED>")
    with pytest.raises(ConfigError):
        MDTDeviceModel("MDT694B", vlimit=120.0)


def test_the_three_channels_are_written_in_one_command(served):
    model, conn = served
    seen = []
    model.on_axis_voltage = lambda axis, value, at: seen.append((axis, value))
    conn.exchange("xyzvoltage=10,20.5,30")
    assert model.applied_voltages() == {"x": 10.0, "y": 20.5, "z": 30.0}
    assert seen == [("x", 10.0), ("y", 20.5), ("z", 30.0)]
    assert conn.exchange("xyzvoltage?").replace(" ", "") == "[10.00,20.50,30.00]"
    for bad in ("xyzvoltage=1,2", "xyzvoltage=1,2,200", "xyzvoltage=1,x,3"):
        with pytest.raises(DeviceError):
            conn.exchange(bad)
    assert model.applied_voltages() == {"x": 10.0, "y": 20.5, "z": 30.0}
