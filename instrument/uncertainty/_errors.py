"""Errors of ``instrument.uncertainty``."""


class UncertaintyError(ValueError):
    """Unusable input for an uncertainty evaluation; the message names the argument and the fault."""
