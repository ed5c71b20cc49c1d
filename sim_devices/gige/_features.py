"""The twin camera's features: one table, from which both its register map and its GenICam XML come.

A GigE Vision client learns every feature beyond the bootstrap registers from the device's GenICam
XML (a ``RegisterDescription``: each feature a node pointing at a register). The twin keeps the
features in ``FEATURES`` below; ``genicam_xml()`` writes the XML from them and the camera
(``_camera.py``) serves the same addresses, so the two cannot drift apart. Node kinds used:
``IntReg``/``Integer``, ``FloatReg``/``Float`` (IEEE 754 doubles, big-endian), ``Enumeration``
over an ``IntReg``, ``Command`` (a register written with its command value) and ``StringReg``;
``IntSwissKnife`` for the ROI limits (``Width`` ≤ ``SensorWidth − OffsetX``).

The names are the SFNC ones (GenICam Standard Features Naming Convention) that Aravis's
``ArvCamera`` and most applications look for: ``Width``, ``Height``, ``OffsetX``, ``OffsetY``,
``PixelFormat``, ``PayloadSize``, ``AcquisitionMode``, ``AcquisitionStart``/``Stop``,
``TriggerSelector``/``Mode``/``Source``/``Activation``/``Software``, ``TriggerDelay``,
``ExposureTime`` (µs), ``Gain`` (dB), ``AcquisitionFrameRate``, ``ActionDeviceKey``,
``ActionSelector``/``ActionGroupKey``/``ActionGroupMask``, ``GevTimestampTickFrequency``,
``GevTimestampControlLatch``/``GevTimestampValue``, ``GevSCPSPacketSize``, ``GevHeartbeatTimeout``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from xml.sax.saxutils import escape

# Bootstrap registers (GigE Vision) the twin serves.
VERSION = 0x0000
DEVICE_MODE = 0x0004
MAC_HIGH = 0x0008
MAC_LOW = 0x000C
SUPPORTED_IP_CONFIGURATION = 0x0010
CURRENT_IP_CONFIGURATION = 0x0014
CURRENT_IP = 0x0024
CURRENT_SUBNET_MASK = 0x0034
CURRENT_GATEWAY = 0x0044
MANUFACTURER_NAME = 0x0048  # 32 bytes
MODEL_NAME = 0x0068  # 32
DEVICE_VERSION = 0x0088  # 32
MANUFACTURER_INFO = 0x00A8  # 48
SERIAL_NUMBER = 0x00D8  # 16
USER_NAME = 0x00E8  # 16
DISCOVERY_DATA_SIZE = 0xF8
FIRST_URL = 0x0200  # 512
SECOND_URL = 0x0400
NETWORK_INTERFACES = 0x0600
MESSAGE_CHANNELS = 0x0900
STREAM_CHANNELS = 0x0904
ACTION_DEVICE_KEY = 0x090C
GVCP_CAPABILITY = 0x0934
HEARTBEAT_TIMEOUT = 0x0938
TICK_FREQUENCY_HIGH = 0x093C
TICK_FREQUENCY_LOW = 0x0940
TIMESTAMP_CONTROL = 0x0944
TIMESTAMP_LATCHED_HIGH = 0x0948
TIMESTAMP_LATCHED_LOW = 0x094C
CONTROL_CHANNEL_PRIVILEGE = 0x0A00
STREAM_PORT = 0x0D00
STREAM_PACKET_SIZE = 0x0D04
STREAM_PACKET_DELAY = 0x0D08
STREAM_DESTINATION = 0x0D18
STREAM_SOURCE_PORT = 0x0D1C
ACTION_GROUP_KEY = 0x9800  # action 1 (ActionSelector 1); GigE Vision puts action n at + 0x10·(n − 1)
ACTION_GROUP_MASK = 0x9804

CCP_EXCLUSIVE = 0x1
CCP_CONTROL = 0x2
TIMESTAMP_LATCH = 0x2
TIMESTAMP_RESET = 0x1
# GVCP capability bits the twin has: several registers per READREG/WRITEREG (concatenation),
# WRITEMEM, PACKETRESEND, PENDING_ACK, ACTION, the serial number and user name registers.
CAPABILITIES = (1 << 0) | (1 << 1) | (1 << 2) | (1 << 5) | (1 << 6) | (1 << 30) | (1 << 31)

DEVICE_REGISTERS = 0x10000
XML_ADDRESS = 0x20000

PIXEL_FORMATS = {"Mono8": 0x01080001, "Mono12": 0x01100005, "Mono16": 0x01100007}
BYTES_PER_PIXEL = {"Mono8": 1, "Mono12": 2, "Mono16": 2}
ACQUISITION_MODES = {"Continuous": 0, "SingleFrame": 1}
TRIGGER_SELECTORS = {"FrameStart": 0}
TRIGGER_MODES = {"Off": 0, "On": 1}
TRIGGER_SOURCES = {"Software": 0, "Line0": 1, "Line1": 2, "Action1": 3}
TRIGGER_ACTIVATIONS = {"RisingEdge": 0}


@dataclass(frozen=True)
class Feature:
    """One feature: its SFNC name, node kind, register address and limits.

    ``kind``: ``int``, ``float``, ``enum``, ``command``, ``string``. ``access``: ``RO``, ``RW``, ``WO``.
    ``maximum`` may name another feature or a formula over ``SensorWidth``/``OffsetX`` … (an
    ``IntSwissKnife``).
    """

    name: str
    kind: str
    address: int
    access: str = "RW"
    length: int = 4
    minimum: float | None = None
    maximum: float | str | None = None
    increment: int | None = None
    unit: str | None = None
    entries: dict[str, int] = field(default_factory=dict)
    category: str = "AcquisitionControl"


def _device(offset: int) -> int:
    return DEVICE_REGISTERS + offset


FEATURES: tuple[Feature, ...] = (
    Feature("DeviceVendorName", "string", MANUFACTURER_NAME, "RO", 32, category="DeviceControl"),
    Feature("DeviceModelName", "string", MODEL_NAME, "RO", 32, category="DeviceControl"),
    Feature("DeviceVersion", "string", DEVICE_VERSION, "RO", 32, category="DeviceControl"),
    Feature("DeviceSerialNumber", "string", SERIAL_NUMBER, "RO", 16, category="DeviceControl"),
    Feature("DeviceUserID", "string", USER_NAME, "RW", 16, category="DeviceControl"),
    Feature("SensorWidth", "int", _device(0x00), "RO", category="ImageFormatControl"),
    Feature("SensorHeight", "int", _device(0x04), "RO", category="ImageFormatControl"),
    Feature("WidthMax", "int", _device(0x08), "RO", category="ImageFormatControl"),
    Feature("HeightMax", "int", _device(0x0C), "RO", category="ImageFormatControl"),
    Feature("Width", "int", _device(0x10), minimum=16, maximum="SensorWidth - OffsetX", increment=4,
            category="ImageFormatControl"),
    Feature("Height", "int", _device(0x14), minimum=2, maximum="SensorHeight - OffsetY", increment=2,
            category="ImageFormatControl"),
    Feature("OffsetX", "int", _device(0x18), minimum=0, maximum="SensorWidth - Width", increment=4,
            category="ImageFormatControl"),
    Feature("OffsetY", "int", _device(0x1C), minimum=0, maximum="SensorHeight - Height", increment=2,
            category="ImageFormatControl"),
    Feature("PixelFormat", "enum", _device(0x20), entries=PIXEL_FORMATS, category="ImageFormatControl"),
    Feature("PayloadSize", "int", _device(0x24), "RO", category="ImageFormatControl"),
    Feature("AcquisitionMode", "enum", _device(0x28), entries=ACQUISITION_MODES),
    Feature("AcquisitionStart", "command", _device(0x2C), "WO"),
    Feature("AcquisitionStop", "command", _device(0x30), "WO"),
    Feature("TriggerSelector", "enum", _device(0x34), entries=TRIGGER_SELECTORS),
    Feature("TriggerMode", "enum", _device(0x38), entries=TRIGGER_MODES),
    Feature("TriggerSource", "enum", _device(0x3C), entries=TRIGGER_SOURCES),
    Feature("TriggerActivation", "enum", _device(0x40), entries=TRIGGER_ACTIVATIONS),
    Feature("TriggerSoftware", "command", _device(0x44), "WO"),
    Feature("ActionSelector", "int", _device(0x48), minimum=1, maximum=1, increment=1),
    Feature("ExposureTime", "float", _device(0x50), length=8, minimum=10.0, maximum=500_000.0, unit="us"),
    Feature("Gain", "float", _device(0x58), length=8, minimum=0.0, maximum=24.0, unit="dB"),
    Feature("AcquisitionFrameRate", "float", _device(0x60), length=8, minimum=0.1, maximum=10_000.0, unit="Hz"),
    Feature("TriggerDelay", "float", _device(0x68), length=8, minimum=0.0, maximum=1_000_000.0, unit="us"),
    Feature("ActionDeviceKey", "int", ACTION_DEVICE_KEY, "WO", category="ActionControl"),
    Feature("ActionGroupKey", "int", ACTION_GROUP_KEY, category="ActionControl"),
    Feature("ActionGroupMask", "int", ACTION_GROUP_MASK, category="ActionControl"),
    Feature("GevTimestampTickFrequency", "int", TICK_FREQUENCY_HIGH, "RO", 8, category="TransportLayerControl"),
    Feature("GevTimestampControlLatch", "command", TIMESTAMP_CONTROL, "WO", category="TransportLayerControl"),
    Feature("GevTimestampValue", "int", TIMESTAMP_LATCHED_HIGH, "RO", 8, category="TransportLayerControl"),
    Feature("GevHeartbeatTimeout", "int", HEARTBEAT_TIMEOUT, minimum=500, maximum=600_000, unit="ms",
            category="TransportLayerControl"),
    Feature("GevSCPSPacketSize", "int", STREAM_PACKET_SIZE, minimum=576, maximum=16_384, increment=4,
            category="TransportLayerControl"),
    Feature("GevSCPD", "int", STREAM_PACKET_DELAY, minimum=0, maximum=1_000_000, category="TransportLayerControl"),
)
FEATURE = {f.name: f for f in FEATURES}
COMMAND_VALUES = {"GevTimestampControlLatch": TIMESTAMP_LATCH}

_HEADER = """<?xml version="1.0" encoding="utf-8"?>
<RegisterDescription ModelName="{model}" VendorName="{vendor}" StandardNameSpace="GEV" SchemaMajorVersion="1"
 SchemaMinorVersion="1" SchemaSubMinorVersion="0" MajorVersion="1" MinorVersion="0" SubMinorVersion="0"
 ToolTip="OPR repeatability screen camera (simulated)" ProductGuid="0" VersionGuid="0"
 xmlns="http://www.genicam.org/GenApi/Version_1_1" xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
 xsi:schemaLocation="http://www.genicam.org/GenApi/Version_1_1 GenApiSchema.xsd">
