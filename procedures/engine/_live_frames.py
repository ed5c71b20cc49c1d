"""The live frames of a run: the latest frame triple, small, written by the engine after every pose.

``RUN_DIR/live/`` holds one PNG per screen (reduced ``scale`` times) and ``latest.json`` (the step,
the image size and the located crosses). The web view (``procedures.serve``) reads them; this module
is the writer, kept apart from the web stack so the engine loads no web framework.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

LIVE_DIR = "live"
LIVE_INDEX = "latest.json"
DEFAULT_SCALE = 4  # 1024 × 1040 px → 256 × 260 px: a phone shows three of them side by side


def _to_8bit(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3:
        image = image[..., 0] if image.shape[2] == 1 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if image.dtype == np.uint8:
        return image
    top = float(image.max()) if image.size else 0.0
    return (image.astype(np.float64) * (255.0 / top if top > 0 else 0.0)).astype(np.uint8)


def png_of(image: np.ndarray, scale: int = DEFAULT_SCALE) -> bytes:
    """A grey image reduced ``scale`` times (area average, so a thin stripe stays visible) as PNG bytes."""
    grey = _to_8bit(image)
    height, width = grey.shape[:2]
    small = cv2.resize(grey, (max(1, width // scale), max(1, height // scale)), interpolation=cv2.INTER_AREA)
    ok, encoded = cv2.imencode(".png", small)
    if not ok:
        raise ValueError("PNG encoding failed")
    return bytes(encoded.tobytes())


def write_live_frames(run_dir: str | Path, step: int, key: str, images: Mapping[str, np.ndarray],
                      crosses: Mapping[str, Mapping[str, Any] | None] | None = None, *,
                      scale: int = DEFAULT_SCALE) -> Path | None:
    """Publish one frame triple as the run's live frames (``RUN_DIR/live/``); returns the index file.

    Parameters
    ----------
    run_dir : the run's folder (``RunStore.run_dir(run_id)``)
    step, key : the step the frames belong to
    images : per screen (``x``, ``y``, ``z``) the grey image as grabbed
    crosses : per screen the located cross (``PoseMeasurement.crosses[screen]``), or None where none was found
    scale : reduction of the stored PNGs

    The PNGs get the step in their names and ``latest.json`` is replaced atomically after them, so a
    reader never pairs one pose's lines with another pose's image; older PNGs are then removed.
    A failure to write is swallowed (None returned): a live view must never stop a measurement.
    """
    try:
        folder = Path(run_dir) / LIVE_DIR
        folder.mkdir(parents=True, exist_ok=True)
        files, size = {}, None
        for screen, image in images.items():
            name = f"{step:05d}_{screen}.png"
            (folder / name).write_bytes(png_of(image, scale))
            files[screen] = name
            size = [int(np.shape(image)[1]), int(np.shape(image)[0])]
        index = {"step": int(step), "key": key, "time": time.time(), "size": size, "scale": scale, "files": files,
                 "crosses": {s: (dict(c) if c else None) for s, c in (crosses or {}).items()}}
        temporary = folder / (LIVE_INDEX + ".tmp")
        temporary.write_text(json.dumps(index), encoding="utf-8")
        os.replace(temporary, folder / LIVE_INDEX)
        for old in folder.glob("*.png"):
            if old.name not in files.values():
                old.unlink(missing_ok=True)
        return folder / LIVE_INDEX
    except (OSError, ValueError, TypeError):
        return None
