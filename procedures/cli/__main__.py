"""``python -m procedures.cli …``: the ``instrument`` command line."""

import sys

from procedures.cli import main

sys.exit(main())
