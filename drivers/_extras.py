"""Adapters whose client library is an optional extra: imported when an adapter is created.

``pip install opr-repeatability`` gives the pure measurement core; each device family's client
library comes with its extra (``[ur]``, ``[basler]``, ``[rotary-table]``, ``[interferometer]``; ``[all]``
for everything). A station that names an adapter whose library is missing gets one typed error
saying which extra to install, not an ``ImportError`` when the drivers package is imported.
"""

from __future__ import annotations

import importlib
from typing import Any

from drivers._errors import ClientLibraryMissing

DISTRIBUTION = "opr-repeatability"


def load_adapter(module: str, name: str, *, device: str, adapter: str, libraries: tuple[str, ...],
                 extra: str) -> Any:
    """The adapter class ``module.name``, importing its module (and so its client library) now.

    Raises
    ------
    ClientLibraryMissing
        One of ``libraries`` (top-level module names, e.g. ``"pymodbus"``) cannot be imported.
    """
    try:
        return getattr(importlib.import_module(module), name)
    except ImportError as exc:
        missing = (exc.name or "").split(".")[0]
        if missing not in libraries:
            raise
        raise ClientLibraryMissing(device, f"create the {adapter} adapter",
                                   f"its client library {missing} is not installed "
                                   f"(pip install '{DISTRIBUTION}[{extra}]')") from None
