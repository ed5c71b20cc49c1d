"""Device drivers: one subpackage per device kind, each an interface plus adapters on the real
client libraries. This package never imports ``sim_devices``."""

from drivers._errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceFault,
    DeviceTimeout,
    MotionRefused,
    ProtocolError,
)

__all__ = [
    "DeviceConnectionError",
    "DeviceError",
    "DeviceFault",
    "DeviceTimeout",
    "MotionRefused",
    "ProtocolError",
]
