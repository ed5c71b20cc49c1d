"""Minimal inline SVG scatter plots (no plotting library needed in the report)."""

from __future__ import annotations

from collections.abc import Sequence
from html import escape

import numpy as np
from numpy.typing import ArrayLike

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b")


def _ticks(low: float, high: float, count: int = 5) -> list[float]:
    if not np.isfinite(low) or not np.isfinite(high) or high <= low:
        return [low]
    raw = (high - low) / count
    magnitude = 10 ** np.floor(np.log10(raw))
    step = min((m * magnitude for m in (1, 2, 5, 10) if m * magnitude >= raw), default=raw)
    first = np.ceil(low / step) * step
    return [float(v) for v in np.arange(first, high + step * 1e-9, step)]


def scatter(series: Sequence[tuple[str, ArrayLike, ArrayLike]], *, title: str, xlabel: str, ylabel: str,
            width: int = 420, height: int = 300, square: bool = False, zero_line: bool = False) -> str:
    """An SVG scatter plot. ``series`` is a list of ``(name, xs, ys)``; units belong in the labels."""
    left, right, top, bottom = 64, 12, 28, 44
    xs = np.concatenate([np.asarray(s[1], float) for s in series]) if series else np.zeros(1)
    ys = np.concatenate([np.asarray(s[2], float) for s in series]) if series else np.zeros(1)
    finite = np.isfinite(xs) & np.isfinite(ys)
    xs, ys = (xs[finite], ys[finite]) if finite.any() else (np.zeros(1), np.zeros(1))
    x0, x1, y0, y1 = xs.min(), xs.max(), ys.min(), ys.max()
    if zero_line:
        y0, y1 = min(y0, 0.0), max(y1, 0.0)
    if square:
        half = max(x1 - x0, y1 - y0) / 2 or 1.0
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        x0, x1, y0, y1 = cx - half, cx + half, cy - half, cy + half
    padx, pady = (x1 - x0) * 0.06 or 1.0, (y1 - y0) * 0.06 or 1.0
    x0, x1, y0, y1 = x0 - padx, x1 + padx, y0 - pady, y1 + pady
    pw, ph = width - left - right, height - top - bottom

    def px(x: float) -> float:
        return left + (x - x0) / (x1 - x0) * pw

    def py(y: float) -> float:
        return top + (y1 - y) / (y1 - y0) * ph

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
             f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="10">',
             f'<text x="{width / 2}" y="16" text-anchor="middle" font-size="12">{escape(title)}</text>',
             f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="none" stroke="#888"/>']
    for t in _ticks(x0, x1):
        parts.append(f'<line x1="{px(t):.1f}" y1="{top + ph}" x2="{px(t):.1f}" y2="{top + ph + 4}" stroke="#888"/>'
                     f'<text x="{px(t):.1f}" y="{top + ph + 15}" text-anchor="middle">{t:.4g}</text>')
    for t in _ticks(y0, y1):
        parts.append(f'<line x1="{left - 4}" y1="{py(t):.1f}" x2="{left}" y2="{py(t):.1f}" stroke="#888"/>'
                     f'<text x="{left - 6}" y="{py(t) + 3:.1f}" text-anchor="end">{t:.4g}</text>')
    if zero_line and y0 < 0 < y1:
        parts.append(f'<line x1="{left}" y1="{py(0):.1f}" x2="{left + pw}" y2="{py(0):.1f}" stroke="#ccc"/>')
    parts.append(f'<text x="{left + pw / 2}" y="{height - 8}" text-anchor="middle">{escape(xlabel)}</text>')
    parts.append(f'<text x="12" y="{top + ph / 2}" text-anchor="middle" '
                 f'transform="rotate(-90 12 {top + ph / 2})">{escape(ylabel)}</text>')
    for i, (name, sx, sy) in enumerate(series):
        color = PALETTE[i % len(PALETTE)]
        for x, y in zip(np.asarray(sx, float), np.asarray(sy, float)):
            if np.isfinite(x) and np.isfinite(y):
                parts.append(f'<circle cx="{px(x):.1f}" cy="{py(y):.1f}" r="2.2" fill="{color}" fill-opacity="0.7"/>')
        parts.append(f'<circle cx="{left + 8}" cy="{top + 10 + 13 * i}" r="3" fill="{color}"/>'
                     f'<text x="{left + 15}" y="{top + 13 + 13 * i}">{escape(name)}</text>')
    parts.append("</svg>")
    return "".join(parts)
