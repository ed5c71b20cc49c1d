"""A camera's settings in a station file: one model per adapter, discriminated on ``adapter``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field

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


# One adapter today; the union is the seam another camera family is added to.
CameraSettings = Annotated[PylonSettings, Field(discriminator="adapter")]
