"""Minimal inline SVG plots for the reports (no plotting library, no scripts, prints as vectors).

Two kinds: ``scatter`` (points, optionally at equal scales on both axes with circles drawn in data
units, e.g. the RP sphere) and ``lines`` (series against a common x, e.g. deviations per cycle).
The legend sits below the plot area, never over the data. Ticks carry their value in
``data-value`` so a test can read the drawn scale back.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from html import escape

import numpy as np
from numpy.typing import ArrayLike

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b")
LEFT, RIGHT, TOP, BOTTOM = 52, 10, 24, 34  # plot-area margins, px (the legend adds rows below)
LEGEND_ROW = 14


@dataclass(frozen=True)
class Circle:
    """A circle in data units (``label`` goes into the legend), e.g. the RP_l sphere about the barycentre."""

    cx: float
    cy: float
    radius: float
    label: str


def svg_text(text: str) -> str:
    """Escaped text for an SVG ``<text>``; ``RP_l`` is written with its subscript (``RP`` then ``l`` lowered)."""
    head, sep, tail = text.partition("_")
    if not sep or not tail:
        return escape(text)
    return (f'{escape(head)}<tspan dy="2.5" font-size="8">{escape(tail[0])}</tspan>'
            f'<tspan dy="-2.5">{escape(tail[1:])}</tspan>')


def _ticks(low: float, high: float, count: int = 5) -> list[float]:
    if not np.isfinite(low) or not np.isfinite(high) or high <= low:
        return [low]
    raw = (high - low) / count
    magnitude = 10 ** np.floor(np.log10(raw))
    step = min((m * magnitude for m in (1, 2, 5, 10) if m * magnitude >= raw), default=raw)
    first = np.ceil(low / step) * step
    return [float(v) + 0.0 for v in np.arange(first, high + step * 1e-9, step)]  # + 0.0: no "-0"


def _extent(values: np.ndarray, include_zero: bool) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    low, high = (float(finite.min()), float(finite.max())) if finite.size else (-1.0, 1.0)
    if include_zero:
        low, high = min(low, 0.0), max(high, 0.0)
    if high - low <= 0:
        low, high = low - 1.0, high + 1.0
    pad = (high - low) * 0.06
    return low - pad, high + pad


class _Frame:
    """The data → pixel mapping of one plot and the SVG of its frame, ticks, labels and legend."""

    def __init__(self, x_range: tuple[float, float], y_range: tuple[float, float], *, width: int, height: int,
                 legend_rows: int) -> None:
        self.width, self.height = width, height + legend_rows * LEGEND_ROW
        self.pw, self.ph = width - LEFT - RIGHT, height - TOP - BOTTOM
        (self.x0, self.x1), (self.y0, self.y1) = x_range, y_range

    def equalise(self) -> None:
        """Widen the smaller span so one data unit is as many pixels along x as along y."""
        per_px = max((self.x1 - self.x0) / self.pw, (self.y1 - self.y0) / self.ph)
        cx, cy = (self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2
        self.x0, self.x1 = cx - per_px * self.pw / 2, cx + per_px * self.pw / 2
        self.y0, self.y1 = cy - per_px * self.ph / 2, cy + per_px * self.ph / 2

    def px(self, x: float) -> float:
        return LEFT + (x - self.x0) / (self.x1 - self.x0) * self.pw

    def py(self, y: float) -> float:
        return TOP + (self.y1 - y) / (self.y1 - self.y0) * self.ph

    def open(self, title: str, xlabel: str, ylabel: str, *, zero_line: bool) -> list[str]:
        w, h, pw, ph = self.width, self.height, self.pw, self.ph
        parts = [f'<svg xmlns="http://www.w3.org/2000/svg" class="plot" width="{w}" height="{h}" '
                 f'viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="10">',
                 f'<text x="{w / 2}" y="14" text-anchor="middle" font-size="11">{escape(title)}</text>',
                 f'<rect x="{LEFT}" y="{TOP}" width="{pw}" height="{ph}" fill="none" stroke="#888"/>']
        for t in _ticks(self.x0, self.x1):
            parts.append(f'<g class="xtick" data-value="{t:.6g}" data-px="{self.px(t):.3f}">'
                         f'<line x1="{self.px(t):.1f}" y1="{TOP + ph}" x2="{self.px(t):.1f}" y2="{TOP + ph + 4}" '
                         f'stroke="#888"/><text x="{self.px(t):.1f}" y="{TOP + ph + 14}" '
                         f'text-anchor="middle">{t:.4g}</text></g>')
        for t in _ticks(self.y0, self.y1):
            parts.append(f'<g class="ytick" data-value="{t:.6g}" data-px="{self.py(t):.3f}">'
                         f'<line x1="{LEFT - 4}" y1="{self.py(t):.1f}" x2="{LEFT}" y2="{self.py(t):.1f}" '
                         f'stroke="#888"/><text x="{LEFT - 6}" y="{self.py(t) + 3:.1f}" '
                         f'text-anchor="end">{t:.4g}</text></g>')
        if zero_line and self.y0 < 0 < self.y1:
            parts.append(f'<line x1="{LEFT}" y1="{self.py(0):.1f}" x2="{LEFT + pw}" y2="{self.py(0):.1f}" '
                         'stroke="#ccc"/>')
        parts.append(f'<text x="{LEFT + pw / 2}" y="{TOP + ph + 27}" text-anchor="middle">{escape(xlabel)}</text>')
        parts.append(f'<text x="11" y="{TOP + ph / 2}" text-anchor="middle" '
                     f'transform="rotate(-90 11 {TOP + ph / 2})">{escape(ylabel)}</text>')
        return parts

    def legend(self, entries: Sequence[tuple[str, str, str]]) -> list[str]:
        """``(name, colour, mark)`` entries (mark: dot, ring or line) in rows below the x label."""
        parts, x, row = [], float(LEFT), 0
        for name, colour, mark in entries:
            width = 22 + 5.6 * len(name)
            if x + width > self.width - RIGHT and x > LEFT:
                x, row = float(LEFT), row + 1
            y = TOP + self.ph + BOTTOM + 4 + row * LEGEND_ROW
            if mark == "ring":
                parts.append(f'<circle cx="{x + 5}" cy="{y - 3}" r="4" fill="none" stroke="{colour}"/>')
            elif mark == "line":
                parts.append(f'<line x1="{x}" y1="{y - 3}" x2="{x + 10}" y2="{y - 3}" stroke="{colour}" '
                             'stroke-width="1.5"/>')
            else:
                parts.append(f'<circle cx="{x + 5}" cy="{y - 3}" r="3" fill="{colour}"/>')
            parts.append(f'<text x="{x + 14}" y="{y}">{svg_text(name)}</text>')
            x += width
        return parts


def _legend_rows(names: Sequence[str], width: int) -> int:
    rows, x = 1, float(LEFT)
    for name in names:
        w = 22 + 5.6 * len(name)
        if x + w > width - RIGHT and x > LEFT:
            rows, x = rows + 1, float(LEFT)
        x += w
    return rows if names else 0


def scatter(series: Sequence[tuple[str, ArrayLike, ArrayLike]], *, title: str, xlabel: str, ylabel: str,
            width: int = 300, height: int = 240, equal_aspect: bool = False, zero_line: bool = False,
            circles: Sequence[Circle] = ()) -> str:
    """An SVG scatter plot.

    Parameters
    ----------
    series : ``(name, xs, ys)`` per data set; units belong in the labels.
    title, xlabel, ylabel : text of the plot.
    width, height : size in px of the plot without its legend rows.
    equal_aspect : one data unit spans as many pixels along x as along y (for positions in a plane).
    zero_line : draw y = 0 and keep it in range.
    circles : circles in data units (drawn in outline, named in the legend), kept in range.

    Returns
    -------
    str
        One ``<svg>`` element.
    """
    xs = [np.asarray(s[1], float).ravel() for s in series]
    ys = [np.asarray(s[2], float).ravel() for s in series]
    all_x = np.concatenate(xs + [np.array([c.cx - c.radius, c.cx + c.radius]) for c in circles] or [np.zeros(1)])
    all_y = np.concatenate(ys + [np.array([c.cy - c.radius, c.cy + c.radius]) for c in circles] or [np.zeros(1)])
    names = [s[0] for s in series] + [c.label for c in circles]
    frame = _Frame(_extent(all_x, False), _extent(all_y, zero_line), width=width, height=height,
                   legend_rows=_legend_rows(names, width))
    if equal_aspect:
        frame.equalise()
    parts = frame.open(title, xlabel, ylabel, zero_line=zero_line)
    legend = []
    for i, (name, sx, sy) in enumerate(zip([s[0] for s in series], xs, ys)):
        colour = PALETTE[i % len(PALETTE)]
        dots = "".join(f'<circle cx="{frame.px(x):.1f}" cy="{frame.py(y):.1f}" r="2"/>'
                       for x, y in zip(sx, sy) if np.isfinite(x) and np.isfinite(y))
        parts.append(f'<g class="series" fill="{colour}" fill-opacity="0.7">{dots}</g>')
        legend.append((name, colour, "dot"))
    for j, c in enumerate(circles):
        colour = PALETTE[(len(series) + j) % len(PALETTE)]
        r_px = c.radius / (frame.x1 - frame.x0) * frame.pw
        parts.append(f'<circle class="circle" cx="{frame.px(c.cx):.3f}" cy="{frame.py(c.cy):.3f}" r="{r_px:.3f}" '
                     f'fill="none" stroke="{colour}" stroke-width="1.2" stroke-dasharray="4 2"/>')
        legend.append((c.label, colour, "ring"))
    parts += frame.legend(legend)
    parts.append("</svg>")
    return "".join(parts)


def lines(series: Sequence[tuple[str, ArrayLike, ArrayLike]], *, title: str, xlabel: str, ylabel: str,
          width: int = 300, height: int = 200, zero_line: bool = True) -> str:
    """An SVG line plot with a marker at every point (e.g. a deviation against the cycle number).

    Parameters
    ----------
    series : ``(name, xs, ys)`` per line; a non-finite value breaks the line.
    title, xlabel, ylabel : text of the plot.
    width, height : size in px of the plot without its legend rows.
    zero_line : draw y = 0 and keep it in range.

    Returns
    -------
    str
        One ``<svg>`` element.
    """
    xs = [np.asarray(s[1], float).ravel() for s in series]
    ys = [np.asarray(s[2], float).ravel() for s in series]
    frame = _Frame(_extent(np.concatenate(xs or [np.zeros(1)]), False),
                   _extent(np.concatenate(ys or [np.zeros(1)]), zero_line), width=width, height=height,
                   legend_rows=_legend_rows([s[0] for s in series], width))
    parts = frame.open(title, xlabel, ylabel, zero_line=zero_line)
    legend = []
    for i, (name, sx, sy) in enumerate(zip([s[0] for s in series], xs, ys)):
        colour = PALETTE[i % len(PALETTE)]
        runs: list[list[str]] = [[]]
        for x, y in zip(sx, sy):
            if np.isfinite(x) and np.isfinite(y):
                runs[-1].append(f"{frame.px(x):.1f},{frame.py(y):.1f}")
            elif runs[-1]:
                runs.append([])
        for run in runs:
            if len(run) > 1:
                parts.append(f'<polyline points="{" ".join(run)}" fill="none" stroke="{colour}" stroke-width="1"/>')
        dots = "".join(f'<circle cx="{p.split(",")[0]}" cy="{p.split(",")[1]}" r="1.6"/>' for run in runs for p in run)
        parts.append(f'<g class="series" fill="{colour}">{dots}</g>')
        legend.append((name, colour, "line"))
    parts += frame.legend(legend)
    parts.append("</svg>")
    return "".join(parts)
