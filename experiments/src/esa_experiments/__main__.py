"""``python -m esa_experiments``: see :mod:`esa_experiments.commands`."""

import sys

from esa_experiments.commands import main

sys.exit(main())
