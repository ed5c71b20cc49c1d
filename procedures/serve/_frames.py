"""The latest frame triple of a run, for the live page: images as PNG and the fitted stripe lines.

Two sources, newest first:

1. the **live frames** of a run, ``RUN_DIR/live/``: ``latest.json`` plus one small PNG per screen,
   written by ``write_live_frames`` after every pose (the engine calls it; see docs/web_view.md);
2. the frames the engine saves as ``.npy`` files (``save_frames: always``, or ``failed`` for the
   poses that failed), listed in each sample's ``frames``.

A cross is stored as the measurement core reports it (``procedures.station._science``): ``center_px`` (x, y),
``angle_rad`` = (φh + φv) / 2 and ``perpendicularity_rad`` = φv − φh, where φh turns the horizontal
stripe from +x toward +y and φv the vertical stripe from +y toward −x. The lines are drawn from these.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from instrument import SCREENS
from procedures.engine import DEFAULT_SCALE, LIVE_DIR, LIVE_INDEX, png_of
from procedures.store import Sample


def stripe_lines(cross: Mapping[str, Any], width: float, height: float) -> dict[str, Any]:
    """The two fitted stripe lines of a cross as segments across the image (px, full resolution).

    Returns ``{"center": [x, y], "horizontal": [[x0, y0], [x1, y1]], "vertical": [...]}``.
    """
    cx, cy = (float(v) for v in cross["center_px"])
    angle = float(cross.get("angle_rad") or 0.0)
    perpendicularity = float(cross.get("perpendicularity_rad") or 0.0)
    phi_h, phi_v = angle - perpendicularity / 2, angle + perpendicularity / 2
    reach = math.hypot(width, height)  # long enough to cross the whole image from the centre
    h = (math.cos(phi_h), math.sin(phi_h))
    v = (-math.sin(phi_v), math.cos(phi_v))
    return {
        "center": [cx, cy],
        "horizontal": [[cx - reach * h[0], cy - reach * h[1]], [cx + reach * h[0], cy + reach * h[1]]],
        "vertical": [[cx - reach * v[0], cy - reach * v[1]], [cx + reach * v[0], cy + reach * v[1]]],
    }


def _last_triple(files: Sequence[str]) -> dict[str, str]:
    """The newest saved file per screen (names end in ``_<screen>.npy``; later triples come later)."""
    triple: dict[str, str] = {}
    for name in files:
        for screen in SCREENS:
            if name.endswith(f"_{screen}.npy"):
                triple[screen] = name
    return triple


def latest_frames(run_dir: str | Path, samples: Sequence[Sample]) -> dict[str, Any] | None:
    """The newest frame triple of a run and its crosses and lines, or None when the run has none.

    ``{"step", "key", "source": "live" | "saved", "size": [w, h], "screens": {screen: {"file",
    "cross", "lines"}}}``; ``file`` is relative to the run folder.
    """
    run_dir = Path(run_dir)
    live = _read_live_index(run_dir)
    saved = next((s for s in sorted(samples, key=lambda s: s.step_index, reverse=True) if s.frames), None)
    if live is not None and (saved is None or live["step"] >= saved.step_index):
        size = live.get("size") or [0, 0]
        screens = {}
        for screen, name in (live.get("files") or {}).items():
            cross = (live.get("crosses") or {}).get(screen)
            screens[screen] = {"file": f"{LIVE_DIR}/{name}", "cross": cross,
                               "lines": stripe_lines(cross, *size) if cross else None}
        return {"step": live["step"], "key": live.get("key"), "source": "live", "size": size, "screens": screens}
    if saved is None:
        return None
    triple = _last_triple(saved.frames or [])
    if not triple:
        return None
    first = np.load(run_dir / next(iter(triple.values())), mmap_mode="r")
    size = [int(first.shape[1]), int(first.shape[0])]
    screens = {}
    for screen, name in triple.items():
        per_frame = (saved.crosses or {}).get(screen) or []
        cross = per_frame[-1] if per_frame else None
        screens[screen] = {"file": name, "cross": cross, "lines": stripe_lines(cross, *size) if cross else None}
    return {"step": saved.step_index, "key": saved.step_key, "source": "saved", "size": size, "screens": screens}


def _read_live_index(run_dir: Path) -> dict[str, Any] | None:
    try:
        index = json.loads((run_dir / LIVE_DIR / LIVE_INDEX).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return index if isinstance(index, dict) and isinstance(index.get("step"), int) else None


def frame_png(run_dir: str | Path, relative: str, scale: int = DEFAULT_SCALE) -> bytes:
    """The PNG of a frame file named by ``latest_frames`` (a live PNG as stored, a saved ``.npy`` reduced).

    Raises ``FileNotFoundError`` for anything outside the run's ``live/`` and ``frames/`` folders.
    """
    run_dir = Path(run_dir).resolve()
    path = (run_dir / relative).resolve()
    if path.parent not in (run_dir / LIVE_DIR, run_dir / "frames") or path.suffix not in (".png", ".npy"):
        raise FileNotFoundError(relative)
    if path.suffix == ".png":
        return path.read_bytes()
    return png_of(np.load(path), scale)
