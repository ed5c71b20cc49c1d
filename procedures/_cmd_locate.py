"""``instrument locate IMAGE...``: the sub-pixel cross in each image file."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def register(subparsers) -> None:
    parser = subparsers.add_parser("locate", help="locate the laser cross in image files")
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="8- or 16-bit greyscale image files")
    parser.add_argument("--json", action="store_true", help="one JSON object per image")
    parser.add_argument("--saturation", type=int, default=None, help="saturation level (default by dtype)")
    parser.set_defaults(handler=run)


def run(args) -> int:
    import cv2

    from instrument.vision import CrossNotFound, locate_cross

    status = 0
    for name in args.images:
        record: dict = {"image": name}
        img = cv2.imread(name, cv2.IMREAD_UNCHANGED) if Path(name).is_file() else None
        if img is None:
            record["error"] = "cannot read image file"
            status = 1
        else:
            if img.ndim == 3:  # a colour file of a grey image: take one channel
                img = np.ascontiguousarray(img[..., 0])
            try:
                m = locate_cross(img, saturation=args.saturation)
                record.update(
                    center_px=[float(m.center[0]), float(m.center[1])],
                    angle_rad=float(m.angle),
                    perpendicularity_rad=float(m.perpendicularity),
                    horizontal=_line(m.horizontal),
                    vertical=_line(m.vertical),
                )
            except (CrossNotFound, TypeError, ValueError) as exc:
                record["error"] = str(exc)
                status = 1
        if args.json:
            print(json.dumps(record))
        elif "error" in record:
            print(f"{name}: {record['error']}", file=sys.stderr)
        else:
            print(
                f"{name}: centre ({record['center_px'][0]:.4f}, {record['center_px'][1]:.4f}) px  "
                f"angle {np.degrees(record['angle_rad']):.5f}°  "
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
