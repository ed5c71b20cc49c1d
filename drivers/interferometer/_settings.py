"""An interferometer's settings in a station file: one model per adapter, discriminated on ``adapter``.

Both CAN transports share the frame layout and the receive options (the annotated types below);
each model lists its transport's own fields first.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from drivers._settings import DeviceSettings
from drivers.interferometer._layout import COUNTER_MODULUS, FrameLayout

Layout = Annotated[FrameLayout, Field(description="CAN ids, scaling and rates of the feed (any subset of fields)")]
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
