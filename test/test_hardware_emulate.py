"""`piezo-stage emulate`: printed endpoints, clients connecting to them, the rig coupling, clean
shutdown."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from piezo_stage.cli import main
from piezo_stage.hardware.amplifier import make_amplifier
from piezo_stage.hardware.driver import DriverConfig, VoltageDriver
from piezo_stage.hardware.emulators.rig import RigEmulator
from piezo_stage.hardware.emulators.voltage_log import read_voltage_log
from piezo_stage.hardware.errors import ConnectionLost
from piezo_stage.hardware.gcs import GCSConnection
from piezo_stage.hardware.optoncdt import SampleBlock, Status, frame_format
from piezo_stage.hardware.sensor import SensorConfig, SensorReader
from piezo_stage.hardware.transport import make_transport

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
MR = 10e-3


def run_in_thread(argv, capsys, n_lines: int):
    """Start ``main(argv)`` in a thread; return (thread, endpoint lines printed, result holder).
    What an earlier emulator printed on its way out ("gcs: outputs at exit: ...") is dropped
    first: it is not this one's endpoint."""
    capsys.readouterr()
    result: dict[str, int] = {}
    thread = threading.Thread(target=lambda: result.setdefault("rc", main(argv)), daemon=True)
    thread.start()
    text, deadline = "", time.monotonic() + 30.0
    while len(text.splitlines()) < n_lines and time.monotonic() < deadline:
        time.sleep(0.02)
        text += capsys.readouterr().out
    return thread, dict(line.split(": ", 1) for line in text.splitlines()), result


def test_gcs_subprocess_prints_pty_and_stops_cleanly_on_sigint():
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "piezo_stage.cli", "emulate", "gcs", "--pty"],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        cwd=ROOT,
    )
    try:
        line = proc.stdout.readline().strip()
        assert re.fullmatch(r"gcs: /dev/pts/\d+", line)
        driver = VoltageDriver(
            make_amplifier("gcs", line.split(": ")[1]), DriverConfig(v_min=0, v_max=100)
        )
        driver.connect()
        assert driver.set_voltage(42.0).sent == 42.0
        assert driver.shutdown() == 0.0
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0


def test_gcs_on_tcp_and_mdt_on_pty_in_process(capsys):
    thread, ends, result = run_in_thread(
        ["emulate", "gcs", "--tcp", "0", "--duration", "0.5"], capsys, 1
    )
    assert ends["gcs"].startswith("tcp://127.0.0.1:")
    amp = make_amplifier("gcs", ends["gcs"])
    assert "E-709" in amp.open().identity
    amp.close()
    thread.join(5)
    assert result["rc"] == 0

    thread, ends, result = run_in_thread(
        ["emulate", "mdt69x", "--vlimit", "75", "--duration", "0.5"], capsys, 1
    )
    amp = make_amplifier("mdt69x", ends["mdt69x"])
    assert amp.open().v_max == 75.0
    amp.close()
    thread.join(5)
    assert result["rc"] == 0


def test_an_e727_class_controller_logs_what_each_axis_applied(capsys, tmp_path):
    log = tmp_path / "applied.csv"
    thread, ends, result = run_in_thread(
        ["emulate", "gcs", "--axes", "1,2,3", "--tcp", "0", "--log", str(log), "--duration", "1"],
        capsys,
        1,
    )
    with make_transport(ends["gcs"]) as transport:
        conn = GCSConnection(transport, timeout=1.0)
        assert conn.query("SAI?") == ["1", "2", "3"]
        conn.command("SVO 1 0 2 0 3 0")
        conn.command("SVA 1 10 2 20 3 30")
        conn.command("SVA 2 21")
    thread.join(5)
    assert result["rc"] == 0
    rows = read_voltage_log(log)
    assert {axis: [v for _, v in r] for axis, r in rows.items()} == {
        "1": [10.0],
        "2": [20.0, 21.0],
        "3": [30.0],
    }
    times = [t for r in rows.values() for t, _ in r]
    assert all(0.0 <= t < 5.0 for t in times) and rows["2"][0][0] <= rows["2"][1][0]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["gcs", "--axes", "1,1"], "distinct alphanumeric axis names"),
        (["gcs", "--axes", "1,,2"], "distinct alphanumeric axis names"),
        (["mdt69x", "--log", "/nonexistent/dir/a.csv"], "--log /nonexistent/dir/a.csv: no folder"),
    ],
)
def test_bad_axes_or_log_are_one_line_and_exit_2(argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        rc = main(["emulate", *argv, "--duration", "0.1"])
        raise SystemExit(rc)
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1]


def test_optoncdt_with_error_values_and_periodic_disconnect(capsys, tmp_path):
    link = str(tmp_path / "laser")
    argv = [
        "emulate",
        "optoncdt",
        "--family",
        "ild1700",
        "--rate",
        "2000",
        "--error-values",
        "0.3",
        "--disconnect-every",
        "0.3",
        "--link",
        link,
        "--duration",
        "1.0",
        "--seed",
        "1",
    ]
    thread, ends, result = run_in_thread(argv, capsys, 1)
    assert ends["optoncdt"] == link
    reader = SensorReader.from_url(link, SensorConfig("ild1700", MR, reconnect_delay=0.05))
    reader.connect()
    statuses, lost = [], 0
    deadline = time.monotonic() + 0.8
    while time.monotonic() < deadline:
        try:
            statuses.append(reader.read(0.05).status)
        except ConnectionLost:
            lost += 1
            reader.reconnect()
    reader.close()
    thread.join(5)
    assert result["rc"] == 0
    status = np.concatenate(statuses)
    assert lost >= 1 and reader.reconnects == lost  # hung up at least once, came back each time
    assert (status == Status.OK).any() and (status != Status.OK).mean() > 0.1