"""


def _register(name: str, feature: Feature, *, float_register: bool = False) -> str:
    kind = "FloatReg" if float_register else "IntReg"
    sign = "" if float_register else "<Sign>Unsigned</Sign>"
    return (f'<{kind} Name="{name}"><Address>0x{feature.address:x}</Address><Length>{feature.length}</Length>'
            f"<AccessMode>{feature.access}</AccessMode><pPort>Device</pPort>{sign}"
            f"<Endianess>BigEndian</Endianess></{kind}>\n")


def _limit(tag: str, feature: Feature, value: float | str | None) -> str:
    if value is None:
        return ""
    if isinstance(value, str):
        return f"<p{tag}>{feature.name}{tag}Calc</p{tag}>"
    return f"<{tag}>{value:g}</{tag}>" if feature.kind == "float" else f"<{tag}>{int(value)}</{tag}>"


def _swiss_knife(feature: Feature, formula: str) -> str:
    """``SensorWidth - OffsetX`` → an IntSwissKnife over those features' registers."""
    names = [token for token in formula.replace("-", " ").split() if token in FEATURE]
    variables = "".join(f'<pVariable Name="{n.upper()}">{n}Reg</pVariable>' for n in names)
    expression = formula
    for n in names:
        expression = expression.replace(n, n.upper())
    return (f'<IntSwissKnife Name="{feature.name}MaxCalc">{variables}<Formula>{escape(expression.replace(" ", ""))}'
            f"</Formula></IntSwissKnife>\n")


