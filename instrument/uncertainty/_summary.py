"""From Monte Carlo draws of a figure to its estimate, u, U and coverage interval.

The draws f* are the figure recomputed on the measured poses with the budget's errors added once
more. Their deviations stand in for the measured figure's own error, and their mean shift for its
bias (one SIMEX step, Cook & Stefanski 1994):

- signed figures (AP_x, AD, a drift difference): bias = mean f* − f, estimate f − bias,
  u = std f*;
- spreads and distances (RP, AP_P, RD, vAP, an RMS), f ≥ 0: the errors add to the *square*
  (RP_a² = 9·(S_r² + σ²); AP_P² gains σ²/n), so the step is taken on g = f²: ĝ = 2·f² − mean g*,
  estimate √ĝ; the interval ĝ ± k·std(g*) is mapped back through the square root and
  U = the larger of its two half-widths (so the interval stays ≥ 0 and U is not
  underestimated when noise is comparable to the figure, where std f* is too small by f*/f).
  u = U/k; for f ≫ U this is std(g*)/(2f), the delta method.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Summary:
    estimate: float  # bias-corrected
    bias: float  # measured value − estimate
    standard_uncertainty: float
    expanded_uncertainty: float
    interval: tuple[float, float]  # Monte Carlo coverage interval of the measurand


def summarise(value: float, samples: np.ndarray, k: float, probability: float, *, squared: bool) -> Summary:
    """Estimate, bias, u, U and interval of one figure from its draws (see the module docstring)."""
    tail = (1.0 - probability) / 2.0
    if not squared:
        u = float(np.std(samples, ddof=1))
        estimate = 2.0 * value - float(np.mean(samples))
        low, high = np.quantile(estimate - (samples - np.mean(samples)), [tail, 1.0 - tail])
        return Summary(estimate, value - estimate, u, k * u, (float(low), float(high)))
    squares = samples**2
    g_hat = max(2.0 * value**2 - float(np.mean(squares)), 0.0)
    estimate = math.sqrt(g_hat)
    expanded = spread_expanded(estimate, float(np.std(squares, ddof=1)), k)
    low, high = np.quantile(g_hat - (squares - np.mean(squares)), [tail, 1.0 - tail])
    interval = (math.sqrt(max(float(low), 0.0)), math.sqrt(max(float(high), 0.0)))
    return Summary(estimate, value - estimate, expanded / k, expanded, interval)


def spread_expanded(estimate: float, u_square: float, k: float) -> float:
    """U of a non-negative figure from the standard uncertainty of its square."""
    g_hat = estimate**2
    lower = estimate - math.sqrt(max(g_hat - k * u_square, 0.0))
    upper = math.sqrt(g_hat + k * u_square) - estimate
    return max(lower, upper)


def contribution(estimate: float, samples: np.ndarray, k: float, *, squared: bool) -> float:
    """One term's standard uncertainty from the draws with that term alone."""
    if not squared:
        return float(np.std(samples, ddof=1))
    return spread_expanded(estimate, float(np.std(samples**2, ddof=1)), k) / k
