"""`python -m inhand_tracker.service.cli`: the command line."""

import sys

from . import main

sys.exit(main())
