"""Errors of ``instrument.environment``."""


class AirConditionsError(ValueError):
    """Conditions outside the range the refractive-index equation covers, or not numbers; the
    message names the argument, its value and the range."""
