"""``instrument locate IMAGE...``: the sub-pixel cross in each image file.

Image files are not trusted: only regular files of at most ``MAX_IMAGE_BYTES`` are read, and
OpenCV may decode at most ``MAX_IMAGE_PIXELS`` pixels (a small compressed file can claim a huge
image). A file that cannot be read, decoded or measured is one line naming it (exit status 1).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import stat
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
    # Read by OpenCV when it first decodes: a decompression bomb is refused, not allocated.
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