def _node(feature: Feature) -> str:
    name, reg = feature.name, f"{feature.name}Reg"
    if feature.kind == "string":
        return (f'<StringReg Name="{name}" NameSpace="Standard"><Address>0x{feature.address:x}</Address>'
                f"<Length>{feature.length}</Length><AccessMode>{feature.access}</AccessMode>"
                f"<pPort>Device</pPort></StringReg>\n")
    if feature.kind == "command":
        value = COMMAND_VALUES.get(name, 1)
        return (f'<Command Name="{name}" NameSpace="Standard"><pValue>{reg}</pValue>'
                f"<CommandValue>{value}</CommandValue></Command>\n" + _register(reg, feature))
    if feature.kind == "enum":
        entries = "".join(f'<EnumEntry Name="{k}"><Value>{v}</Value></EnumEntry>' for k, v in feature.entries.items())
        return (f'<Enumeration Name="{name}" NameSpace="Standard">{entries}<pValue>{reg}</pValue></Enumeration>\n'
                + _register(reg, feature))
    body = _limit("Min", feature, feature.minimum) + _limit("Max", feature, feature.maximum)
    if feature.increment is not None:
        body += f"<Inc>{feature.increment}</Inc>"
    if feature.unit is not None:
        body += f"<Unit>{feature.unit}</Unit>"
    kind = "Float" if feature.kind == "float" else "Integer"
    extra = _swiss_knife(feature, feature.maximum) if isinstance(feature.maximum, str) else ""
    return (f'<{kind} Name="{name}" NameSpace="Standard"><pValue>{reg}</pValue>{body}</{kind}>\n'
            + _register(reg, feature, float_register=feature.kind == "float") + extra)


def genicam_xml(vendor: str, model: str) -> bytes:
    """The GenICam XML the twin serves at ``XML_ADDRESS`` (its URL in the first URL register)."""
    categories: dict[str, list[str]] = {}
    for feature in FEATURES:
        categories.setdefault(feature.category, []).append(feature.name)
    parts = [_HEADER.format(model=escape(model), vendor=escape(vendor))]
    parts.append('<Category Name="Root" NameSpace="Standard">'
                 + "".join(f"<pFeature>{c}</pFeature>" for c in categories) + "</Category>\n")
    for category, names in categories.items():
        parts.append(f'<Category Name="{category}" NameSpace="Standard">'
                     + "".join(f"<pFeature>{n}</pFeature>" for n in names) + "</Category>\n")
    parts += [_node(feature) for feature in FEATURES]
    parts.append('<Port Name="Device" NameSpace="Standard"/>\n</RegisterDescription>\n')
    xml = "".join(parts).encode()
    return xml + b" " * (-len(xml) % 4)  # READMEM reads whole 4-byte words: the file ends on one
