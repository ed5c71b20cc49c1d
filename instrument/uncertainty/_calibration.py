"""Uncertainty of a calibration's residual: the RMS of the compensated error against the reference.

The reported figure is r = RMS(corrected − reference) over the held-out observations of one
component. The reference has its own error: per-reading noise (independent per observation) and
a scale error (common, times the reference value from its datum). Measured against a noisy
reference, r is inflated (r² ≈ r_true² + σ_ref²); the Monte Carlo adds the reference's errors
once more, and, as for the ISO figures (``_summary``), one step back in the square removes that
bias (√(2·r² − mean r*²)) and the spread of r*² gives U.
The sampling interval (which calibration points happened to be measured) is a cluster bootstrap
over the calibration points, percentile, seeded.
"""

from __future__ import annotations

import math

import numpy as np

from instrument.uncertainty._budget import COMPONENTS, Distribution
from instrument.uncertainty._errors import UncertaintyError
from instrument.uncertainty._propagate import FigureUncertainty
from instrument.uncertainty._sampling import unit_draws
from instrument.uncertainty._summary import contribution, summarise

BOOTSTRAP_SAMPLES = 2000


def calibration_residual_uncertainty(
    residuals,
    reference,
    points,
    *,
    component: str,
    reference_noise: float = 0.0,
    reference_scale: float = 0.0,
    scale_distribution: Distribution | str = Distribution.RECTANGULAR,
    datum: float = 0.0,
    draws: int = 4000,
    seed: int = 0,
    coverage_factor: float = 2.0,
    confidence: float = 0.95,
    true_residuals=None,
    characteristic: float | None = None,
) -> FigureUncertainty:
    """RMS of a calibration's (held-out) residuals with its uncertainty from the reference.

    Parameters
    ----------
    residuals : (N,) corrected − reference for each held-out observation (m or rad)
    reference : (N,) the reference's readings (for its scale error)
    points : (N,) calibration point of each observation (the bootstrap resamples whole points)
    component : "x", "y", "z", "a", "b" or "c"
    reference_noise : standard uncertainty of one reference reading (m or rad)
    reference_scale : relative standard uncertainty of the reference's scale
    scale_distribution : its distribution (a specification ±a is rectangular)
    datum : where the reference reads true (its zero)
    draws, seed : Monte Carlo draws and seed
    coverage_factor : k (2)
    confidence : level of the sampling interval
    true_residuals : (N,) corrected − true value (simulation), optional: fills ``true``
    characteristic : for the 25 % rule (e.g. the target 1.5 µm); default the value itself

    Returns
    -------
    FigureUncertainty
        name ``residual_rms_<component>``; contributions "reference noise" and "reference scale".
    """
    from scipy import special
    if component not in COMPONENTS:
        raise UncertaintyError(f"component: expected one of x, y, z, a, b, c, got {component!r}")
    r = _vector(residuals, "residuals")
    ref = _vector(reference, "reference", len(r))
    labels = np.asarray(points).reshape(-1)
    if labels.shape != r.shape:
        raise UncertaintyError(f"points: expected {len(r)} labels, got {labels.size}")
    if not (reference_noise >= 0 and reference_scale >= 0):
        raise UncertaintyError("reference_noise and reference_scale: expected ≥ 0")
    if int(draws) < 50:
        raise UncertaintyError(f"draws: expected ≥ 50, got {draws}")
    distribution = Distribution(scale_distribution)
    value = float(np.sqrt(np.mean(r**2)))

    def simulate(noise: float, scale: float, rng: np.random.Generator) -> np.ndarray:
        shifted = r[None, :] + noise * rng.standard_normal((int(draws), len(r)))
        shifted += scale * unit_draws(distribution, (int(draws), 1), rng) * (ref - datum)[None, :]
        return np.sqrt(np.mean(shifted**2, axis=1))

    samples = simulate(reference_noise, reference_scale, np.random.default_rng(seed))
    probability = float(special.erf(coverage_factor / math.sqrt(2.0)))
    summary = summarise(value, samples, coverage_factor, probability, squared=True)
    contributions = {
        name: contribution(summary.estimate, simulate(noise, scale, np.random.default_rng([seed, index])),
                           coverage_factor, squared=True)
        for index, (name, noise, scale) in enumerate((("reference noise", reference_noise, 0.0),
                                                      ("reference scale", 0.0, reference_scale)), start=1)
    }
    true = None
    if true_residuals is not None:
        true = float(np.sqrt(np.mean(_vector(true_residuals, "true_residuals", len(r)) ** 2)))
    return FigureUncertainty(
        name=f"residual_rms_{component}", unit="m" if component in "xyz" else "rad", value=summary.estimate,
        expanded_uncertainty=summary.expanded_uncertainty, coverage_factor=float(coverage_factor),
        standard_uncertainty=summary.standard_uncertainty, uncorrected_value=value, noise_bias=summary.bias,
        bias_corrected=True, contributions=contributions,
        confidence_interval=_cluster_interval(r, labels, confidence, seed), mc_interval=summary.interval,
        characteristic=summary.estimate if characteristic is None else float(characteristic), true=true)


def _cluster_interval(r: np.ndarray, labels: np.ndarray, confidence: float, seed: int) -> tuple[float, float] | None:
    """Percentile interval of the RMS when whole calibration points are resampled."""
    if not 0 < confidence < 1:
        raise UncertaintyError(f"confidence: expected a level in (0, 1), got {confidence}")
    _, index = np.unique(labels, return_inverse=True)
    groups = index.max() + 1
    if groups < 3:
        return None
    sums = np.bincount(index, weights=r**2, minlength=groups)
    counts = np.bincount(index, minlength=groups)
    picks = np.random.default_rng([seed, 3]).integers(0, groups, size=(BOOTSTRAP_SAMPLES, groups))
    rms = np.sqrt(sums[picks].sum(axis=1) / counts[picks].sum(axis=1))
    alpha = 1.0 - confidence
    low, high = np.quantile(rms, [alpha / 2.0, 1.0 - alpha / 2.0])
    return float(low), float(high)


def _vector(values, name: str, length: int | None = None) -> np.ndarray:
    try:
        array = np.asarray(values, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise UncertaintyError(f"{name}: expected numbers") from None
    if array.size == 0 or not np.all(np.isfinite(array)):
        raise UncertaintyError(f"{name}: expected finite values, at least one")
    if length is not None and array.size != length:
        raise UncertaintyError(f"{name}: expected {length} values, got {array.size}")
    return array
