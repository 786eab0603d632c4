"""An emulated stage answers for what its amplifier heard: a command that reached the amplifier
while the emulator's process was stalled applies from its arrival, and a sensor's sample after
that arrival shows it (on a bench the amplifier applies a command when it arrives, whatever the
sensor does). The sensor waits for the amplifier's thread to handle its input before it takes a
sample past the last instant the thread has heard."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from piezo_stage.hardware.emulators import scanner
from piezo_stage.hardware.emulators.scanner import ScannerCoupling
from piezo_stage.hardware.emulators.server import EmulatorServer

RATE = 1000.0
T0 = 100.0  # the sensor's sample 0 [s, server time]
GAIN = 1e-6  # [m/V] of the static stage below


class StaticAxis:
    """One axis whose reading is GAIN times the voltage held over the step."""

    def step(self, commands, dt):
        volts = np.asarray(commands, dtype=float)
        return volts, GAIN * volts, np.zeros(volts.size, dtype=np.int64)


def coupling(heard: list[float]) -> ScannerCoupling:
    c = ScannerCoupling(StaticAxis(), ["1"], RATE, standoff=0.0)
    c.heard = lambda: heard[0]
    return c


def read_in_thread(source, times) -> tuple[threading.Thread, list]:
    out: list = []
    thread = threading.Thread(target=lambda: out.append(source(times)), daemon=True)
    thread.start()
    return thread, out


@pytest.mark.unit
def test_a_command_heard_late_applies_from_its_arrival_in_the_samples_after_it():
    heard = [T0]  # the amplifier has handled its input up to the sensor's sample 0
    c = coupling(heard)
    source = c.source(0, lambda: T0)
    thread, out = read_in_thread(source, np.arange(100) / RATE)  # up to T0 + 99 ms
    time.sleep(0.05)
    # the amplifier's thread, back from a stall, handles a command that arrived at T0 + 30 ms
    c.on_axis_voltage("1", 50.0, at=T0 + 0.030)
    heard[0] = T0 + 1.0
    thread.join(5.0)
    readings = out[0]
    np.testing.assert_array_equal(readings[:30], 0.0)
    np.testing.assert_allclose(readings[30:], 50.0 * GAIN)


@pytest.mark.unit
def test_a_sensor_waits_for_a_silent_amplifier_no_longer_than_its_bound(monkeypatch):
    monkeypatch.setattr(scanner, "HEARD_WAIT", 0.2)
    c = coupling([T0])  # never hears further
    source = c.source(0, lambda: T0)
    started = time.monotonic()
    readings = source(np.arange(10) / RATE)
    waited = time.monotonic() - started
    assert 0.2 <= waited < 5.0
    np.testing.assert_array_equal(readings, 0.0)  # the voltage it had


@pytest.mark.unit
def test_samples_already_taken_do_not_wait():
    heard = [T0 + 1.0]
    c = coupling(heard)
    source = c.source(0, lambda: T0)
    source(np.arange(50) / RATE)
    heard[0] = -np.inf  # the amplifier busy from now on
    started = time.monotonic()
    source(np.arange(50) / RATE)  # the same samples again: in the backlog
    assert time.monotonic() - started < 0.5


class _Blocking:
    """A device whose first command keeps its thread busy until ``release`` is set."""

    name = "blocking"
    stream_period = None

    def __init__(self) -> None:
        self.release = threading.Event()
        self.busy = threading.Event()
        self.arrived = float("nan")  # when the command reached the server

    def session(self):
        model = self

        class _Session:
            def handle(self, data: bytes, now: float) -> bytes:
                model.arrived = now
                model.busy.set()
                model.release.wait(10.0)
                return b"ok\n"

        return _Session()

    def stream(self, now: float) -> bytes:
        return b""


@pytest.mark.ros
def test_the_server_has_heard_until_now_when_idle_and_not_past_a_command_it_is_handling():
    model = _Blocking()
    with EmulatorServer(model, tcp_port=0) as server:
        time.sleep(0.1)
        before = time.monotonic()
        assert server.heard_until() >= before  # waiting with nothing to read: now
        with socket.create_connection(("127.0.0.1", server.port), timeout=5.0) as client:
            client.sendall(b"command\n")
            assert model.busy.wait(5.0)
            arrived = model.arrived
            for _ in range(5):  # busy with it: heard only up to before its arrival
                assert server.heard_until() <= arrived
                time.sleep(0.02)
            model.release.set()
            assert client.recv(16) == b"ok\n"
            deadline = time.monotonic() + 5.0
            while server.heard_until() <= arrived and time.monotonic() < deadline:
                time.sleep(0.01)
            assert server.heard_until() > arrived
