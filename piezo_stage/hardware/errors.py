"""Exception classes of the hardware layer: one specific class per failure a caller can act on."""

from __future__ import annotations

from piezo_stage.errors import PiezoStageError


class HardwareError(PiezoStageError):
    """Base class for every error raised by piezo_stage.hardware."""


class ConfigError(HardwareError, ValueError):
    """A configuration value is invalid (bad URL, unknown family, negative rate, ...)."""


# --- link ---------------------------------------------------------------------------------------
class TransportError(HardwareError):
    """The byte link (serial port, pty or TCP socket) failed."""


class ConnectionLost(TransportError):
    """The link dropped (EOF, hang-up, I/O error) or the device stopped answering."""


class DeviceTimeout(TransportError):
    """No complete reply arrived within the timeout."""


class NotConnected(TransportError):
    """An operation needs an open link; call connect() (or reconnect()) first."""


# --- device / protocol --------------------------------------------------------------------------
class ProtocolError(HardwareError):
    """A reply did not have the expected form (garbled, wrong field, unexpected text)."""


class DeviceError(HardwareError):
    """The device reported an error for a command."""

    def __init__(self, code: int | str, message: str, command: str = "") -> None:
        self.code = code
        self.message = message
        self.command = command
        where = f" after {command!r}" if command else ""
        super().__init__(f"device error {code}{where}: {message}")


class GCSError(DeviceError):
    """A PI GCS controller latched a non-zero error code (read with ``ERR?``)."""


class SensorCommandError(DeviceError):
    """An optoNCDT ASCII command was refused (``Exxx`` reply) or is not available."""


# --- safety -------------------------------------------------------------------------------------
class SafetyError(HardwareError, ValueError):
    """A voltage command was refused by the driver's safety checks."""


class NonFiniteVoltageError(SafetyError):
    """The requested voltage is NaN or infinite; nothing was sent."""


class VoltageOutOfRangeError(SafetyError):
    """The requested voltage lies outside [min, max] and the driver is set to refuse, not clamp."""


class LimitsError(SafetyError):
    """The configured and device voltage limits do not intersect, or safe_voltage is outside."""


class CommandExpired(SafetyError):
    """A command received before the watchdog fired arrived for application after it: dropped."""


class SafeStateNotReached(HardwareError):
    """Shutdown could not bring the output to ``safe_voltage`` (link down, device refused)."""
