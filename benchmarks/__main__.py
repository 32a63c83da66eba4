"""``python -m benchmarks [--quick] [--out FILE] [--only SECTION ...] [--fresh]``: see benchmarks/__init__.py."""

import sys

from .runner import main

sys.exit(main())
