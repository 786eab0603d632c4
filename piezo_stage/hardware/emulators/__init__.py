"""Device emulators (PI GCS controller, Thorlabs MDT69x, optoNCDT sensor, and a stage of one
or more axes coupling them to the simulated plant) served on ptys or loopback TCP by
:class:`EmulatorServer`.
"""

from .gcs_device import GCSDeviceModel
from .loopback import LoopbackTransport, ManualClock
from .mdt_device import MDTDeviceModel
from .optoncdt_device import OptoNCDTDeviceModel
from .server import EmulatorServer, Faults

__all__ = [
    "EmulatorServer",
    "Faults",
    "GCSDeviceModel",
    "LoopbackTransport",
    "ManualClock",
    "MDTDeviceModel",
    "OptoNCDTDeviceModel",
]
