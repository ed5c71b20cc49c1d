"""Confidence intervals for the ISO figures.

- RP_a, RP_b, RP_c (= 3·S): the exact chi-square interval for a normal standard deviation,
  3·S·sqrt((n−1)/χ²_{1−α/2, n−1}) … 3·S·sqrt((n−1)/χ²_{α/2, n−1}).
- AP_a, AP_b, AP_c (= mean − commanded): Student's t interval, ± t_{1−α/2, n−1}·S/√n.
- RP_l (= l̄ + 3·S_l) has no closed form: a studentized (bootstrap-t) interval. The poses are
  resampled with replacement (barycentre recomputed in each resample); each resample's RP_l is
  standardised by its delta-method standard error
  se² = (S² + 9·(m4 − S⁴)/(4·S²) + 3·m3/S) / n  (m3, m4: central moments of the l_j),
  and the interval is RP_l − t*_{hi}·se … RP_l − t*_{lo}·se. A resample drawn with many
  duplicates has a standard error far below the sample's, and dividing by it puts the long tail
  of t* into the interval (upper bounds at 2.7× RP_l were seen); so each resample's standard
  error is floored at ``SE_FLOOR`` × the sample's. For n = 30 Gaussian scatter (600 seeded
  trials) the coverage of the population value μ_l + 3·σ_l is 0.93 at a nominal 0.95 (0.94
  without the floor), and the 95th percentile of the interval's width is 0.58·RP_l (0.83 without
  it). The plain percentile bootstrap reaches only ≈ 0.80 (it inherits the estimator's downward
  bias); a delta-method normal interval or BCa ≈ 0.87.
- AP_P (the distance of the barycentre from the commanded point): a percentile bootstrap; good
  when AP_P is several times the barycentre's own scatter (S/√n), conservative-to-biased near 0.

Every bootstrap draws ``samples`` resamples from a generator seeded by ``seed``: reproducible.
"""

from __future__ import annotations

import numpy as np

from instrument.iso9283._errors import ISO9283Error

SE_FLOOR = 0.7  # smallest resample standard error, as a fraction of the sample's (see above)


def check_confidence(confidence: float, n: int) -> float:
    confidence = float(confidence)
    if not 0.0 < confidence < 1.0:
        raise ISO9283Error(f"confidence: expected a level in (0, 1), e.g. 0.95, got {confidence}")
    if n < 3:
        raise ISO9283Error(f"confidence intervals need at least 3 attained poses, got {n}")
    return confidence


def chi_square_interval(three_sigma: float, n: int, confidence: float) -> tuple[float, float]:
    from scipy import stats
    alpha = 1.0 - confidence
    dof = n - 1
    return (
        float(three_sigma * np.sqrt(dof / stats.chi2.ppf(1.0 - alpha / 2.0, dof))),
        float(three_sigma * np.sqrt(dof / stats.chi2.ppf(alpha / 2.0, dof))),
    )


def t_interval(mean: float, std: float, n: int, confidence: float) -> tuple[float, float]:
    from scipy import stats
    half = float(stats.t.ppf(0.5 + confidence / 2.0, n - 1) * std / np.sqrt(n))
    return (mean - half, mean + half)


def bootstrap_resamples(positions: np.ndarray, samples: int, seed: int) -> np.ndarray:
    """(samples, n, 3) resampled position sets."""
    if int(samples) < 100:
        raise ISO9283Error(f"bootstrap_samples: at least 100 needed for a percentile interval, got {samples}")
    rng = np.random.default_rng(seed)
    indices = rng.integers(0, len(positions), size=(int(samples), len(positions)))
    return positions[indices]


def percentile_interval(values: np.ndarray, confidence: float) -> tuple[float, float]:
    alpha = 1.0 - confidence
    low, high = np.quantile(values, [alpha / 2.0, 1.0 - alpha / 2.0])
    return (float(low), float(high))


def rp_l_of(positions: np.ndarray) -> np.ndarray:
    """RP_l of each set in a (..., n, 3) stack."""
    return rp_l_with_standard_error(positions)[0]


def rp_l_with_standard_error(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RP_l and its delta-method standard error for each set in a (..., n, 3) stack."""
    deviations = positions - positions.mean(axis=-2, keepdims=True)
    distances = np.sqrt((deviations**2).sum(axis=-1))
    n = distances.shape[-1]
    mean = distances.mean(axis=-1)
    std = distances.std(axis=-1, ddof=1)
    centred = distances - mean[..., None]
    m3 = (centred**3).mean(axis=-1)
    m4 = (centred**4).mean(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        variance = (std**2 + 9.0 * (m4 - std**4) / (4.0 * std**2) + 3.0 * m3 / std) / n
    # In small samples a strongly negative m3 can drive the estimate to zero or below (about 4 % of
    # n = 5 Gaussian sets), which would collapse the interval to a point; the variance of l̄ alone,
    # S²/n, is then the honest floor. All poses identical still gives 0.
    variance = np.where(variance > 0.0, variance, std**2 / n)
    return mean + 3.0 * std, np.sqrt(np.clip(np.nan_to_num(variance, nan=0.0), 0.0, None))


def rp_l_interval(positions: np.ndarray, confidence: float, samples: int, seed: int) -> tuple[float, float]:
    """Bootstrap-t interval of RP_l (see the module docstring)."""
    estimate, standard_error = (float(v) for v in rp_l_with_standard_error(positions))
    if standard_error == 0.0:  # all poses identical (or symmetric to rounding): nothing to resample
        return (estimate, estimate)
    boot, boot_se = rp_l_with_standard_error(bootstrap_resamples(positions, samples, seed))
    t_low, t_high = percentile_interval((boot - estimate) / np.maximum(boot_se, SE_FLOOR * standard_error),
                                        confidence)
    return (max(estimate - t_high * standard_error, 0.0), estimate - t_low * standard_error)
