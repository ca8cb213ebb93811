"""``python -m vehjax.reproduce.dutta2019``: the same as ``vehjax reproduce dutta2019``."""

import sys

from .report import main

sys.exit(main())
