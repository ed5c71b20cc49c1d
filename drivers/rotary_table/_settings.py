"""A rotary table's settings in a station file: one model per adapter, discriminated on ``adapter``."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator

from drivers._settings import DeviceSettings
from drivers.rotary_table._registers import RegisterMap

# What every adapter shares: how long to wait for one answer, how often to retry, how often to poll.
AnswerTimeout = Annotated[float, Field(gt=0, le=60, description="seconds to wait for one answer")]
Retries = Annotated[
    int, Field(ge=0, le=10, description="extra attempts after a timeout or a garbled answer (bounded)")
]
PollInterval = Annotated[float, Field(gt=0, le=1, description="seconds between status polls while waiting")]
ModbusUnit = Annotated[int, Field(ge=0, le=247, description="Modbus device id of the drive")]
SerialPort = Annotated[
    str, Field(min_length=1, description="serial device path or pyserial URL (socket://127.0.0.1:50000)")
]
Baudrate = Annotated[int, Field(gt=0, description="serial line speed, bit/s")]
ReferenceOnOpen = Annotated[
    bool, Field(description="open() makes the table usable: servo on, and a reference move if it is unreferenced")
]
ServoTimeout = Annotated[float, Field(gt=0, le=60, description="seconds open() allows the servo to come on")]
ReferenceTimeout = Annotated[
    float, Field(gt=0, le=600, description="seconds open() allows the reference move (homing) to finish")
]
GcsAxis = Annotated[str, Field(pattern=r"^[A-Za-z0-9_]+$", description="GCS axis identifier")]


class ModbusTcpSettings(DeviceSettings):
    """A servo drive over Modbus TCP (pymodbus; ``ModbusTable``)."""

    adapter: Literal["modbus_tcp"] = Field("modbus_tcp", description="this adapter: a Modbus TCP servo drive")
    host: str = Field(min_length=1, description="the drive's (or gateway's) address")
    port: int = Field(502, ge=1, le=65535, description="TCP port")
    unit: ModbusUnit = 1
    register_map: RegisterMap = Field(
        default_factory=RegisterMap, description="the drive's registers and scaling (any subset of fields)"
    )
    timeout: AnswerTimeout = 0.5
    retries: Retries = 2
    poll_interval: PollInterval = 0.01
    reference_on_open: ReferenceOnOpen = True
    servo_timeout: ServoTimeout = 5.0
    reference_timeout: ReferenceTimeout = 60.0


class ModbusRtuSettings(DeviceSettings):
    """A servo drive over Modbus RTU on a serial line (pymodbus; ``ModbusTable``)."""

    adapter: Literal["modbus_rtu"] = Field("modbus_rtu", description="this adapter: a Modbus RTU servo drive")
    port: SerialPort
    baudrate: Baudrate = 115200
    unit: ModbusUnit = 1
    register_map: RegisterMap = Field(
        default_factory=RegisterMap, description="the drive's registers and scaling (any subset of fields)"
    )
    timeout: AnswerTimeout = 0.5
    retries: Retries = 2
    poll_interval: PollInterval = 0.01
    reference_on_open: ReferenceOnOpen = True
    servo_timeout: ServoTimeout = 5.0
    reference_timeout: ReferenceTimeout = 60.0

    @field_validator("unit")
    @classmethod
    def _not_broadcast(cls, unit: int) -> int:
        if unit == 0:  # on TCP 0 may name the device itself; on a serial line nobody answers it
            raise ValueError("unit 0 is the RTU broadcast address, which no drive answers; use the drive's id 1..247")
        return unit


class GcsSerialSettings(DeviceSettings):
    """One axis of a PI GCS 2.0 controller on a serial line (pyserial; ``GcsTable``)."""

    adapter: Literal["gcs_serial"] = Field("gcs_serial", description="this adapter: a PI GCS 2.0 controller")
    port: SerialPort
    baudrate: Baudrate = 115200
    axis: GcsAxis = "1"
    timeout: AnswerTimeout = 0.5
    retries: Retries = 2
    poll_interval: PollInterval = 0.01
    reference_on_open: ReferenceOnOpen = True
    servo_timeout: ServoTimeout = 5.0
    reference_timeout: ReferenceTimeout = 60.0


class GcsTcpSettings(DeviceSettings):
    """One axis of a PI GCS 2.0 controller on its TCP interface (``GcsTable``; PI listens on port 50000)."""

    adapter: Literal["gcs_tcp"] = Field("gcs_tcp", description="this adapter: a PI GCS 2.0 controller over TCP")
    host: str = Field(min_length=1, description="the controller's address")
    port: int = Field(50000, ge=1, le=65535, description="TCP port (PI controllers: 50000)")
    axis: GcsAxis = "1"
    timeout: AnswerTimeout = 0.5
    retries: Retries = 2
    poll_interval: PollInterval = 0.01
    reference_on_open: ReferenceOnOpen = True
    servo_timeout: ServoTimeout = 5.0
    reference_timeout: ReferenceTimeout = 60.0


GcsSettings = GcsSerialSettings | GcsTcpSettings
RotaryTableSettings = Annotated[ModbusTcpSettings | ModbusRtuSettings | GcsSerialSettings | GcsTcpSettings,
                                Field(discriminator="adapter")]
