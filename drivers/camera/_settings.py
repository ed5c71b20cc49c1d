"""A camera's settings in a station file: one model per adapter, discriminated on ``adapter``."""

from __future__ import annotations

from ipaddress import IPv4Address
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, model_validator

from drivers._settings import DeviceSettings
from drivers.camera._interface import Roi


class PylonSettings(DeviceSettings):
    """A Basler GigE/USB3 camera (or pylon's camera emulator) through pypylon (``PylonCamera``)."""

    adapter: Literal["pylon"] = Field("pylon", description="this adapter: Basler cameras through pypylon")
    serial: str = Field(
        min_length=1, description="the camera's serial number (emulated cameras: 0815-0000, 0815-0001 ...)"
    )
    emulator_image: Path | None = Field(
        None,
        description="emulated cameras only: serve this image file (replaced atomically, it changes the next frame)",
    )
    exposure_s: float | None = Field(None, gt=0, description="exposure time, seconds (default: the camera's)")
    gain_db: float | None = Field(None, description="gain, dB (default: the camera's)")
    pixel_format: str | None = Field(
        None, min_length=1, description="Mono8, Mono10, Mono12, Mono16 ... (default: the camera's)"
    )
    roi: Roi | None = Field(
        None, description="region of interest {offset_x, offset_y, width, height}, pixels (default: full sensor)"
    )
    software_trigger: bool = Field(
        True, description="each grab fires a software trigger, so a frame is never older than the grab call"
    )
    trigger_source: str | None = Field(
        None, min_length=1,
        description="Software (default with software_trigger) or a hardware line such as Line1",
    )
    retries: int = Field(2, ge=0, le=10, description="extra grab attempts after an incomplete buffer or a timeout")
    timeout_s: float = Field(2.0, gt=0, description="default grab timeout, seconds")
    embedded_stamp: bool = Field(
        False, description="the camera embeds a frame stamp (frame number and time) in the image's first pixels: "
        "read it as the frame's exposure evidence and blank it (docs/cameras.md)")


class ActionSettings(DeviceSettings):
    """A GigE Vision action command that triggers several cameras at once (``trigger_source: Action1``)."""

    device_key: int = Field(0x0F0E0D0C, ge=0, lt=2**32, description="ActionDeviceKey, the same on every camera")
    group_key: int = Field(1, ge=0, lt=2**32, description="ActionGroupKey of action 1")
    group_mask: int = Field(1, ge=1, lt=2**32, description="ActionGroupMask of action 1")
    broadcast: IPv4Address | None = Field(
        None, description="send one command to this broadcast address (a real subnet); default: to each camera")


class AravisSettings(DeviceSettings):
    """Any GigE Vision camera through Aravis 0.8 (``AravisCamera``)."""

    adapter: Literal["aravis"] = Field("aravis", description="this adapter: GigE Vision cameras through Aravis")
    device: str | None = Field(
        None, min_length=1, description="Aravis device id (vendor-model-serial) or serial; or give address")
    address: IPv4Address | None = Field(None, description="the camera's IPv4 address (opened directly)")
    pixel_format: Literal["Mono8", "Mono12", "Mono16"] | None = Field(
        None, description="Mono8, Mono12 or Mono16 (default: the camera's)")
    exposure_s: float | None = Field(None, gt=0, description="exposure time, seconds (default: the camera's)")
    gain_db: float | None = Field(None, description="gain, dB (default: the camera's)")
    roi: Roi | None = Field(
        None, description="region of interest {offset_x, offset_y, width, height}, pixels (default: full sensor)")
    trigger_source: str = Field(
        "Software", pattern=r"^(Software|Line[0-9]|Action1)$",
        description="Software (each grab fires TriggerSoftware), a hardware line (Line0 …) or Action1")
    action: ActionSettings | None = Field(None, description="the action command's keys (trigger_source Action1)")
    packet_size: int | None = Field(
        None, ge=576, le=16384, description="GevSCPSPacketSize, bytes per stream datagram (9000: jumbo frames)")
    packet_resend: bool = Field(True, description="ask the camera to resend lost stream packets")
    packet_timeout_s: float = Field(0.02, gt=0, description="wait for a missing packet before asking again, s")
    frame_retention_s: float = Field(0.2, gt=0, description="keep an incomplete frame this long, s")
    buffers: int = Field(16, ge=2, le=1024, description="stream buffers queued for the camera")
    retries: int = Field(2, ge=0, le=10, description="extra grab attempts after an incomplete frame or a timeout")
    timeout_s: float = Field(2.0, gt=0, description="default grab timeout, seconds")

    @model_validator(mode="after")
    def _one_address(self) -> AravisSettings:
        if (self.device is None) == (self.address is None):
            raise ValueError("give exactly one of device (Aravis id or serial) and address")
        return self


# The union is the seam another camera family is added to.
CameraSettings = Annotated[PylonSettings | AravisSettings, Field(discriminator="adapter")]
