"""Device wire protocols (PI GCS2, Thorlabs MDT69x, Micro-Epsilon optoNCDT), emulators. No rclpy.

For the ROS nodes:

- voltage_driver: ``VoltageDriver(make_amplifier(kind, url), DriverConfig(...))`` with
  ``connect()``, ``set_voltage(v)`` (all safety checks inside), ``read_voltage()``,
  ``tick()`` from a timer (watchdog), ``shutdown()``; link loss is handled by reconnecting.
- laser_reader: ``SensorReader.from_url(url, SensorConfig(family, measuring_range))`` with
  ``connect()``, ``read()`` -> :class:`SampleBlock` (metres, :class:`Status`), ``stale``,
  ``reconnect()``, ``command()``/``get_info()`` for the ASCII channel.
- rig timing (``timing``): ``SampleClock`` stamps samples on the sensor's clock,
  ``CommandPlayout`` applies commands at their stamps (open-loop runs), ``set_realtime_priority``.
"""

from .amplifier import Amplifier, DeviceInfo, GCSAmplifier, MDT69xAmplifier, make_amplifier
from .decimation import Decimated, Decimator
from .driver import DriverConfig, DriverState, SetResult, VoltageDriver, Watchdog
from .errors import (
    ConfigError,
    ConnectionLost,
    DeviceError,
    DeviceTimeout,
    GCSError,
    HardwareError,
    LimitsError,
    NonFiniteVoltageError,
    NotConnected,
    ProtocolError,
    SafetyError,
    SensorCommandError,
    TransportError,
    VoltageOutOfRangeError,
)
from .optoncdt import FrameFormat, OptoNCDTParser, SampleBlock, Status, frame_format
from .safety import VoltageLimits
from .sensor import SensorConfig, SensorReader
from .timing import CommandPlayout, SampleClock, set_realtime_priority
from .transport import SerialTransport, TcpTransport, Transport, make_transport

__all__ = [
    "Amplifier",
    "CommandPlayout",
    "ConfigError",
    "ConnectionLost",
    "Decimated",
    "Decimator",
    "DeviceError",
    "DeviceInfo",
    "DeviceTimeout",
    "DriverConfig",
    "DriverState",
    "FrameFormat",
    "GCSAmplifier",
    "GCSError",
    "HardwareError",
    "LimitsError",
    "MDT69xAmplifier",
    "NonFiniteVoltageError",
    "NotConnected",
    "OptoNCDTParser",
    "ProtocolError",
    "SafetyError",
    "SampleBlock",
    "SampleClock",
    "SensorCommandError",
    "SensorConfig",
    "SensorReader",
    "SerialTransport",
    "SetResult",
    "Status",
    "TcpTransport",
    "Transport",
    "TransportError",
    "VoltageDriver",
    "VoltageLimits",
    "VoltageOutOfRangeError",
    "Watchdog",
    "frame_format",
    "make_amplifier",
    "make_transport",
    "set_realtime_priority",
]
