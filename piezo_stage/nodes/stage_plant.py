"""`stage_plant` node: a simulated stage of several axes, a drop-in for ``stage_driver`` and one
``laser_reader`` per axis.

The axes, their models and the coupling come from a stage file
(:mod:`piezo_stage.model.stage_file`); the mathematics is
:class:`piezo_stage.model.stage.CoupledStage`. Per axis, in the axis's namespace: subscribes
``<axis>/voltage_command``, publishes ``<axis>/voltage`` (what its amplifier applied at the
sample) and ``<axis>/displacement`` (its sensor, which sees the coupled displacements); one
tick steps every axis together, and a tick's messages carry one stamp. Clocks
(``clock_mode``), as the ``plant`` node's: ``realtime``, a wall timer at ``rate_hz`` whose
samples fall on the grid t0 + k/rate_hz (a late tick publishes every sample due since the last);
``lockstep``, the node owns ``/clock`` and steps once every axis's commander has answered the
step (:mod:`piezo_stage.nodes.lockstep`): deterministic, as fast as the graph can go.

Each amplifier is a Butterworth low-pass (``amplifier_bandwidth_hz``, order
``amplifier_filter_order``) stepped finely between samples, as ``emulate rig``'s: a staircase
at the sample rate straight into a lightly damped stage rings its resonance at every step and
wears the hysteresis down. A NaN or infinite command is refused (that axis holds).
"""

from __future__ import annotations

import functools
import math
import sys

import numpy as np
from builtin_interfaces.msg import Time
from numpy.typing import NDArray

from piezo_stage.config_path import ConfigNotFoundError, find_user_file
from piezo_stage.hardware.emulators.rig import AmplifierLowPass, substeps_for
from piezo_stage.model.errors import ModelError
from piezo_stage.model.stage import AmplifierModel, AxesSample, CoupledStage
from piezo_stage.model.stage_file import load_stage
from piezo_stage.model.tick_grid import TickGrid
from piezo_stage_msgs.msg import Displacement, Voltage

from .base import PiezoNode
from .choices import ClockMode
from .diagnostics import OK, WARN, Diagnosis, Diagnostics
from .errors import RosParameterError
from .lockstep import LockstepClock
from .plant import PARAMETERS as PLANT_PARAMETERS
from .plant import REALTIME_CATCH_UP
from .qos import COMMAND_QOS, LOCKSTEP_QOS, SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run
from .settings import StagePlantSettings
from .spec import Param, ParameterTable

PARAMETERS = ParameterTable(
    "stage_plant",
    (
        Param(
            "stage_file",
            "xy_scanner.yaml",
            "stage file (name in config/ or path): the axes, their models and the coupling",
            read_only=True,
        ),
        PLANT_PARAMETERS["rate_hz"],
        PLANT_PARAMETERS["clock_mode"],
        PLANT_PARAMETERS["lockstep_timeout"],
        PLANT_PARAMETERS["wait_for_commander"],
        PLANT_PARAMETERS["wait_for_subscribers"],
        PLANT_PARAMETERS["start_time"],
        PLANT_PARAMETERS["initial_voltage"],
        PLANT_PARAMETERS["v_min"],
        PLANT_PARAMETERS["v_max"],
        Param(
            "amplifier_bandwidth_hz",
            500.0,
            "every axis's amplifier: Butterworth low-pass corner (0: ideal, the staircase "
            "reaches the stage)",
            "Hz",
            (0.0, 1e6),
            read_only=True,
        ),
        Param(
            "amplifier_filter_order",
            2,
            "order of that low-pass",
            range=(1, 2),
            read_only=True,
        ),
    ),
    summary="Simulated stage of several axes (a stage file), coupled: per axis the real "
    "stage's topics in <axis>/ (realtime or lockstep).",
    settings_type=StagePlantSettings,
)


