"""``python -m validation ...``: see validation/__init__.py. A user error is one line, exit status 2."""

import sys

from elo_mitsuba.errors import EloError

from .runner import main

try:
    sys.exit(main())
except EloError as exc:  # ``elo-mitsuba validate`` prints these itself (cli/checkout.py)
    print(f"python -m validation: error: {exc}", file=sys.stderr)
    sys.exit(2)
