"""`piezo-stage identify --device URL`: the ch. 10 identification at a PI controller's servo
rate (:mod:`piezo_stage.experiments.servo_identification`), run from the identify command."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from typing import TYPE_CHECKING, Callable, TypeVar

from piezo_stage.commands.quick import QUICK_SETTLE_PERIODS, quick_run, say_quick
from piezo_stage.errors import PiezoStageError
from piezo_stage.identification.methods import Method, identify_runs
from piezo_stage.identification.pipeline import IdentifyOptions
from piezo_stage.identification.recording import Recording
from piezo_stage.identification.result import IdentificationResult
from piezo_stage.identification.simfit import FitOptions

if TYPE_CHECKING:
    from piezo_stage.experiments.servo_identification import TWaveExcitation
    from piezo_stage.hardware.amplifier import DeviceInfo, GCSAmplifier
    from piezo_stage.hardware.pi_recorder import ServoRecorder

_T = TypeVar("_T")

#: [samples] the ch. 11 form's pairing of a record: position k is read between voltage k - 1,
#: held the cycle before, and voltage k, held the cycle after; the stage (its 7 kHz resonance
#: slower than a 50 µs step) follows their mean, as the average of u = Φ(x) + m x'' + c x'
#: over a held step is that step's voltage. Delaying the measured input by half a sample
#: pairs it so (the input's noise hides the corners that would time it)
MIDPOINT_LAG = 0.5


class DeviceRunError(PiezoStageError):
    """The controller refused, the link failed or the record is unusable (exit 2)."""


def pair(text: str, name: str, kind: Callable[[str], _T]) -> tuple[_T, _T]:
    """``A,B`` of option ``name`` as two values of ``kind`` (:class:`DeviceRunError`)."""
    try:
        a, b = (kind(v) for v in text.split(","))
    except ValueError:
        raise DeviceRunError(f"{name} needs two comma-separated values, got {text!r}") from None
    return a, b


def excitation_from(args: argparse.Namespace, v_min: float, v_max: float) -> TWaveExcitation:
    """The T-wave pair the options ask for, defaults from the output range (VMI?, VMA?)."""
    from piezo_stage.experiments.servo_identification import TWaveExcitation

    base = max(v_min, 0.0)
    total = v_max - base
    low, high = (
        pair(args.voltage, "--voltage", float) if args.voltage else (base, base + 0.75 * total)
    )
    q = args.offset if args.offset is not None else 0.25 * total
    settle, record = pair(args.periods, "--periods", int)
    if quick_run() and settle > QUICK_SETTLE_PERIODS:
        say_quick("identify", f"{QUICK_SETTLE_PERIODS} settling periods instead of {settle}")
        settle = QUICK_SETTLE_PERIODS
    excitation = TWaveExcitation(low, high, q, args.period, settle, record, args.record_rate)
    try:
        excitation.check(v_min, v_max)
    except ValueError as exc:
        raise DeviceRunError(str(exc)) from None
    return excitation


def open_controller(
    url: str, axis: str | None
) -> tuple[GCSAmplifier, DeviceInfo, ServoRecorder, int]:
    """(amplifier opened with its servo off, its DeviceInfo, a ServoRecorder on its link, the
    wave generator of the axis): axis i of ``SAI?`` drives output channel i and is driven by
    generator i. :class:`DeviceRunError` when the link or the axis is refused."""
    from piezo_stage.hardware.amplifier import GCSAmplifier
    from piezo_stage.hardware.errors import HardwareError
    from piezo_stage.hardware.pi_recorder import ServoRecorder
    from piezo_stage.hardware.transport import make_transport

    try:
        amplifier = GCSAmplifier(make_transport(url), axis=axis)
    except HardwareError as exc:
        raise DeviceRunError(f"{url}: {exc}") from None
    try:
        info = amplifier.open()
        axes = [a.strip() for a in amplifier.conn.query("SAI?") if a.strip()]
    except HardwareError as exc:
        amplifier.close()
        raise DeviceRunError(f"{url}: {exc}") from None
    generator = axes.index(amplifier.axis) + 1
    amplifier.channel = generator
    return amplifier, info, ServoRecorder(amplifier.conn), generator


@contextmanager
def open_axes(
    url: str, names: Sequence[str | None]
) -> Iterator[tuple[list[tuple[GCSAmplifier, int]], DeviceInfo, ServoRecorder]]:
    """The controller at ``url`` opened for axes ``names`` (None: its first), servo off, closed
    after: ((amplifier, wave generator) per axis, the first's DeviceInfo, a ServoRecorder on
    the link). The other axes are siblings on the same link; :class:`DeviceRunError` when the
    link or an axis is refused, before anything moves."""
    from piezo_stage.hardware.errors import HardwareError

    amplifier, info, recorder, generator = open_controller(url, names[0])
    try:
        axes = [(amplifier, generator)]
        for name in names[1:]:
            try:
                other = amplifier.sibling(str(name))
            except HardwareError as exc:
                raise DeviceRunError(f"{url}: {exc}") from None
            axes.append((other, other.channel))
        yield axes, info, recorder
    finally:
        amplifier.close()


def warn_at_limits(
    counts: dict[str, int], points: dict[str, int], limits: tuple[float, float], asks: str
) -> None:
    """Say, per axis, how many of its table's points sit at the amplifier's limits: the error
    there is the amplifier's, not the table's, and is not learned (``asks``: what to change)."""
    for name, count in counts.items():
        if count:
            print(
                f"warning: axis {name}: {count} of the table's {points[name]} points at the "
                f"amplifier's limits ({limits[0]:g}..{limits[1]:g} V): {asks}",
                file=sys.stderr,
            )


def identify_on_device(
    args: argparse.Namespace, options: IdentifyOptions, fit: FitOptions
) -> tuple[IdentificationResult, list[Recording]]:
    """Record the T-wave pair on ``args.device`` / ``args.axis``, write ``args.bag`` if given,
    identify the runs as a bag of them is identified; the output is left at max(VMI?, 0 V)."""
    from piezo_stage.experiments.errors import ExperimentError
    from piezo_stage.experiments.servo_identification import (
        record_t_waves,
        safe_state,
        write_bag,
    )
    from piezo_stage.hardware.errors import HardwareError

    def say(text: str) -> None:
        print(f"piezo-stage identify: {text}", file=sys.stderr, flush=True)

    amplifier, info, recorder, generator = open_controller(args.device, args.axis)
    try:
        excitation = excitation_from(args, info.v_min, info.v_max)
        say(
            f"{info.identity.split(',')[1].strip() if ',' in info.identity else info.identity}"
            f" axis {amplifier.axis}: T-waves {excitation.low:g}..{excitation.high:g} V and "
            f"+{excitation.q:g} V, {excitation.periods} periods of {excitation.period:g} s each"
        )
        record = record_t_waves(
            amplifier, recorder, excitation, generator, (info.v_min, info.v_max), say
        )
        safe_state(amplifier, recorder, generator, info.v_min)
        say(
            f"recorded {record.t.size} points at {1e-3 / (record.cycle * excitation.rate):g} kHz"
            f" in {len(record.segments)} part(s)"
        )
    except (HardwareError, ExperimentError) as exc:
        safe_state(amplifier, recorder, generator, info.v_min)
        raise DeviceRunError(f"{args.device}: {exc}") from None
    finally:
        amplifier.close()
    if args.bag:
        say(f"wrote {write_bag(record, args.bag)}")
    runs = record.recordings(f"{args.device} axis {amplifier.axis}", args.model_input)
    if args.steady_periods is None:  # the recorded periods, after the settling ones
        cycle = replace(options.cycle, steady_periods=excitation.record_periods)
        options = replace(options, cycle=cycle)
    if args.model_input == "displacement":
        options = replace(options, input_name="displacement", output_name="voltage")
        if options.lag_samples is None:
            options = replace(options, lag_samples=MIDPOINT_LAG)
    return identify_runs(runs, options, Method(args.method), fit), runs
