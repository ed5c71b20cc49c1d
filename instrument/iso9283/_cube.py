"""The ISO 9283 test cube and its five test poses (method.md §5).

Corners, in the cube's own axes (half edge h): C1 (−h, −h, −h), C2 (+h, −h, −h), C3 (+h, +h, −h),
C4 (−h, +h, −h), and C5…C8 above C1…C4 (z = +h). The plane C1-C2-C7-C8 is the diagonal plane
y = z through two opposite edges. P1 is the centre; P2, P3, P4, P5 lie on the plane's diagonals
C1–C7 and C2–C8 at ``fraction`` (10 %) of the diagonal's length from C1, C2, C7, C8 respectively,
i.e. at centre + (1 − 2·fraction)·(corner − centre). (This corner labelling is our convention;
ISO 9283's figure is not reproduced here.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from instrument.iso9283._errors import ISO9283Error

VISITING_ORDER = ("P1", "P5", "P4", "P3", "P2")  # the paper's cycle; the next cycle starts at P1 again
_CORNER_SIGNS = {
    "C1": (-1, -1, -1),
    "C2": (1, -1, -1),
    "C3": (1, 1, -1),
    "C4": (-1, 1, -1),
    "C5": (-1, -1, 1),
    "C6": (1, -1, 1),
    "C7": (1, 1, 1),
    "C8": (-1, 1, 1),
}
_TEST_CORNERS = {"P2": "C1", "P3": "C2", "P4": "C7", "P5": "C8"}


@dataclass(frozen=True)
class IsoCube:
    """The test cube: ``points`` P1…P5 and ``corners`` C1…C8 in the working frame (m)."""

    center: np.ndarray
    edge: float
    rotation: np.ndarray
    corners: dict[str, np.ndarray]
    points: dict[str, np.ndarray]
    order: tuple[str, ...] = VISITING_ORDER

    def cycle(self, cycles: int) -> list[str]:
        """Names of the points visited in ``cycles`` cycles: P1 → P5 → P4 → P3 → P2, repeated."""
        return [name for _ in range(int(cycles)) for name in self.order]

    def positions_in_order(self) -> np.ndarray:
        """(5, 3) positions in visiting order."""
        return np.array([self.points[name] for name in self.order])


def iso_cube_points(center, edge: float, rotation=None, *, fraction: float = 0.1) -> IsoCube:
    """The ISO 9283 test points of a cube of edge ``edge`` (m) centred at ``center``.

    Parameters
    ----------
    center : (3,) array, m
    edge : float, m (> 0)
    rotation : (3, 3) array, optional
        Orientation of the cube's axes in the working frame (identity by default).
    fraction : float
        Distance of P2…P5 from their corners as a fraction of the diagonal (ISO: 0.10 ± 0.02).
    """
    centre = np.asarray(center, dtype=float).reshape(-1)
    if centre.shape != (3,) or not np.all(np.isfinite(centre)):
        raise ISO9283Error(f"center: expected 3 finite numbers (m), got {center!r}")
    if not (np.isfinite(edge) and edge > 0):
        raise ISO9283Error(f"edge: expected a positive length (m), got {edge!r}")
    if not 0.0 < fraction < 0.5:
        raise ISO9283Error(f"fraction: expected a value in (0, 0.5), ISO uses 0.1, got {fraction!r}")
    axes = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
    if axes.shape != (3, 3) or not np.allclose(axes @ axes.T, np.eye(3), atol=1e-9) or np.linalg.det(axes) < 0:
        raise ISO9283Error("rotation: expected a proper 3×3 rotation matrix")
    half = edge / 2.0
    corners = {name: centre + axes @ (half * np.array(signs, dtype=float)) for name, signs in _CORNER_SIGNS.items()}
    points = {"P1": centre.copy()}
    for name, corner in _TEST_CORNERS.items():
        points[name] = centre + (1.0 - 2.0 * fraction) * (corners[corner] - centre)
    return IsoCube(centre, float(edge), axes, corners, dict(sorted(points.items())))
