"""Reading a frame stamp embedded in the first pixels of an image (``PylonSettings.embedded_stamp``).

A camera that embeds a stamp in its image (several industrial cameras can; the simulated cell's
camera file twin does, for pylon's emulator) says in the pixels themselves which frame it is and
when it was exposed. The layout (docs/cameras.md, "Embedded frame stamp"): the first 24 pixels of
the top row, one byte per pixel value — magic ``OPRS``, version 1, flags (bit 0: the frame shows a
scene still since the time), 2 reserved bytes, the frame number (u32), the time in seconds on the
host's wall clock (f64), and a CRC-32 of the 20 bytes before it (all little-endian).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

STAMP_PIXELS = 24
_LAYOUT = struct.Struct("<4sBBHIdI")


@dataclass(frozen=True)
class EmbeddedStamp:
    """A decoded frame stamp: the frame's number, a host wall-clock time (s), and what that time means
    (``still``: the scene shown has been still since then; otherwise the exposure's start)."""

    frame_number: int
    time: float
    still: bool


def read_stamp(image: np.ndarray) -> EmbeddedStamp | None:
    """The stamp in ``image``'s first top-row pixels, or None if there is none (or it is corrupt)."""
    if image.ndim != 2 or image.shape[1] < STAMP_PIXELS or image.shape[0] < 2:
        return None
    values = image[0, :STAMP_PIXELS]
    if np.any(values > 255):
        return None
    raw = values.astype(np.uint8).tobytes()
    magic, version, flags, _reserved, frame_number, time_s, crc = _LAYOUT.unpack(raw)
    if magic != b"OPRS" or version != 1 or crc != zlib.crc32(raw[:20]) or not np.isfinite(time_s):
        return None
    return EmbeddedStamp(int(frame_number), float(time_s), bool(flags & 0x01))


def without_stamp(image: np.ndarray) -> np.ndarray:
    """``image`` with the stamp's pixels replaced by the row below them (in place), so that the
    measurement never sees the stamp's bytes as light."""
    image[0, :STAMP_PIXELS] = image[1, :STAMP_PIXELS]
    return image
