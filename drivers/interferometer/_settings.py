"""An interferometer's settings in a station file: one model per adapter, discriminated on ``adapter``.

Both CAN transports share the frame layout and the receive options (the annotated types below);
each model lists its transport's own fields first.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivers._settings import DeviceSettings
from drivers.interferometer._layout import COUNTER_MODULUS, FrameLayout


class HeadOptics(BaseModel):
    """How the head turns fringes into metres: its laser's vacuum wavelength and the nominal air
    whose refractive index it uses (the displacement is compensated for the real air by the host,
    from the environmental unit's readings). SI units; any subset of fields may be given."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    vacuum_wavelength: float = Field(632.991e-9, ge=300e-9, le=1700e-9, description="laser vacuum wavelength, m")
    nominal_air_temperature: float = Field(293.15, gt=0, description="nominal air temperature, K")
    nominal_pressure: float = Field(101_325.0, gt=0, description="nominal air pressure, Pa")
    nominal_relative_humidity: float = Field(0.5, ge=0, le=1, description="nominal relative humidity, a fraction")
    nominal_co2: float = Field(400.0, ge=0, description="nominal CO2 content, ppm (µmol/mol)")
    air_co2: float = Field(400.0, ge=0, description="CO2 content assumed for the measured air (the unit has no "
                           "CO2 sensor), ppm")

Layout = Annotated[FrameLayout, Field(description="CAN ids, scaling and rates of the feed (any subset of fields)")]
Optics = Annotated[HeadOptics, Field(description="the head's vacuum wavelength and nominal air (any subset of fields)")]
RingCapacity = Annotated[int, Field(ge=16, description="samples kept in the ring buffer (65536: a minute at 1 kHz)")]
OpenTimeout = Annotated[float, Field(gt=0, description="seconds allowed for one attempt to open the bus")]
OpenAttempts = Annotated[int, Field(ge=1, le=20, description="attempts before open() gives up")]
StallTimeout = Annotated[
    float | None,
    Field(gt=0, description="seconds of silence that count as a gap even with a contiguous counter; below 256 "
          "sample periods (default: 200 sample periods)"),
]
ReconnectInterval = Annotated[float, Field(gt=0, description="seconds between attempts to re-open a lost connection")]
CommandTimeout = Annotated[float, Field(gt=0, description="seconds to wait for the head's reply to a command")]
SyncBeforeAverage = Annotated[
    bool, Field(description="average only samples taken after the call (one sync round trip, ~1-2 ms)")
]


def _check_stall_timeout(stall_timeout: float | None, layout: FrameLayout) -> None:
    if stall_timeout is not None and stall_timeout * layout.sample_rate >= COUNTER_MODULUS:
        raise ValueError(f"stall_timeout {stall_timeout} s spans >= {COUNTER_MODULUS} samples at "
                         f"{layout.sample_rate} Hz; the 8-bit sample counter could wrap unnoticed")


class SocketcandSettings(DeviceSettings):
    """The feed served by a socketcand daemon over TCP (python-can ``socketcand``; ``CanInterferometer``)."""

    adapter: Literal["socketcand"] = Field("socketcand", description="this adapter: CAN through a socketcand daemon")
    host: str = Field(min_length=1, description="the socketcand daemon's address")
    port: int = Field(ge=1, le=65535, description="the socketcand daemon's TCP port (29536 by convention)")
    channel: str = Field("can0", min_length=1, description="CAN interface name on the daemon's host")
    layout: Layout = Field(default_factory=FrameLayout)
    optics: Optics = Field(default_factory=HeadOptics)
    ring_capacity: RingCapacity = 65536
    open_timeout: OpenTimeout = 5.0
    open_attempts: OpenAttempts = 5
    stall_timeout: StallTimeout = None
    reconnect_interval: ReconnectInterval = 0.5
    command_timeout: CommandTimeout = 3.0
    sync_before_average: SyncBeforeAverage = True

    @model_validator(mode="after")
    def _counter_cannot_wrap(self) -> SocketcandSettings:
        _check_stall_timeout(self.stall_timeout, self.layout)
        return self


class SlcanSettings(DeviceSettings):
    """The feed on an slcan (Lawicel ASCII) USB-CAN adapter (python-can ``slcan``; ``CanInterferometer``)."""

    adapter: Literal["slcan"] = Field("slcan", description="this adapter: an slcan (Lawicel) USB-CAN adapter")
    port: str = Field(min_length=1, description="serial device of the adapter (/dev/ttyACM0)")
    bitrate: int = Field(1_000_000, gt=0, le=1_000_000, description="CAN bit rate, bit/s")
    layout: Layout = Field(default_factory=FrameLayout)
    optics: Optics = Field(default_factory=HeadOptics)
    ring_capacity: RingCapacity = 65536
    open_timeout: OpenTimeout = 5.0
    open_attempts: OpenAttempts = 5
    stall_timeout: StallTimeout = None
    reconnect_interval: ReconnectInterval = 0.5
    command_timeout: CommandTimeout = 3.0
    sync_before_average: SyncBeforeAverage = True

    @model_validator(mode="after")
    def _counter_cannot_wrap(self) -> SlcanSettings:
        _check_stall_timeout(self.stall_timeout, self.layout)
        return self


InterferometerSettings = Annotated[SocketcandSettings | SlcanSettings, Field(discriminator="adapter")]
