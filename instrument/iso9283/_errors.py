"""Errors of ``instrument.iso9283``."""


class ISO9283Error(ValueError):
    """Unusable input for an ISO 9283 characteristic; the message names the argument and the fault."""
