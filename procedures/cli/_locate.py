"""``instrument locate IMAGE...``: the sub-pixel cross in each image file.

Image files are not trusted: only regular files of at most ``MAX_IMAGE_BYTES`` are read, and an
image is decoded only when its header declares at most ``MAX_IMAGE_PIXELS`` pixels (a small
compressed file can claim a huge image: a 0.9 MB PNG can declare 30000 × 30000). The declared size
is read from the header itself (PNG, BMP, TIFF, JPEG, PNM) before OpenCV sees a byte: OpenCV's own
limit (``OPENCV_IO_MAX_IMAGE_PIXELS``) is read once, when OpenCV loads, so it guards nothing in a
process that imported cv2 first. Other formats are refused. A file that cannot be read, decoded or
measured is one line naming it (exit status 1).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import stat
import struct
import sys
from collections.abc import Iterator

MAX_IMAGE_BYTES = 256 * 1024 * 1024
MAX_IMAGE_PIXELS = 64 * 1024 * 1024  # 8k × 8k; the cameras give 1024×1040 and 2448×2048


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "locate", help="locate the laser cross in image files",
        description="The sub-pixel centre, angle and line fits of the laser cross in each image file.",
        epilog="exit codes: 0 a cross in every image, 1 an image could not be read or has no cross (one line "
               "each), 2 bad arguments")
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="8- or 16-bit greyscale image files")
    parser.add_argument("--json", action="store_true", help="one JSON object per image")
    parser.add_argument("--saturation", type=int, default=None,
                        help="grey level counted as saturated (default: the image type's maximum)")
    parser.set_defaults(handler=run)


@contextlib.contextmanager
def _native_stderr_quiet() -> Iterator[None]:
    """Silence what C libraries write to file descriptor 2 meanwhile (Python's own stderr is kept)."""
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


HEADER_BYTES = 64 * 1024  # read to find the declared size (a JPEG's frame header may follow its metadata)
_PNM_MAGIC = (b"P1", b"P2", b"P3", b"P4", b"P5", b"P6", b"P7", b"Pf", b"PF")


def _pnm_size(data: bytes) -> tuple[int, int] | None:
    if data[:2] == b"P7":  # PAM: WIDTH and HEIGHT lines
        fields = dict(line.split(None, 1) for line in data.split(b"ENDHDR")[0].splitlines()[1:]
                      if len(line.split(None, 1)) == 2 and not line.startswith(b"#"))
        try:
            return int(fields[b"WIDTH"]), int(fields[b"HEIGHT"])
        except (KeyError, ValueError):
            return None
    tokens: list[bytes] = []
    for line in data[2:].splitlines():  # whitespace-separated numbers, '#' comments to the end of a line
        tokens += line.split(b"#", 1)[0].split()
        if len(tokens) >= 2:
            break
    try:
        return int(tokens[0]), int(tokens[1])
    except (IndexError, ValueError):
        return None


def _tiff_size(data: bytes) -> tuple[int, int] | None:
    order = "<" if data[:2] == b"II" else ">"
    try:
        (version,) = struct.unpack_from(order + "H", data, 2)
        if version == 42:
            (offset,) = struct.unpack_from(order + "I", data, 4)
            (count,) = struct.unpack_from(order + "H", data, offset)
            entry, first, size_of = "HHI4s", offset + 2, 12
        elif version == 43:  # BigTIFF
            (offset,) = struct.unpack_from(order + "Q", data, 8)
            (count,) = struct.unpack_from(order + "Q", data, offset)
            entry, first, size_of = "HHQ8s", offset + 8, 20
        else:
            return None
        found: dict[int, int] = {}
        for i in range(min(count, 4096)):
            tag, kind, _, value = struct.unpack_from(order + entry, data, first + i * size_of)
            if tag in (256, 257):  # ImageWidth, ImageLength: SHORT, LONG or LONG8
                code = {3: "H", 4: "I", 16: "Q"}.get(kind)
                if code is None:
                    return None
                (found[tag],) = struct.unpack_from(order + code, value)
        return (found[256], found[257]) if len(found) == 2 else None
    except (struct.error, KeyError):
        return None  # the first directory lies beyond what was read, or is cut short


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            return None
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length
            at += 2
            continue
        (length,) = struct.unpack_from(">H", data, at + 2)
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # a start of frame
            if at + 9 > len(data):
                return None
            height, width = struct.unpack_from(">HH", data, at + 5)
            return width, height
        at += 2 + length
    return None


def declared_image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) an image file's header declares, from its first bytes; None when the format is not
    one of PNG, BMP, TIFF, JPEG, PNM or the header is unreadable."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        if len(data) < 24 or data[12:16] != b"IHDR":
            return None
        width, height = struct.unpack_from(">II", data, 16)
        return width, height
    if data[:2] == b"BM" and len(data) >= 26:
        (header_size,) = struct.unpack_from("<I", data, 14)
        if header_size == 12:  # BITMAPCOREHEADER: 16-bit sizes
            width, height = struct.unpack_from("<hh", data, 18)
        else:
            width, height = struct.unpack_from("<ii", data, 18)
        return abs(width), abs(height)  # a negative height is a top-down bitmap
    if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return _tiff_size(data)
    if data[:2] == b"\xff\xd8":
        return _jpeg_size(data)
    if data[:2] in _PNM_MAGIC:
        return _pnm_size(data)
    return None


