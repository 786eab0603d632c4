"""A whole rig on emulators: amplifier and sensor bound to one simulated stage.

The amplifier emulator's applied voltage drives the plant; the sensor emulator steps the plant
once per sample (dt = 1/rate, so the plant runs on the sensor's sample clock) and streams
``standoff + displacement`` (metres from the start of its measuring range). Any object with
``step(command_voltage, dt) -> (applied_voltage, displacement, status)`` serves as the stage
(``piezo_stage.model.plant.SimulatedStage``).
"""

from __future__ import annotations

import math
import threading
from typing import Protocol

import numpy as np

from ..errors import ConfigError
from ..optoncdt import FrameFormat
from .gcs_device import GCSDeviceModel
from .mdt_device import MDTDeviceModel
from .optoncdt_device import OptoNCDTDeviceModel
from .server import EmulatorServer, Faults


class Stage(Protocol):
    def step(self, command_voltage: float, dt: float) -> tuple[float, float, int]: ...


class RigCoupling:
    """The sensor's displacement source: steps the stage with the amplifier's applied voltage."""

    def __init__(self, stage: Stage, amplifier: GCSDeviceModel | MDTDeviceModel, rate: float,
                 standoff: float) -> None:
        self.stage = stage
        self.amplifier = amplifier
        self.dt = 1.0 / rate
        self.standoff = standoff
        self.lock = threading.Lock()
        self.applied = 0.0  # last voltage the plant received [V]
        self.displacement = 0.0  # last plant output [m]

    def __call__(self, times: np.ndarray) -> np.ndarray:
        out = np.empty(len(times))
        with self.lock:
            for k in range(len(times)):
                applied, y, status = self.stage.step(self.amplifier.applied_voltage, self.dt)
                self.applied, self.displacement = float(applied), float(y)
                out[k] = self.standoff + y if int(status) == 0 and math.isfinite(y) else math.nan
        return out


class RigEmulator:
    """Amplifier (GCS on TCP or pty, or MDT69x on pty) + optoNCDT sensor (pty) around one stage."""

    def __init__(self, stage: Stage, sensor_format: FrameFormat, measuring_range: float, *,
                 amplifier: str = "gcs", amplifier_tcp_port: int | None = None, rate: float = 1000.0,
                 standoff: float | None = None, sensor_errors: float = 0.0,
                 amplifier_faults: Faults | None = None, sensor_faults: Faults | None = None,
                 seed: int | None = None) -> None:
        if amplifier == "gcs":
            self.amplifier = GCSDeviceModel()
        elif amplifier == "mdt69x":
            if amplifier_tcp_port is not None:
                raise ConfigError("the MDT69x emulator serves a pty only")
            self.amplifier = MDTDeviceModel()
        else:
            raise ConfigError(f"amplifier must be 'gcs' or 'mdt69x', got {amplifier!r}")
        standoff = 0.5 * measuring_range if standoff is None else standoff
        self.coupling = RigCoupling(stage, self.amplifier, rate, standoff)
        self.sensor = OptoNCDTDeviceModel(sensor_format, measuring_range, rate, source=self.coupling,
                                          error_probability=sensor_errors, seed=seed)
        amp_endpoint = {"tcp_port": amplifier_tcp_port} if amplifier_tcp_port is not None else {"pty": True}
        self.amplifier_server = EmulatorServer(self.amplifier, faults=amplifier_faults, **amp_endpoint)
        self.sensor_server = EmulatorServer(self.sensor, pty=True, faults=sensor_faults)

    @property
    def servers(self) -> dict[str, EmulatorServer]:
        return {self.amplifier.name: self.amplifier_server, "optoncdt": self.sensor_server}

    def start(self) -> "RigEmulator":
        self.amplifier_server.start()
        self.sensor_server.start()
        return self

    def stop(self) -> None:
        self.sensor_server.stop()
        self.amplifier_server.stop()

    def __enter__(self) -> "RigEmulator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
