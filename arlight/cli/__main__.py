"""`python -m arlight.cli`: the `arlight` command."""

import sys

from arlight.cli import main

sys.exit(main())