def size_refusal(data: bytes) -> str | None:
    """Why an image file with these first bytes is not decoded (one line), or None when it may be."""
    size = declared_image_size(data)
    if size is None:
        return ("cannot read the image size from its header (not a PNG, BMP, TIFF, JPEG or PNM file, or "
                "cut short): not decoded")
    width, height = size
    if width * height > MAX_IMAGE_PIXELS:
        return (f"image declares {width}×{height} pixels ({width * height} pixels); at most {MAX_IMAGE_PIXELS} "
                "are decoded: not decoded")
    return None


def _read_image(name: str):
    """The image in file ``name`` (a numpy array), or the reason there is none (a string)."""
    import cv2
    import numpy as np

    try:
        info = os.stat(name)
    except OSError:
        return "cannot read image file"
    if not stat.S_ISREG(info.st_mode):
        return "not a regular file (a folder, FIFO or device)"
    if info.st_size > MAX_IMAGE_BYTES:
        return f"image file of {info.st_size} bytes; at most {MAX_IMAGE_BYTES} are read"
    try:
        data = np.fromfile(name, dtype=np.uint8, count=MAX_IMAGE_BYTES + 1)
    except OSError:
        return "cannot read image file"
    refusal = size_refusal(data[:HEADER_BYTES].tobytes())
    if refusal is not None:
        return refusal
    try:
        with _native_stderr_quiet():  # libpng & co. print their own complaint; ours is the one line
            image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    except (OSError, cv2.error) as exc:
        return f"cannot decode image file: {(str(exc).strip().splitlines() or [type(exc).__name__])[-1]}"
    if image is None:
        return "cannot decode image file (not an image format OpenCV reads, or cut short)"
    if image.ndim == 3:  # a colour file of a grey image: take one channel
        image = np.ascontiguousarray(image[..., 0])
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        return f"expected an 8- or 16-bit greyscale image, got {image.dtype} with shape {image.shape}"
    return image


def run(args) -> int:
    # A second guard only: OpenCV reads this once, when cv2 loads (here, if nothing imported it before); the
    # header check in _read_image is what refuses a decompression bomb in any process.
    os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS))
    from instrument.vision import CrossNotFound, locate_cross

    status = 0
    for name in args.images:
        record: dict = {"image": name}
        img = _read_image(name)
        if isinstance(img, str):
            record["error"] = img
            status = 1
        else:
            try:
                m = locate_cross(img, saturation=args.saturation)
                record.update(
                    center_px=[float(m.center[0]), float(m.center[1])],
                    angle_rad=float(m.angle),
                    perpendicularity_rad=float(m.perpendicularity),
                    horizontal=_line(m.horizontal),
                    vertical=_line(m.vertical),
                )
            except (CrossNotFound, TypeError, ValueError, ArithmeticError) as exc:
                record["error"] = str(exc) or type(exc).__name__
                status = 1
        if args.json:
            print(json.dumps(record))
        elif "error" in record:
            print(f"{name}: {record['error']}", file=sys.stderr)
        else:
            print(
                f"{name}: centre ({record['center_px'][0]:.4f}, {record['center_px'][1]:.4f}) px  "
                f"angle {math.degrees(record['angle_rad']):.5f}°  "
                f"sections {record['horizontal']['sections']}/{record['vertical']['sections']}  "
                f"rms {record['horizontal']['residual_rms_px']:.4f}/{record['vertical']['residual_rms_px']:.4f} px  "
                f"saturated {record['horizontal']['saturated_sections']}/{record['vertical']['saturated_sections']}"
            )
    return status


def _line(line) -> dict:
    return {
        "point_px": [float(v) for v in line.point],
        "direction": [float(v) for v in line.direction],
        "sections": int(line.sections),
        "residual_rms_px": float(line.residual_rms),
        "saturated_sections": int(line.saturated_sections),
    }
