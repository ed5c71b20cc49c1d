"""Device drivers: one subpackage per device kind, each an interface, typed settings and adapters
on the real client libraries. This package never imports ``sim_devices``.

Shared here: the typed device errors (every one names device, operation and cause) and
``SettingsError``, raised by every kind's ``create()`` for settings that do not validate.
"""

from drivers._errors import (
    ClientLibraryMissing,
    DeviceConnectionError,
    DeviceError,
    DeviceFault,
    DeviceTimeout,
    MotionRefused,
    ProtocolError,
    SettingsError,
)

__all__ = [
    "ClientLibraryMissing",
    "DeviceConnectionError",
    "DeviceError",
    "DeviceFault",
    "DeviceTimeout",
    "MotionRefused",
    "ProtocolError",
    "SettingsError",
]