class LinearStage:
    """A stand-in plant for testing the wiring only: y = 1e-7 m/V * v, one sample of delay."""

    def __init__(self) -> None:
        self.steps = 0

    def step(self, command_voltage: float, dt: float) -> tuple[float, float, int]:
        self.steps += 1
        return command_voltage, 1e-7 * command_voltage, 0


def test_rig_couples_amplifier_voltage_to_sensor_reading():
    stage = LinearStage()
    fmt = frame_format("ild1320")
    with RigEmulator(
        stage, fmt, MR, amplifier="gcs", amplifier_tcp_port=0, rate=2000.0, standoff=4e-3
    ) as rig:
        driver = VoltageDriver(
            make_amplifier("gcs", rig.amplifier_server.url), DriverConfig(v_min=0, v_max=100)
        )
        reader = SensorReader.from_url(rig.sensor_server.url, SensorConfig("ild1320", MR))
        driver.connect()
        reader.connect()
        for volts in (0.0, 100.0):
            driver.set_voltage(volts)
            time.sleep(0.1)
            reader.read(0.05)  # discard samples taken before the new voltage
            block = reader.read(0.1)
            assert len(block) and np.all(block.status == Status.OK)
            expected = 4e-3 + 1e-7 * volts
            assert np.all(np.abs(block.displacement - expected) <= MR * 1.02 / 65520)
        driver.shutdown()
        reader.close()
        deadline = (
            time.monotonic() + 2.0
        )  # the plant gets 0 V from the samples taken after the ramp
        while rig.coupling.applied[0] != 0.0 and time.monotonic() < deadline:
            time.sleep(0.01)
    assert stage.steps > 100 and rig.coupling.applied[0] == 0.0


def test_rig_command_with_the_simulated_plant(capsys, tmp_path):
    """`emulate rig` with the real SimulatedStage: voltage in, plant displacement out."""
    from piezo_stage.model.bouc_wen import BoucWenParameters
    from piezo_stage.model.parameter_set import Dynamics, ParameterSet, save_parameter_set

    params = ParameterSet(
        name="ch11_rig",
        form="dynamic",
        bouc_wen=BoucWenParameters(
            kappa=(10.35e6,), kappa_w=43.57, rho=8.566e4, sigma=0.9153, n=1.176
        ),
        dynamics=Dynamics(m=5.3e-3, c=13.0),
        input_name="voltage",
        output_name="displacement",
    )
    path = tmp_path / "rig.yaml"
    save_parameter_set(params, path)
    argv = [
        "emulate",
        "rig",
        "--params",
        str(path),
        "--family",
        "ild1750",
        "--measuring-range",
        "2e-3",
        "--rate",
        "2000",
        "--duration",
        "8.0",
    ]
    thread, ends, result = run_in_thread(argv, capsys, 2)
    driver = VoltageDriver(make_amplifier("gcs", ends["gcs"]), DriverConfig(v_min=0, v_max=100))
    reader = SensorReader.from_url(ends["optoncdt"], SensorConfig("ild1750", 2e-3))
    driver.connect()
    reader.connect()

    def read_at_least(n: int) -> SampleBlock:
        """The next n samples or more (a loaded host delivers them late, never fewer)."""
        blocks, deadline = [], time.monotonic() + 5.0
        while sum(len(b) for b in blocks) < n and time.monotonic() < deadline:
            blocks.append(reader.read(0.1))
        return SampleBlock.concat(blocks)

    k = SensorConfig("ild1750", 2e-3).relock_frames
    rest = read_at_least(k + 10)  # the first K - 1 frames are withheld (unlocked), then all OK
    driver.set_voltage(100.0)
    read_at_least(400)  # 0.2 s at 2 kHz: the stage settles
    moved = read_at_least(10)
    driver.shutdown()
    reader.close()
    thread.join(15)
    assert result["rc"] == 0
    assert (
        len(rest) > k
        and np.all(rest.status[k - 1 :] == Status.OK)
        and np.all(moved.status == Status.OK)
    )
    assert np.median(moved.displacement) > np.nanmedian(rest.displacement) + 1e-6  # ~10 µm at 100 V


def test_rig_sensor_link_and_signal_waits_for_the_driver_ramp(tmp_path):
    """`emulate rig --sensor-link PATH`: the reader opens the fixed path; on SIGINT the emulator
    keeps serving its connected driver, which ramps to 0 V through it, then exits 0 once the
    driver hung up, removing the link (a launcher signals every process at once)."""
    link = tmp_path / "sensor"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "piezo_stage.cli",
            "emulate",
            "rig",
            "--params",
            "ch10_patch.yaml",
            "--amp-tcp",
            "0",
            "--sensor-link",
            str(link),
            "--family",
            "ild1320",
            "--measuring-range",
            "2e-3",
            "--linger",
            "30",
        ],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        cwd=ROOT,
    )
    try:
        ends = dict(proc.stdout.readline().strip().split(": ", 1) for _ in range(2))
        assert ends["optoncdt"] == str(link) and link.is_symlink()
        driver = VoltageDriver(
            make_amplifier("gcs", ends["gcs"]), DriverConfig(v_min=0, v_max=100, slew_rate=500.0)
        )
        reader = SensorReader.from_url(str(link), SensorConfig("ild1320", 2e-3))
        driver.connect()
        reader.connect()
        driver.ramp_to(60.0)
        proc.send_signal(signal.SIGINT)
        time.sleep(0.3)
        assert proc.poll() is None  # still there for the connected driver
        assert driver.shutdown() == 0.0  # the ramp down reached the device and was read back
        reader.close()
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not os.path.lexists(link)
