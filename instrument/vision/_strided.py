"""Strided read-only views that let one fancy-index read gather many short runs of pixels."""

from __future__ import annotations

import numpy as np


def across_view(flat, width: int, step: int) -> np.ndarray:
    """Read-only view of a raveled frame whose row i is the ``width`` pixels from flat index i in
    steps of ``step`` (1: along an image row, the row length: down a column), so that one
    fancy-index read with N start indices gathers N cross-sections — no (N, width) index array.
    (A direct ndarray over the buffer: ``sliding_window_view`` costs more to set up than the read.)
    """
    rows = flat.size - (width - 1) * step
    view = np.ndarray((rows, width), flat.dtype, flat, 0, (flat.itemsize, step * flat.itemsize))
    view.flags.writeable = False
    return view
