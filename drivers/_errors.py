"""Typed device errors shared by every adapter.

Every error names the device, the operation that failed and the cause, so that an operator (or the
procedure engine) can act on it without reading a traceback.
"""

from __future__ import annotations


class DeviceError(Exception):
    """A device operation failed.

    Parameters
    ----------
    device : str
        Which device (its configured name, e.g. ``"robot"`` or ``"camera x (0815-0000)"``).
    operation : str
        What was being done (``"moveL"``, ``"read position register 0x0008"`` ...).
    cause : str
        Why it failed, in words an operator understands.
    """

    def __init__(self, device: str, operation: str, cause: str) -> None:
        self.device = device
        self.operation = operation
        self.cause = cause
        super().__init__(f"{device}: {operation} failed: {cause}")

    def __reduce__(self):  # keep the three fields across pickling (subprocess watchdogs)
        return (self.__class__, (self.device, self.operation, self.cause))


class DeviceTimeout(DeviceError):
    """The device did not answer or finish within the allowed time."""


class DeviceConnectionError(DeviceError):
    """The device could not be reached, or the connection was lost."""


class ProtocolError(DeviceError):
    """The device answered with something the protocol does not allow (garbage, bad CRC, ...)."""


class DeviceFault(DeviceError):
    """The device reports a fault or alarm state of its own."""


class MotionRefused(DeviceError):
    """A motion was refused before anything was sent (outside the envelope, too fast, ...)."""


class ClientLibraryMissing(DeviceConnectionError):
    """The adapter's client library is not installed (its optional extra was not asked for)."""


class SettingsError(ValueError):
    """A device's settings do not validate. The message names the device, the adapter and the
    setting, and what was expected, on one line."""
