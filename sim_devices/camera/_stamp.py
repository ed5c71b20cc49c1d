"""The camera file twin's embedded frame stamp: when a frame was exposed, written into its pixels.

Cameras that cannot send chunk data along with the image (and pylon's camera emulator, which
serves a file's pixels and nothing else) can embed a frame stamp in the first pixels of the image,
as several industrial cameras do. The file twin stamps every frame it puts in place, so that a
reader can *prove* the frame shows the scene after a move ended, not merely guess it from the
content. Written from the format below (docs/cameras.md, "Embedded frame stamp"); the driver reads
it with its own decoder.

Layout: the first ``STAMP_PIXELS`` pixels of the top row, one byte per pixel (the pixel's value)::

    0   4  magic b"OPRS"
    4   1  version (1)
    5   1  flags: bit 0 = the frame shows the scene as it has been still since ``time`` (a file twin
           writes a frame only for a settled scene); otherwise ``time`` is the exposure's start
    6   2  reserved (0)
    8   4  frame number, little-endian unsigned
    12  8  time: seconds on the host's wall clock (``time.time()``), IEEE-754 double, little-endian
    20  4  CRC-32 of bytes 0-19, little-endian
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

STAMP_PIXELS = 24
MAGIC = b"OPRS"
VERSION = 1
STILL_SINCE = 0x01
_HEAD = struct.Struct("<4sBBHId")


def stamp_bytes(frame_number: int, time_s: float, *, still: bool = True) -> bytes:
    """The 24 stamp bytes of frame ``frame_number`` at host time ``time_s`` (see module docstring)."""
    head = _HEAD.pack(MAGIC, VERSION, STILL_SINCE if still else 0, 0, int(frame_number) & 0xFFFFFFFF, float(time_s))
    return head + struct.pack("<I", zlib.crc32(head))


def stamp_image(image: np.ndarray, frame_number: int, time_s: float, *, still: bool = True) -> np.ndarray:
    """``image`` with the stamp in its first top-row pixels (in place; returned for convenience)."""
    image[0, :STAMP_PIXELS] = np.frombuffer(stamp_bytes(frame_number, time_s, still=still), dtype=np.uint8)
    return image


def stamp_bmp_file(path: Path, frame_number: int, time_s: float, *, still: bool = True) -> bytes:
    """The bytes of the 8-bit BMP file at ``path`` with the stamp written into its top row.

    Patches the encoded file (a frame rendered ahead is stamped when it is put in place, without
    encoding it again): the pixel array starts at the header's offset, rows are padded to 4 bytes and
    stored bottom-up unless the height is negative.
    """
    data = bytearray(path.read_bytes())
    offset = struct.unpack_from("<I", data, 10)[0]
    width, height = struct.unpack_from("<ii", data, 18)
    bits = struct.unpack_from("<H", data, 28)[0]
    if bits != 8 or width < STAMP_PIXELS:
        raise ValueError(f"{path.name}: only 8-bit BMPs at least {STAMP_PIXELS} pixels wide take a stamp")
    stride = (width + 3) & ~3
    top = offset + (abs(height) - 1) * stride if height > 0 else offset
    data[top:top + STAMP_PIXELS] = stamp_bytes(frame_number, time_s, still=still)
    return bytes(data)
