"""Fault injection counts for the hardware paths: the voltage driver and the optoNCDT
reader against their emulators, under seeded random fault schedules.

Driver: the PI GCS emulator behind an in-process loopback link on a fake clock (deterministic);
a random schedule of commands (-50..150 V, 0-400 ms apart), watchdog ticks every 10 ms, link
hang-ups, slow reconnects (the device gone for 0.5 s) and 1 % corrupted reply bytes. Printed:
commands sent, device writes, reconnects, the largest single step against the per-write cap
(slew_rate x min(write_period, 25 ms)), the worst slew excess over any interval (|dv| - slew
dt - cap, <= 0 when the ramps hold) and the watchdog latency (last received command -> output at
safe_voltage, minus command_timeout and the ramp time).

Reader: every frame family, the emulator's encoding of a slow sine (ground truth per frame):
10^6 random bytes; one byte lost in every frame; one byte replaced in every frame; 1e-3 byte
corruption; mixed damage. Printed: OK values (of them from damaged or inserted frames, and of
those the ones with no exact value in reach before them), OK values off the truth by > 1e-3 of
the measuring range, the worst error, OK values past the speed gate (0 by construction), and the
frames until publishing again after garbage.

Baseline: the figures measured on the driver and reader before their fault hardening: 100 V single
steps at 2000 V/s, 4.86 s to safe with queued commands, 396 OK values per 10^5 random bytes,
210 wrong OK values from 2000 frames with one random byte each.

    python bench/faults.py [--seconds 300] [--seed 1]
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from piezo_stage.hardware.amplifier import GCSAmplifier  # noqa: E402
from piezo_stage.hardware.driver import MAX_STEP_TIME, DriverConfig, DriverState, VoltageDriver  # noqa: E402
from piezo_stage.hardware.emulators import (  # noqa: E402
    Faults,
    GCSDeviceModel,
    LoopbackTransport,
    ManualClock,
)
from piezo_stage.hardware.emulators.streams import damage, score, sensor_stream  # noqa: E402
from piezo_stage.hardware.errors import HardwareError  # noqa: E402
from piezo_stage.hardware.optoncdt import (  # noqa: E402
    FrameCheck,
    OptoNCDTParser,
    SampleBlock,
    Status,
    frame_format,
)

FAMILIES = (("ild1700", None), ("ild1320", 18), ("ild1320", 16), ("ild1750", None))


class FlakyLink(LoopbackTransport):
    """A hang-up leaves the device unreachable for ``gone`` seconds of the fake clock."""

    gone = 0.5
    back_at = -math.inf

    def disconnect(self) -> None:
        super().disconnect()
        self.back_at = self.clock() + self.gone

    def open(self) -> None:
        self.down = self.clock() < self.back_at
        super().open()


def bench_driver(seconds: float, seed: int, slew: float = 2000.0, timeout: float = 0.5) -> dict:
    rng = np.random.default_rng(seed)
    clock = ManualClock()
    model = GCSDeviceModel(v_min=-30.0, v_max=130.0)
    applied = [(0.0, model.voltage)]
    model.on_voltage = lambda v, at=None: applied.append((clock.t, float(v)))
    faults = Faults(corrupt=0.01, seed=seed)
    link = FlakyLink(model, faults, clock=clock)
    config = DriverConfig(
        0.0, 100.0, slew_rate=slew, command_timeout=timeout, reconnect_delay=0.001
    )
    driver = VoltageDriver(GCSAmplifier(link, timeout=0.02), config, clock=clock, sleep=clock.sleep)
    driver.connect()
    commands = refused = 0
    latencies = []
    ramp = 0.0
    t_next = 0.0
    t_last_command = 0.0
    while clock.t < seconds:
        clock.t += 0.01
        if clock.t >= t_next:
            if rng.random() < 0.02:
                link.disconnect()
            if rng.random() < 0.05:  # a silence longer than command_timeout
                t_next = clock.t + rng.uniform(timeout, 3 * timeout)
            else:
                t_next = clock.t + rng.uniform(0.0, 0.4)
            commands += 1
            try:
                driver.set_voltage(float(rng.uniform(-50.0, 150.0)))
            except HardwareError:
                refused += 1
            t_last_command = clock.t
        was, trips, v_before = driver.state, driver.trips, model.voltage
        driver.tick()
        if driver.trips != trips:
            ramp = abs(v_before - config.safe_voltage) / slew  # time the ramp down needs
        if was is not DriverState.SAFE and driver.state is DriverState.SAFE:
            latencies.append(clock.t - t_last_command - timeout - ramp)
        if driver.state is DriverState.DISCONNECTED and clock.t >= link.back_at:
            driver.wait_connected(5.0)
    driver.close()
    t, v = np.array(applied).T
    cap = slew * min(config.write_period, MAX_STEP_TIME)
    steps = np.abs(np.diff(v))
    worst = -math.inf
    for i in range(0, t.size, 256):  # all pairs, in blocks
        dv = np.abs(v[i : i + 256, None] - v[None, :])
        dt = np.abs(t[i : i + 256, None] - t[None, :])
        worst = max(worst, float(np.max(dv - slew * dt - cap)))
    return {
        "commands": commands,
        "refused (link down)": refused,
        "device writes": len(applied) - 1,
        "reconnects": driver.reconnects,
        "watchdog trips": driver.trips,
        "largest step [V]": float(steps.max()),
        "per-write cap [V]": cap,
        "worst slew excess [V]": worst,
        "watchdog latency beyond timeout + ramp [ms] (max)": 1e3 * max(latencies)
        if latencies
        else math.nan,
    }


def bench_reader(seed: int, mr: float = 2e-3, rate: float = 1000.0) -> list[dict]:
    t = np.arange(100_000) / rate
    truth_d = 0.5 * mr + 0.05 * mr * np.sin(2 * np.pi * 0.5 * t)
    check = FrameCheck(relock_frames=6, max_speed=1e-3, rate=rate)
    rows = []
    for family, bits in FAMILIES:
        fmt = frame_format(family, bits)
        row = {"family": f"{family}{'-' + str(bits) if bits else ''}"}
        junk = np.random.default_rng(seed).integers(0, 256, 1_000_000, dtype=np.uint8).tobytes()
        parser = OptoNCDTParser(fmt, mr)
        block = SampleBlock.concat(
            [parser.feed(junk[i : i + 4096]) for i in range(0, len(junk), 4096)]
        )
        row["1e6 random bytes: OK"] = int(np.count_nonzero(block.status == Status.OK))
        data, origin, truth = sensor_stream(fmt, truth_d, mr)
        for name, kw in (
            ("lose 1/frame", dict(lose_one=True)),
            ("replace 1/frame", dict(replace_one=True)),
            ("corrupt 1e-3", dict(corrupt=1e-3)),
            ("mixed 1e-3", dict(corrupt=1e-3, drop=1e-3, garbage=1e-3)),
        ):
            d, o = damage(data, origin, np.random.default_rng(seed), fmt.bytes_per_value, **kw)
            s = score(OptoNCDTParser(fmt, mr, check), d, o, truth, 1e-3 * mr)
            row[name] = (
                f"{s.ok} OK ({s.damaged_ok} damaged, {s.chained} chained), "
                f"{s.wrong} off, worst {s.worst / mr:.2e} MR, "
                f"{s.gate_breaks + s.beyond_gate} past the gate"
            )
        rng = np.random.default_rng(seed)
        good, _, _ = sensor_stream(fmt, truth_d[:40], mr)
        latency = 0
        for _ in range(300):
            parser = OptoNCDTParser(fmt, mr, check)
            parser.feed(good.tobytes())
            garbage = rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8).tobytes()
            ok = parser.feed(garbage + good.tobytes()).status[-40:] == Status.OK
            latency = max(latency, int(np.argmax(ok)) + 1 if ok.any() else 99)
        row["frames to publish again (max of 300)"] = latency
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=300.0, help="simulated driver run time")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR + 10)  # the driver's warnings are the faults we inject
    print(
        f"driver: GCS emulator, 2000 V/s, 0-100 V, command_timeout 0.5 s, {args.seconds:g} s "
        "of random commands, hang-ups and 1 % corrupted replies"
    )
    for key, value in bench_driver(args.seconds, args.seed).items():
        print(f"  {key:58s} {value:.4g}" if isinstance(value, float) else f"  {key:58s} {value}")
    print(
        "  baseline (earlier driver): single steps of 100 V at 2000 V/s (cap 20 V); "
        "4.86 s to safe with queued commands"
    )
    print(
        "reader: MR 2 mm, 1 kHz, true motion 0.31 mm/s, max_speed 1 mm/s, relock 6 frames; "
        "tolerance 1e-3 MR"
    )
    for row in bench_reader(args.seed):
        print(f"  {row.pop('family')}")
        for key, value in row.items():
            print(f"    {key:38s} {value}")
    print(
        "  baseline (earlier reader): 396 OK values per 1e5 random bytes; 210 wrong OK values "
        "(up to 4.5 mm) from 2000 frames with one random byte each"
    )


if __name__ == "__main__":
    main()
