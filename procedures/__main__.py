import sys

from procedures.cli import main

sys.exit(main())
