"""``python -m validation [--quick] [--output-dir DIR] [--only STUDY ...]``: see validation/__init__.py."""

import sys

from .runner import main

sys.exit(main())