class StagePlantNode(PiezoNode):
    def __init__(self) -> None:
        super().__init__("stage_plant", namespace=DEFAULT_NAMESPACE)
        s: StagePlantSettings = self.declare_settings(PARAMETERS)
        try:
            self.stage_file = find_user_file(s.stage_file)
            stage = load_stage(self.stage_file)
        except (ConfigNotFoundError, ModelError) as exc:
            raise RosParameterError(f"parameter 'stage_file': {exc}") from None
        self.names = stage.names
        n = len(self.names)
        self.sim = CoupledStage(
            stage,
            amplifiers=[AmplifierModel(v_min=s.v_min, v_max=s.v_max) for _ in range(n)],
        )
        self.dt = 1.0 / s.rate_hz
        self._commands = np.full(n, float(s.initial_voltage))
        self.substeps = 1
        self.lowpass: list[AmplifierLowPass] = []
        if s.amplifier_bandwidth_hz > 0.0:
            self.substeps = max(
                substeps_for(axis, s.rate_hz, s.amplifier_bandwidth_hz) for axis in self.sim.axes
            )
            h = self.dt / self.substeps
            self.lowpass = [
                AmplifierLowPass(s.amplifier_bandwidth_hz, s.amplifier_filter_order, h, v)
                for v in self._commands
            ]
        for axis, v in zip(self.sim.axes, self._commands):
            axis.amplifier.voltage = float(min(max(v, s.v_min), s.v_max))
        self._rejected = [0] * n
        self._received = [0] * n
        lockstep = ClockMode(s.clock_mode) is ClockMode.LOCKSTEP
        stream_qos = LOCKSTEP_QOS if lockstep else SENSOR_QOS
        self._pub_x, self._pub_v, commands = [], [], []
        for i, name in enumerate(self.names):
            self._pub_x.append(
                self.create_publisher(Displacement, f"{name}/displacement", stream_qos)
            )
            self._pub_v.append(self.create_publisher(Voltage, f"{name}/voltage", stream_qos))
            sub = self.create_subscription(
                Voltage,
                f"{name}/voltage_command",
                functools.partial(self._on_command, i),
                LOCKSTEP_QOS if lockstep else COMMAND_QOS,
            )
            commands.append(sub.topic_name)
        self._msg_x, self._msg_v = Displacement(), Voltage()
        self._dt_ns = int(round(self.dt * 1e9))
        self._grid = TickGrid(self._dt_ns, max(10, int(REALTIME_CATCH_UP * s.rate_hz)))
        self._lockstep: LockstepClock | None = None
        self._last = self.sim.output()  # what the sensors read now, per axis
        Diagnostics(self, "simulation", self._diagnose)
        if lockstep:
            self._lockstep = LockstepClock(
                self,
                dt_ns=self._dt_ns,
                start_ns=int(round(s.start_time * 1e9)),
                timeout=float(s.lockstep_timeout),
                command_topics=commands,
                sample_topics=[p.topic_name for p in self._pub_x],
                samples=(*self._pub_x, *self._pub_v),
                emit=lambda stamp: self._publish(stamp, *self._last),
                advance=self._advance,
            )
        else:
            self.create_timer(self.dt, self._tick)
        self.get_logger().info(
            f"stage {stage.name} ({', '.join(self.names)}) at {s.rate_hz:g} Hz, amplifiers "
            f"{s.amplifier_bandwidth_hz:g} Hz ({self.substeps} steps per sample), clock "
            f"{s.clock_mode}"
        )

    def _on_command(self, i: int, msg: Voltage) -> None:
        if not math.isfinite(msg.voltage):
            self._rejected[i] += 1
            self.get_logger().warn(
                f"rejected non-finite voltage command {msg.voltage} on axis {self.names[i]}: "
                f"holding {self._commands[i]:g} V",
                throttle_duration_sec=1.0,
            )
        else:
            self._commands[i] = msg.voltage
            self._received[i] += 1
        if self._lockstep is not None:  # a non-finite command answers the step too: no timeout
            self._lockstep.answered(i, msg.header.stamp)

    def _step(self, samples: int) -> AxesSample:
        """``samples`` samples (a late tick's backlog in one call), the commands held: every
        axis through its amplifier, then the coupled sensors; arrays (samples, axes)."""
        if not self.lowpass:
            rows = [self.sim.step(self._commands.tolist(), self.dt) for _ in range(samples)]
            return AxesSample(*(np.array([r[k] for r in rows]) for k in range(3)))
        n = samples * self.substeps
        volts = np.empty((len(self.names), n))
        for i, lowpass in enumerate(self.lowpass):
            volts[i] = lowpass.run(np.full(n, self._commands[i]))
        return self.sim.step_voltages(volts, self.dt / self.substeps, self.substeps)

    def _advance(self) -> None:
        """lockstep: one step with the commands held."""
        applied, readings, status = self._step(1)
        self._last = AxesSample(applied[0], readings[0], status[0])

    def _tick(self) -> None:
        due = self._grid.due(self.get_clock().now().nanoseconds)
        if not due:
            return
        applied, readings, status = self._step(len(due))
        for k, ns in enumerate(due):
            sec, nanosec = divmod(ns, 1_000_000_000)
            self._publish(Time(sec=sec, nanosec=nanosec), applied[k], readings[k], status[k])

    def _publish(
        self,
        stamp: Time,
        applied: NDArray[np.float64],
        readings: NDArray[np.float64],
        status: NDArray[np.int64],
    ) -> None:
        """Every axis's sample at ``stamp``: one message of each kind, refilled (publish()
        serializes before it returns)."""
        msg_x, msg_v = self._msg_x, self._msg_v
        msg_x.header.stamp = msg_v.header.stamp = stamp
        for i in range(len(self.names)):
            ok = int(status[i]) == Displacement.OK
            msg_x.displacement = float(readings[i]) if ok else math.nan
            msg_x.status = int(status[i])
            msg_v.voltage = float(applied[i])
            self._pub_x[i].publish(msg_x)
            self._pub_v[i].publish(msg_v)

    def _diagnose(self) -> Diagnosis:
        dropped = self._grid.dropped
        late = self._lockstep.late if self._lockstep is not None else 0
        values: dict[str, object] = {
            "stage_file": str(self.stage_file),
            "axes": ",".join(self.names),
            "dropped_samples": dropped,
            "late_steps": late,
            "substeps": self.substeps,
        }
        for name, received, rejected in zip(self.names, self._received, self._rejected):
            values[f"{name}.commands"] = received
            values[f"{name}.rejected_commands"] = rejected
        rejected_all = sum(self._rejected)
        if dropped or rejected_all or late:
            return Diagnosis(
                WARN,
                f"{late} late step(s), {rejected_all} rejected command(s), "
                f"{dropped} dropped sample(s)",
                values,
            )
        return Diagnosis(OK, f"simulating {len(self.names)} axes", values)


def main(args: list[str] | None = None) -> int:
    return run(StagePlantNode, args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
