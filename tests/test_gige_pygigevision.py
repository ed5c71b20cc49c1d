"""An independent GigE Vision client (pyGigEVision 0.2.2, pure Python) against the same twin Aravis uses.

pyGigEVision does not read GenICam; the test finds each feature's register in the twin's XML with
the standard library (so the XML's addresses are checked too), then drives the camera with raw
GVCP register writes and receives GVSP with pyGigEVision's own receiver. A convention error in the
twin (byte order, header layout, packet ids, the XML URL) that Aravis happens to tolerate fails here
(one did: the URL's bare-hex address, which pyGigEVision reads as decimal). Packet resend is tested
with Aravis only: pyGigEVision hands a frame over as soon as its trailer arrives.
"""

from __future__ import annotations

import socket
import struct
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from tests._gige import Truth, gige_twins, record_of

pyGigEVision = pytest.importorskip("pyGigEVision", reason="pyGigEVision is not installed (the test extra)")
pytestmark = pytest.mark.timeout(120)
NS = {"g": "http://www.genicam.org/GenApi/Version_1_1"}


def _registers(xml: bytes) -> dict[str, int]:
    """Feature name → register address, through each node's pValue (or its own Address)."""
    root = ET.fromstring(xml)
    addresses = {node.get("Name"): int(node.findtext("g:Address", namespaces=NS) or "0", 16)
                 for node in root if node.find("g:Address", NS) is not None}
    out = dict(addresses)
    for node in root:
        target = node.findtext("g:pValue", namespaces=NS)
        if target in addresses:
            out[node.get("Name")] = addresses[target]
    return out


def _entries(xml: bytes, feature: str) -> dict[str, int]:
    root = ET.fromstring(xml)
    node = next(n for n in root if n.get("Name") == feature)
    return {e.get("Name"): int(e.findtext("g:Value", namespaces=NS), 0) for e in node.findall("g:EnumEntry", NS)}


@pytest.fixture(scope="module")
def twin():
    with gige_twins("z") as (started,):
        yield started


def test_pygigevision_discovers_reads_the_xml_and_receives_the_renderers_frame(twin):
    host = twin.endpoints["host"]
    # Discovery, unicast (the twin listens on its own address, not on a broadcast one).
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.settimeout(2.0)
    probe.sendto(struct.pack(">BBHHH", 0x42, 0x11, 0x0002, 0, 0xFFFF), (host, 3956))
    answer, _ = probe.recvfrom(1024)
    probe.close()
    from pyGigEVision.gvcp import _parse_discovery_ack

    found = _parse_discovery_ack(answer, host)
    assert found is not None and found["serial"] == "OPR-GV-z" and found["manufacturer"] == "OPR Lab"

    client, xml = pyGigEVision.bootstrap(host)
    try:
        registers = _registers(xml)
        assert client.read_reg(registers["SensorWidth"]) == 1024 and client.read_reg(registers["SensorHeight"]) == 1040
        sources = _entries(xml, "TriggerSource")
        client.write_reg(registers["TriggerMode"], _entries(xml, "TriggerMode")["On"])
        client.write_reg(registers["TriggerSource"], sources["Software"])
        for name, value in (("OffsetX", 0), ("OffsetY", 0), ("Width", 320), ("Height", 320), ("OffsetX", 352),
                            ("OffsetY", 360)):
            client.write_reg(registers[name], value)
        client.write_reg(registers["PixelFormat"], _entries(xml, "PixelFormat")["Mono16"])
        assert client.read_reg(registers["PayloadSize"]) == 320 * 320 * 2
        receiver = pyGigEVision.GVSPReceiver(local_ip="127.0.0.1", camera_ip=host, packet_size=1500)
        receiver.start()
        try:
            client.write_reg(0x0D18, int.from_bytes(socket.inet_aton("127.0.0.1"), "big"))  # GevSCDA
            client.write_reg(0x0D00, receiver.port)  # GevSCPHostPort
            client.write_reg(registers["AcquisitionStart"], 1)
            client.write_reg(registers["TriggerSoftware"], 1)
            got = receiver.get_frame_with_info(timeout=10.0)
            client.write_reg(registers["AcquisitionStop"], 1)
        finally:
            receiver.close()
        assert got is not None
        image, info = got
        record = record_of(twin, info["block_id"])
        assert info["complete"] and info["timestamp"] == record["ticks"]
        assert (info["width"], info["height"]) == (320, 320) and info["pixel_format"] == 0x01100007
        assert np.array_equal(image, Truth().frame(record))
    finally:
        client.disconnect()
    assert twin.call("stats")["controller"] is False  # the release was honoured


def test_a_second_host_is_refused_while_one_holds_control(twin):
    first = pyGigEVision.GVCPClient(twin.endpoints["host"])
    first.connect()
    try:
        second = pyGigEVision.GVCPClient(twin.endpoints["host"])
        with pytest.raises(pyGigEVision.GVCPError) as refused:
            second.connect(force=False)
        assert refused.value.status == 0x8006  # ACCESS_DENIED
    finally:
        first.disconnect()
