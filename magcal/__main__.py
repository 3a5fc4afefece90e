"""``python -m magcal``: the ``magcal`` command line (:mod:`magcal.cli`)."""

import sys

from magcal.cli import main

sys.exit(main())
