"""A whole rig on emulators: the amplifier and the sensor of a stage of one axis
(:class:`~.scanner.ScannerEmulator` with one axis; ``emulate rig``).

Any object with ``step(command_voltage, dt) -> (applied_voltage, reading, status)`` serves as
the stage (``piezo_stage.model.stage.SimulatedStage``), and with ``step_many`` it is stepped in
batches through an amplifier's low-pass. The sensor streams ``standoff + reading``, the stage
stepped once per sample with the voltage the amplifier applied at that sample's instant.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from ..optoncdt import FrameFormat
from .optoncdt_device import OptoNCDTDeviceModel
from .scanner import ScannerEmulator
from .server import EmulatorServer

__all__ = ["OneAxis", "RigEmulator", "Stage"]

#: (applied, readings, status) per axis: what the scanner's coupled axes return
Sample = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]


class Stage(Protocol):
    """What the rig steps (see the module docstring), e.g. ``SimulatedStage``."""

    def step(self, command_voltage: float, dt: float) -> tuple[float, float, int]:
        """Apply ``command_voltage`` over ``dt`` [s]; returns (applied, reading, status)."""


class OneAxis:
    """A single-axis :class:`Stage` as the scanner's coupled axes: axis 0 is ``stage``."""

    def __init__(self, stage: Stage) -> None:
        self.stage = stage
        self.axes = (stage,)  # its parameter set sets the substeps under a low-pass

    def step(self, commands: Any, dt: float) -> Sample:
        """Hold ``commands[0]`` for ``dt``; (applied, reading, status) as arrays of one."""
        applied, reading, status = self.stage.step(float(commands[0]), dt)
        return np.array([applied]), np.array([reading]), np.array([status], dtype=np.int64)

    def step_voltages(self, voltages: NDArray[np.float64], h: float, every: int) -> Sample:
        """Hold ``voltages[0, k]`` for ``h`` each; a sample after every ``every`` steps."""
        step_many = getattr(self.stage, "step_many", None)
        if step_many is not None:
            rows: NDArray[np.float64] = step_many(voltages[0], h, every)
        else:
            steps = [self.stage.step(float(v), h) for v in voltages[0]]
            rows = np.array(steps[every - 1 :: every], dtype=np.float64).reshape(-1, 3)
        return rows[:, :1], rows[:, 1:2], rows[:, 2:3].astype(np.int64)


class RigEmulator(ScannerEmulator):
    """The amplifier (GCS on TCP or pty, or MDT694B on pty) and one optoNCDT sensor (pty)
    around ``stage``; options as :class:`~.scanner.ScannerEmulator`'s.
    """

    def __init__(
        self, stage: Stage, sensor_format: FrameFormat, measuring_range: float, **options: Any
    ) -> None:
        super().__init__(OneAxis(stage), ("x",), None, sensor_format, measuring_range, **options)

    @property
    def sensor(self) -> OptoNCDTDeviceModel:
        """The sensor's device model."""
        return self.sensors[0]

    @property
    def sensor_server(self) -> EmulatorServer:
        """The sensor's server."""
        return self.sensor_servers[0]

    @property
    def servers(self) -> dict[str, EmulatorServer]:
        """The two servers by device name (the amplifier's, ``optoncdt``)."""
        return {self.amplifier.name: self.amplifier_server, "optoncdt": self.sensor_server}
