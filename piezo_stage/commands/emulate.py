"""Run device emulators on ptys/TCP: gcs, e727, e709 (PI), mdt69x, optoncdt, rig, scanner.

gcs: a PI E-709-class (one axis) or E-727-class (--axes) GCS controller; e727 / e709: a PI
controller on a simulated stage with its servo clock, wave generator and data recorder;
mdt69x: a Thorlabs MDT694B/MDT693B amplifier; optoncdt: a Micro-Epsilon optoNCDT sensor; rig:
an amplifier and a sensor bound to one simulated stage; scanner: a multi-axis amplifier and a
sensor per axis bound to a stage file's coupled stage.

Each endpoint is printed as one line, e.g. ``gcs: /dev/pts/7`` or ``gcs: tcp://127.0.0.1:50000``,
so a launcher or a user can connect the voltage_driver / laser_reader nodes to it; ``--link`` /
``--sensor-link`` / ``--amp-link`` give a pty a fixed path (a symlink, removed on exit;
``run:NAME`` puts it in the per-user run-time folder, where the reader's ``url: run:NAME`` finds
it). Runs until Ctrl-C / SIGTERM (or --duration). Like a real device, it does not vanish under
a driver that is still ramping its output to a safe voltage: on the first signal it
keeps serving until its TCP clients have hung up, at most --linger seconds, then its ptys one
second more (a pty cannot tell whether its client is gone: a reader signalled with it stops
first); a second signal stops it at once.
Fault switches rehearse a bad link: --drop/--corrupt (per output byte), --garbage (random bursts),
--hangup (a reply cut and the line dropped), --stall/--stall-time (the device stops), --slow
(reply delay), --disconnect-every (hang up and come back), --error-values (sensor).
--log FILE (amplifiers, rig and scanner) writes a CSV row (time, axis, volts) per applied
voltage, the axis named as on the device (the stage file's channel).
`scanner` binds a multi-axis amplifier and one sensor per axis to the coupled stage of a stage
file; it prints the amplifier's endpoint, one ``optoncdt <axis>: <path>`` line per sensor, and
last ``scanner: N axes (x, y) at RATE Hz``.

  piezo-stage emulate gcs --tcp 50000
  piezo-stage emulate gcs --axes 1,2,3 --tcp 50000 --log applied.csv   # an E-727-class controller
  piezo-stage emulate e727 --tcp 50000 --stage xyz_scanner.yaml   # E-727 on its servo clock
  piezo-stage emulate mdt69x
  piezo-stage emulate optoncdt --family ild1320 --rate 2000
  piezo-stage emulate rig --params ch10_patch.yaml --amp-tcp 50000 --sensor-link run:rig_sensor
  piezo-stage emulate scanner --stage xy_scanner.yaml --amp-tcp 50000 \
      --sensor-link run:scanner_sensor_{axis}

A TCP port already in use is one line and exit 2 (choose another --tcp / --amp-tcp, or 0 for
any free one).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from typing import TYPE_CHECKING, Any, Callable

from piezo_stage.commands.argtypes import (
    int_range,
    non_negative,
    output,
    port,
    positive,
    probability,
)
from piezo_stage.hardware.emulators import (
    EmulatorServer,
    Faults,
    GCSDeviceModel,
    MDTDeviceModel,
    OptoNCDTDeviceModel,
)
from piezo_stage.hardware.emulators.amplifier_options import add_amplifier_options
from piezo_stage.hardware.emulators.scanner import ScannerEmulator
from piezo_stage.hardware.emulators.voltage_log import VoltageLog
from piezo_stage.hardware.optoncdt import FAMILIES, FrameFormat, frame_format
from piezo_stage.stopping import StopFlag

if TYPE_CHECKING:
    from piezo_stage.model.stage import SimulatedStage

AxisVoltageCallback = Callable[[str, float, "float | None"], None]

SENSOR_FAMILIES = sorted(FAMILIES)
PTY_GRACE = 1.0  # s a signalled emulator still serves its ptys (within --linger)


def _faults(parser: argparse.ArgumentParser, link: bool = True) -> None:
    g = parser.add_argument_group("fault injection")
    g.add_argument(
        "--drop",
        type=probability,
        default=0.0,
        metavar="P",
        help="probability an output byte is lost",
    )
    g.add_argument(
        "--corrupt",
        type=probability,
        default=0.0,
        metavar="P",
        help="probability an output byte is replaced by a random byte",
    )
    g.add_argument(
        "--garbage",
        type=probability,
        default=0.0,
        metavar="P",
        help="probability an output chunk is preceded by 1-32 random bytes",
    )
    g.add_argument(
        "--hangup",
        type=probability,
        default=0.0,
        metavar="P",
        help="probability an output chunk is cut in the middle and the link hung up",
    )
    g.add_argument(
        "--stall",
        type=probability,
        default=0.0,
        metavar="P",
        help="probability the device stalls (no output, input ignored) before a chunk",
    )
    g.add_argument(
        "--stall-time", type=non_negative, default=0.5, metavar="SECONDS", help="length of a stall"
    )
    g.add_argument(
        "--slow", type=non_negative, default=0.0, metavar="SECONDS", help="delay every reply"
    )
    g.add_argument(
        "--disconnect-every",
        type=non_negative,
        default=0.0,
        metavar="SECONDS",
        help="hang up all clients periodically (pty: a new pty, path printed again)",
    )
    g.add_argument("--seed", type=int, default=None, help="seed of the fault generator")
    if link:
        parser.add_argument(
            "--link",
            default=None,
            metavar="PATH",
            help="stable symlink to the pty (kept across --disconnect-every)",
        )
    parser.add_argument(
        "--duration",
        type=non_negative,
        default=0.0,
        metavar="SECONDS",
        help="stop after this long (0: run until Ctrl-C)",
    )
    parser.add_argument(
        "--realtime",
        type=int_range(0, 99),
        default=0,
        metavar="PRIORITY",
        help="run the device threads under SCHED_FIFO at this priority (1-99) when the "
        "system allows it, so a loaded host does not delay the device (0: normal)",
    )
    parser.add_argument(
        "--linger",
        type=non_negative,
        default=3.0,
        metavar="SECONDS",
        help="on Ctrl-C/SIGTERM keep serving while TCP clients are connected, at most "
        "this long (a driver ramping to its safe voltage); 0: stop at once",
    )


def _sensor_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--family", choices=SENSOR_FAMILIES, default="ild1320")
    parser.add_argument(
        "--bits",
        type=int,
        choices=(14, 16, 18),
        default=None,
        help="output word width (ILD1320 family: 16 or 18; default per family)",
    )
    parser.add_argument(
        "--rate", type=positive, default=1000.0, metavar="HZ", help="measuring rate"
    )
    parser.add_argument(
        "--measuring-range",
        type=positive,
        default=10e-3,
        metavar="M",
        help="measuring range MR [m]",
    )
    parser.add_argument(
        "--error-values",
        type=probability,
        default=0.0,
        metavar="P",
        help="probability a sample is replaced by an error value",
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="device", required=True, metavar="DEVICE")
    gcs = sub.add_parser("gcs", help="PI E-709-class (one axis) or E-727-class (--axes) controller")
    where = gcs.add_mutually_exclusive_group()
    where.add_argument(
        "--tcp", type=port, default=None, metavar="PORT", help="serve on 127.0.0.1:PORT (0: any)"
    )
    where.add_argument("--pty", action="store_true", help="serve on a pty (default)")
    gcs.add_argument("--axis", default="1", help="axis identifier reported by SAI?")
    gcs.add_argument(
        "--axes",
        type=axis_names,
        default=None,
        metavar="A,B,...",
        help="several axes (E-727 class: 1,2,3), axis i driving output channel i",
    )
    gcs.add_argument("--v-min", type=float, default=-30.0, help="VMI? [V]")
    gcs.add_argument("--v-max", type=float, default=130.0, help="VMA? [V]")
    gcs.add_argument(
        "--servo-off", action="store_true", help="start with the servo off (default: on)"
    )
    gcs.add_argument(
        "--accept-sva-with-servo-on",
        action="store_true",
        help="do not refuse SVA while the servo is on (the real controller refuses, error 79)",
    )
    _log_arg(gcs)
    _faults(gcs)

    for controller, axes in (("e727", "three"), ("e709", "one")):
        _controller_args(
            sub.add_parser(
                controller,
                help=f"PI {controller.upper()}-class controller on a {axes}-axis simulated stage, "
                "with its servo clock, wave generator and data recorder",
            )
        )

    mdt = sub.add_parser("mdt69x", help="Thorlabs MDT694B/MDT693B on a pty")
    mdt.add_argument("--model", choices=("MDT694B", "MDT693B"), default="MDT694B")
    mdt.add_argument("--vlimit", type=float, choices=(75.0, 100.0, 150.0), default=150.0)
    mdt.add_argument("--no-echo", action="store_true", help="start with command echo off")
    _log_arg(mdt)
    _faults(mdt)

    sensor = sub.add_parser("optoncdt", help="Micro-Epsilon optoNCDT sensor on a pty")
    _sensor_args(sensor)
    _faults(sensor)

    rig = sub.add_parser("rig", help="amplifier + sensor bound to one simulated stage")
    rig.add_argument(
        "--params",
        default="ch11_rig.yaml",
        help="parameter-set YAML of the simulated stage (a path, or a name in config/, "
        "e.g. ch10_patch.yaml; default ch11_rig.yaml, the ch. 11 rig)",
    )
    _amplifier_args(rig, "E-709")
    rig.add_argument(
        "--sensor-link",
        default=None,
        metavar="PATH",
        help="fixed path (symlink) of the sensor's pty, for the laser_reader's url",
    )
    _sensor_args(rig)
    _log_arg(rig)
    _faults(rig, link=False)

    scanner = sub.add_parser(
        "scanner", help="amplifier + one sensor per axis bound to one simulated coupled stage"
    )
    scanner.add_argument(
        "--stage",
        required=True,
        metavar="FILE",
        help="stage file of the simulated stage (a path, or a name in config/, e.g. "
        "xy_scanner.yaml); each axis is driven on its channel",
    )
    _amplifier_args(scanner, "E-727")
    scanner.add_argument(
        "--sensor-link",
        default=None,
        metavar="PATTERN",
        help="fixed path (symlink) of each axis's sensor pty, {axis} replaced by the axis name, "
        "e.g. run:scanner_sensor_{axis}",
    )
    _sensor_args(scanner)
    _log_arg(scanner)
    _faults(scanner, link=False)


def _controller_args(parser: argparse.ArgumentParser) -> None:
    """The options of ``e727`` / ``e709``."""
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--tcp", type=port, default=None, metavar="PORT", help="serve on 127.0.0.1:PORT (0: any)"
    )
    where.add_argument("--pty", action="store_true", help="serve on a pty (default)")
    parser.add_argument(
        "--stage",
        default=None,
        metavar="FILE",
        help="stage file of the simulated stage, its channels the axes (e709: its first axis; "
        "default: ch11_rig.yaml on axes 1, 2, 3)",
    )
    parser.add_argument("--v-min", type=float, default=-30.0, help="VMI? [V]")
    parser.add_argument("--v-max", type=float, default=130.0, help="VMA? [V]")
    parser.add_argument("--servo-on", action="store_true", help="start with the servo on")
    parser.add_argument(
        "--sensor-noise",
        type=non_negative,
        default=2e-9,
        metavar="M",
        help="standard deviation of the position sensors' noise [m] (default 2e-9)",
    )
    _log_arg(parser)
    _faults(parser)


def _controller(args: argparse.Namespace) -> Any:
    """``emulate e727`` / ``e709``: the controller model bound to its simulated stage."""
    from piezo_stage.config_path import find_user_file
    from piezo_stage.model.stage_file import load_stage as load_stage_file

    return emulated_controller(
        None if args.stage is None else load_stage_file(find_user_file(args.stage)),
        one_axis=args.device == "e709",
        v_min=args.v_min,
        v_max=args.v_max,
        sensor_noise=args.sensor_noise,
        servo_on=args.servo_on,
    )


def emulated_controller(
    stage: Any = None,
    *,
    one_axis: bool = False,
    v_min: float = -30.0,
    v_max: float = 130.0,
    sensor_noise: float = 2e-9,
    seed: int = 0,
    servo_on: bool = False,
) -> Any:
    """An E-727 (``one_axis``: E-709, the stage's first axis) bound to a simulated stage: a
    :class:`~piezo_stage.model.stage_file.Stage` (its channels the axes) or, by default, the
    shipped ch. 11 rig on axes 1, 2, 3, uncoupled. Axis i's sensor noise is seeded
    ``seed + i``.
    """
    import numpy as np

    from piezo_stage.hardware.emulators.pi_controller import PIControllerModel
    from piezo_stage.model.parameter_set import shipped_parameter_set
    from piezo_stage.model.stage import AmplifierModel, CoupledStage, SensorModel
    from piezo_stage.model.stage_file import Stage, StageAxis, single_axis_stage

    if stage is None:
        model = shipped_parameter_set("ch11_rig")
        axes = tuple(StageAxis(name, model, str(i + 1)) for i, name in enumerate("xyz"))
        stage = Stage("e727", axes, np.eye(3))
    if one_axis:
        first = stage.axes[0]
        stage = single_axis_stage(first.model, first.name, first.channel)
    n = len(stage.axes)

    def build() -> CoupledStage:
        return CoupledStage(
            stage,
            [AmplifierModel(v_min, v_max) for _ in range(n)],
            [SensorModel(noise_std=sensor_noise, seed=seed + i) for i in range(n)],
        )

    return PIControllerModel(
        build, [axis.channel for axis in stage.axes], v_min=v_min, v_max=v_max, servo_on=servo_on
    )


def _amplifier_args(parser: argparse.ArgumentParser, controller: str) -> None:
    """The amplifier options of ``rig`` and ``scanner``."""
    add_amplifier_options(parser, controller)
    parser.add_argument(
        "--amp-tcp",
        type=port,
        default=None,
        metavar="PORT",
        help="serve the GCS amplifier on TCP instead of a pty",
    )
    parser.add_argument(
        "--amp-link",
        default=None,
        metavar="PATH",
        help="fixed path (symlink) of the amplifier's pty (without --amp-tcp)",
    )
    parser.add_argument(
        "--amp-bandwidth",
        type=non_negative,
        default=1000.0,
        metavar="HZ",
        help="amplifier small-signal bandwidth: a Butterworth low-pass from command to "
        "stage (default 1000; 0: ideal, every 1/rate step reaches the stage)",
    )
    parser.add_argument(
        "--amp-filter-order",
        type=int,
        choices=(1, 2),
        default=2,
        help="order of that low-pass (default 2)",
    )
    parser.add_argument(
        "--standoff",
        type=float,
        default=None,
        metavar="M",
        help="sensor reading at zero displacement [m] (default: MR/2)",
    )


def _log_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--log",
        default=None,
        metavar="FILE",
        action=output("file"),
        help="write a CSV row (time, axis, volts) per applied voltage: what the amplifier saw",
    )


def axis_names(text: str) -> tuple[str, ...]:
    """``1,2,3`` -> ("1", "2", "3"): distinct alphanumeric names."""
    names = tuple(part.strip() for part in text.split(","))
    if not all(n.isalnum() for n in names) or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(
            f"expected distinct alphanumeric axis names separated by commas, got {text!r}"
        )
    return names


def _make_faults(args: argparse.Namespace) -> Faults:
    return Faults(
        drop=args.drop,
        corrupt=args.corrupt,
        garbage=args.garbage,
        hangup=args.hangup,
        stall=args.stall,
        stall_time=args.stall_time,
        reply_delay=args.slow,
        seed=args.seed,
    )


def _servers(args: argparse.Namespace) -> dict[str, EmulatorServer]:
    faults = _make_faults(args)
    rt = args.realtime
    if args.device == "gcs":
        model = GCSDeviceModel(
            axis=args.axis,
            axes=args.axes,
            v_min=args.v_min,
            v_max=args.v_max,
            servo_on=not args.servo_off,
            refuse_sva_when_servo_on=not args.accept_sva_with_servo_on,
        )
        endpoint = (
            {"tcp_port": args.tcp} if args.tcp is not None else {"pty": True, "pty_link": args.link}
        )
        return {"gcs": EmulatorServer(model, faults=faults, realtime_priority=rt, **endpoint)}
    if args.device in ("e727", "e709"):
        endpoint = (
            {"tcp_port": args.tcp} if args.tcp is not None else {"pty": True, "pty_link": args.link}
        )
        server = EmulatorServer(_controller(args), faults=faults, realtime_priority=rt, **endpoint)
        return {args.device: server}
    if args.device == "mdt69x":
        amplifier = MDTDeviceModel(args.model, args.vlimit, echo=not args.no_echo)
        return {
            "mdt69x": EmulatorServer(
                amplifier, pty=True, pty_link=args.link, faults=faults, realtime_priority=rt
            )
        }
    fmt = frame_format(args.family, args.bits)
    if args.device == "optoncdt":
        sensor = OptoNCDTDeviceModel(
            fmt,
            args.measuring_range,
            args.rate,
            error_probability=args.error_values,
            seed=args.seed,
        )
        return {
            "optoncdt": EmulatorServer(
                sensor, pty=True, pty_link=args.link, faults=faults, realtime_priority=rt
            )
        }
    if args.device == "scanner":
        return _scanner(args, fmt, faults).servers
    from piezo_stage.hardware.emulators.rig import RigEmulator

    rig = RigEmulator(
        load_stage(args.params),
        fmt,
        args.measuring_range,
        **_around_a_stage(args, faults),
    )
    return rig.servers


def _around_a_stage(args: argparse.Namespace, faults: Faults) -> dict[str, Any]:
    """The options ``emulate rig`` and ``emulate scanner`` share: the amplifier's endpoint,
    range, low-pass and faults, the sensors' rate, standoff, errors, faults and links."""
    return {
        "amplifier": args.amplifier,
        "amplifier_tcp_port": args.amp_tcp,
        "amplifier_link": args.amp_link,
        "amplifier_range": None if args.amp_range is None else tuple(args.amp_range),
        "rate": args.rate,
        "standoff": args.standoff,
        "sensor_errors": args.error_values,
        "amplifier_faults": faults,
        "sensor_faults": _make_faults(args),
        "seed": args.seed,
        "sensor_link": args.sensor_link,
        "realtime_priority": args.realtime,
        "amplifier_bandwidth": args.amp_bandwidth,
        "amplifier_filter_order": args.amp_filter_order,
    }


def _scanner(args: argparse.Namespace, fmt: FrameFormat, faults: Faults) -> ScannerEmulator:
    """``emulate scanner``: the stage file's coupled stage on the amplifier and its sensors."""
    from piezo_stage.config_path import find_user_file
    from piezo_stage.model.stage import CoupledStage
    from piezo_stage.model.stage_file import load_stage as load_stage_file

    stage = load_stage_file(find_user_file(args.stage))
    return ScannerEmulator(
        CoupledStage(stage),
        stage.names,
        [axis.channel for axis in stage.axes],
        fmt,
        args.measuring_range,
        **_around_a_stage(args, faults),
    )


def _ready_line(args: argparse.Namespace, servers: dict[str, EmulatorServer]) -> str | None:
    """The last line ``emulate scanner`` prints once every endpoint is up (launchers wait on
    ``^scanner: ``), None for the other devices.
    """
    if args.device != "scanner":
        return None
    axes = [name.split(" ", 1)[1] for name in servers if name.startswith("optoncdt ")]
    return f"scanner: {len(axes)} axes ({', '.join(axes)}) at {args.rate:g} Hz"


def load_stage(path: str) -> SimulatedStage:
    """The simulated stage of the parameter set at ``path`` (relative to the current folder),
    or of the shipped config so named."""
    from piezo_stage.config_path import find_user_file
    from piezo_stage.model.parameter_set import load_parameter_set
    from piezo_stage.model.stage import SimulatedStage

    return SimulatedStage(load_parameter_set(find_user_file(path)))


def _announce(servers: dict[str, EmulatorServer], note: str = "") -> None:
    for name, server in servers.items():
        print(f"{name}: {server.url}{note}", flush=True)


def run(args: argparse.Namespace) -> int:
    from piezo_stage.config_path import ConfigNotFoundError
    from piezo_stage.hardware.errors import HardwareError
    from piezo_stage.model.errors import ModelError

    try:
        servers = _servers(args)
    except KeyboardInterrupt:  # stopped while starting (a launch stopped early): nothing to stop
        return 130
    except (ConfigNotFoundError, ModelError, HardwareError) as exc:
        # --params missing or not a parameter set; a port another process listens on
        print(f"piezo-stage emulate: {exc}", file=sys.stderr)
        return 2
    try:
        log = _open_log(args, servers)
    except HardwareError as exc:
        print(f"piezo-stage emulate: {exc}", file=sys.stderr)
        return 2
    stop = StopFlag()
    if threading.current_thread() is threading.main_thread():
        _catch_signals(stop)
    for server in servers.values():
        server.start()
    _announce(servers)
    if (ready := _ready_line(args, servers)) is not None:
        print(ready, flush=True)
    time.sleep(0.01)  # the server threads have set their priority
    _note_realtime(servers)
    t_end = time.monotonic() + args.duration if args.duration > 0 else float("inf")
    next_hangup = (
        time.monotonic() + args.disconnect_every if args.disconnect_every > 0 else float("inf")
    )
    try:
        if (failed := _serve(servers, stop, t_end, next_hangup, args.disconnect_every)) is not None:
            return failed
        if stop.is_set():  # a signal, not --duration: let connected drivers finish their ramp
            if (failed := _linger(servers, stop, args.linger)) is not None:
                return failed
    except KeyboardInterrupt:
        pass
    finally:
        for server in servers.values():
            server.stop()
        if log is not None:
            log.close()
        _say_outputs(servers)
    return 0


def _say_outputs(servers: dict[str, EmulatorServer]) -> None:
    """One line per amplifier: the output each axis was left at (and running wave generators),
    what a meter on the bench would read after the run."""
    for name, server in servers.items():
        model = server.model
        volts = getattr(model, "voltages", None) or getattr(model, "voltage", None)
        if not isinstance(volts, dict):
            continue
        text = ", ".join(f"{axis} {float(v):.3f} V" for axis, v in volts.items())
        running = [i + 1 for i, g in enumerate(getattr(model, "generators", ())) if g.mode]
        wave = f"; wave generators {running} running" if running else ""
        print(f"{name}: outputs at exit: {text}{wave}", flush=True)


def _open_log(args: argparse.Namespace, servers: dict[str, EmulatorServer]) -> VoltageLog | None:
    """``--log``: every amplifier model of ``servers`` reports each applied voltage to it."""
    if getattr(args, "log", None) is None:
        return None
    log = VoltageLog(args.log)
    for server in servers.values():
        model = server.model
        if isinstance(model, (GCSDeviceModel, MDTDeviceModel)):
            model.on_axis_voltage = _also(model.on_axis_voltage, log.record)
    return log


def _also(first: AxisVoltageCallback | None, then: AxisVoltageCallback) -> AxisVoltageCallback:
    """A callback calling ``first`` (a simulated stage's, when there is one), then ``then``."""
    if first is None:
        return then

    def both(axis: str, volts: float, at: float | None = None) -> None:
        first(axis, volts, at)
        then(axis, volts, at)

    return both


def _catch_signals(on_signal: Callable[..., None]) -> None:
    """Route SIGTERM and SIGINT (unless ignored) to ``on_signal``: a stop flag, not an error."""
    # both signals only count and set the flag: a Ctrl-C that comes while the endpoints are
    # being announced (or at any other point) still stops the servers cleanly, exit 0
    signal.signal(signal.SIGTERM, on_signal)
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:  # a launcher may have us ignore it
        signal.signal(signal.SIGINT, on_signal)


def _note_realtime(servers: dict[str, EmulatorServer]) -> None:
    """Print a note for each server that could not get its real-time priority."""
    for name, server in servers.items():
        if server.realtime_error:
            print(f"{name}: note: {server.realtime_error}", flush=True)


def _serve(
    servers: dict[str, EmulatorServer],
    stop: StopFlag,
    t_end: float,
    next_hangup: float,
    disconnect_every: float,
) -> int | None:
    """Serve until ``stop`` or ``t_end`` with periodic hang-ups; 1 if a server died, else None."""
    while not stop.is_set() and time.monotonic() < t_end:
        time.sleep(min(0.05, max(t_end - time.monotonic(), 0.0)))
        if time.monotonic() >= next_hangup:
            for server in servers.values():
                server.disconnect()
            time.sleep(0.05)  # let the server threads reopen their endpoints
            _announce(servers, " (reconnected)")
            next_hangup += disconnect_every
        if (failed := _failed(servers)) is not None:
            return failed
    return None


def _linger(servers: dict[str, EmulatorServer], stop: StopFlag, linger: float) -> int | None:
    """Serve on after a signal so drivers finish their ramp; 1 if a server died, else None."""
    linger_end = time.monotonic() + max(linger, 0.0)
    while (
        stop.signals < 2
        and time.monotonic() < linger_end
        and any(s.clients for s in servers.values())
    ):
        time.sleep(0.02)
        if (failed := _failed(servers)) is not None:
            return failed
    # a pty cannot tell whether its client is still there: serve it a little longer, so
    # that a reader signalled at the same time as this emulator stops first and does not
    # take the emulator's normal stop for a broken link
    grace_end = time.monotonic() + min(PTY_GRACE, max(linger, 0.0))
    if any(s.is_pty for s in servers.values()):
        while stop.signals < 2 and time.monotonic() < grace_end:
            time.sleep(0.02)
    return None


def _failed(servers: dict[str, EmulatorServer]) -> int | None:
    """1 (after saying so) when a server thread died, else None."""
    for name, server in servers.items():
        if server.error is not None:
            print(f"{name}: emulator failed: {server.error}", flush=True)
            return 1
    return None
