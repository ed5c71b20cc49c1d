"""Errors of ``instrument.pose``: one family, each message names the screen or field at fault."""

from __future__ import annotations


class PoseError(ValueError):
    """Base class: the inputs cannot give a trustworthy pose. The message says why."""


class GeometryError(PoseError):
    """The screen geometry (station file ``geometry``) is malformed; the message names the field."""


class MissingScreenError(PoseError):
    """A screen's cross measurement (or its geometry) is absent."""


class CrossOffScreenError(PoseError):
    """The cross centre lies outside the camera's image, or the stripes are unusable (NaN, parallel)."""


class StripeMatchError(PoseError):
    """The two stripes of a screen cannot be told apart by direction (cross turned by ~45°)."""


class InconsistentCrossesError(PoseError):
    """The three crosses cannot come from one rigid pose: the fit residual exceeds the threshold.

    Attributes
    ----------
    residual_rms : float
        RMS of the stripe residuals at the best fit, m.
    threshold : float
        The configured limit, m.
    """

    def __init__(self, message: str, *, residual_rms: float, threshold: float) -> None:
        super().__init__(message)
        self.residual_rms = residual_rms
        self.threshold = threshold

    def __reduce__(self):  # keep the keyword-only figures when pickled (e.g. across processes)
        return (_rebuild_inconsistent, (str(self), self.residual_rms, self.threshold))


def _rebuild_inconsistent(message: str, residual_rms: float, threshold: float) -> InconsistentCrossesError:
    return InconsistentCrossesError(message, residual_rms=residual_rms, threshold=threshold)


class RigidFitError(PoseError):
    """Point sets unusable for a rigid fit: too few, mismatched, non-finite, collinear."""
