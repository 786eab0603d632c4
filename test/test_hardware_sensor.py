"""optoNCDT sensor reader against the sensor emulator over a pty: stream, ASCII commands, faults,
reconnect."""

from __future__ import annotations

import time

import numpy as np
import pytest

from piezo_stage.hardware.emulators import EmulatorServer, Faults, OptoNCDTDeviceModel
from piezo_stage.hardware.errors import ConfigError, ConnectionLost, SensorCommandError
from piezo_stage.hardware.optoncdt import FrameCheck, SampleBlock, Status, frame_format
from piezo_stage.hardware.sensor import SensorConfig, SensorReader

pytestmark = pytest.mark.ros

MR = 10e-3
K = FrameCheck().relock_frames
FAMILIES = ["ild1700", "ild1320", "ild1750"]


def ramp(t: np.ndarray) -> np.ndarray:
    return 1e-3 + 2e-3 * t  # 2 mm/s from 1 mm


def collect(reader: SensorReader, n: int, limit: float = 5.0) -> SampleBlock:
    blocks, got, deadline = [], 0, time.monotonic() + limit
    while got < n and time.monotonic() < deadline:
        block = reader.read(0.05)
        blocks.append(block)
        got += len(block)
    return SampleBlock.concat(blocks)


def served(family: str, faults: Faults | None = None, link: str | None = None, **kw):
    model = OptoNCDTDeviceModel(frame_format(family), MR, kw.pop("rate", 2000.0), **kw)
    return model, EmulatorServer(model, pty=True, pty_link=link, faults=faults)


@pytest.mark.parametrize("family", FAMILIES)
def test_stream_follows_the_source(family):
    model, server = served(family, source=ramp)
    with server:
        reader = SensorReader.from_url(server.url, SensorConfig(family, MR))
        reader.connect()
        block = collect(reader, 400)
        reader.close()
    fmt = frame_format(family)
    # unlocked at the start: the first K - 1 frames are withheld, then every one is OK
    assert len(block) >= 400 and np.all(block.status[K - 1 :] == Status.OK)
    d = block.displacement[K - 1 :]
    quantum = MR * (fmt.scale if family != "ild1750" else 1 / 65536)
    assert np.all(np.diff(d) >= -quantum)  # in order, none lost or duplicated out of order
    assert np.all(np.diff(d) <= 2e-3 / 2000 + 2 * quantum)  # consecutive samples, no gaps
    assert np.all((d > 1e-3 - quantum) & (d < MR))


@pytest.mark.parametrize("family", ["ild1320", "ild1750"])
def test_ascii_commands_while_streaming(family):
    model, server = served(family, source=ramp)
    with server:
        reader = SensorReader.from_url(server.url, SensorConfig(family, MR))
        reader.connect()
        before = collect(reader, 100)
        info = reader.get_info()
        assert info["Name"].startswith(family.upper()) and info["Measuring range"] == "10 mm"
        assert reader.command("MEASRATE") == ["MEASRATE 2.000"]
        with pytest.raises(SensorCommandError) as err:
            reader.command("NOSUCHCOMMAND")
        assert err.value.code == "E01"
        with pytest.raises(SensorCommandError):
            reader.command("MEASRATE 99")
        after = collect(reader, 100)
        assert reader.command("MEASRATE 0.5") == []
        assert model.rate == 500.0
        reader.close()
    both = SampleBlock.concat([before, after])
    ok = both.status == Status.OK
    # frames next to reply text are withheld until the lock is back; none lost, none out of order
    assert np.all(before.status[K - 1 :] == Status.OK) and ok.mean() > 0.5
    assert np.all(np.diff(both.displacement[ok]) >= -1e-6)
    assert reader.parser.stats.text_bytes > 0


def test_ild1700_has_no_ascii_command_channel():
    model, server = served("ild1700")
    with server:
        reader = SensorReader.from_url(server.url, SensorConfig("ild1700", MR))
        reader.connect()
        with pytest.raises(SensorCommandError):
            reader.command("GETINFO")
        reader.close()


def test_out_of_range_and_lost_target_are_error_values():
    def source(t):
        d = np.where(t % 0.03 < 0.01, 1.5 * MR, np.where(t % 0.03 < 0.02, -1e-3, np.nan))
        return d

    model, server = served("ild1320", source=source)
    with server:
        reader = SensorReader.from_url(server.url, SensorConfig("ild1320", MR))
        reader.connect()
        block = collect(reader, 300)
        reader.close()
    assert set(np.unique(block.status)) == {Status.TOO_FAR, Status.TOO_CLOSE, Status.NO_TARGET}
    assert np.all(np.isnan(block.displacement))


@pytest.mark.parametrize("family", FAMILIES)
def test_corrupted_and_dropped_bytes_never_give_invalid_displacements(family):
    faults = Faults(drop=0.01, corrupt=0.01, seed=3)
    model, server = served(
        family,
        faults=faults,
        source=lambda t: np.full(t.shape, 4e-3),
        error_probability=0.05,
        seed=4,
    )
    with server:
        reader = SensorReader.from_url(server.url, SensorConfig(family, MR))
        reader.connect()
        block = collect(reader, 1000)
        reader.close()
    ok = block.status == Status.OK
    assert np.all((block.displacement[ok] >= 0) & (block.displacement[ok] <= MR))
    assert np.mean(np.abs(block.displacement[ok] - 4e-3) < 2e-6) > 0.9  # garbage stays rare
    assert (~ok).sum() > 0.02 * len(block)  # injected error values come through as errors
    assert np.all(np.isnan(block.displacement[~ok]))


def test_reconnect_after_hang_up_and_staleness(tmp_path):
    link = str(tmp_path / "laser")
    faults = Faults()
    model, server = served("ild1320", faults=faults, link=link)
    now = [0.0]
    with server:
        reader = SensorReader.from_url(
            link, SensorConfig("ild1320", MR, stale_timeout=0.5), clock=lambda: now[0]
        )
        reader.connect()
        assert len(collect(reader, 50)) >= 50 and not reader.stale
        faults.silent = True
        time.sleep(0.05)
        reader.read(0.05)
        reader.read(0.05)
        now[0] += 1.0
        assert len(reader.read(0.05)) == 0 and reader.stale
        faults.silent = False
        server.disconnect()
        with pytest.raises(ConnectionLost):
            for _ in range(100):
                reader.read(0.02)
        reader.reconnect()
        assert len(collect(reader, 50)) >= 50 and not reader.stale
        assert reader.reconnects == 1
        reader.close()


def test_sensor_config_validation():
    with pytest.raises(ConfigError):
        SensorConfig("ild1320", 0.0)
    with pytest.raises(ConfigError):
        SensorReader.from_url("/dev/null", SensorConfig("ild4000", MR))


def test_emulated_sensor_wakes_on_its_sample_clock():
    """Frames leave when their sample is due (next_due), not on a free-running stream tick
    whose phase against the samples would be a constant lag the reader's clock cannot see."""
    model = OptoNCDTDeviceModel(frame_format("ild1320"), MR, 1000.0)
    assert model.next_due() is None  # before the first sample
    t0 = 100.0
    model.stream(t0)  # sample 0 at t0
    assert model.next_due() == pytest.approx(t0 + 1e-3, abs=1e-8)
    data = model.stream(t0 + 2.5e-3)  # samples 1 and 2 are due, 3 is not
    assert len(data) == 2 * 3 and model.sent_samples == 3
    assert model.next_due() == pytest.approx(t0 + 3e-3, abs=1e-8)
    assert model.stream(t0 + 2.9e-3) == b""  # nothing due before it
