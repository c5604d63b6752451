"""`python -m colmap_citymodel ...` runs the command line interface."""

import sys

from .cli import main

sys.exit(main())
