"""``elo-mitsuba validate`` and ``elo-mitsuba benchmark``: hand the command line on to the
``validation`` or ``benchmarks`` package of the source checkout.

Those packages live at the top of a checkout, next to ``elo_mitsuba/``, and are not installed;
they own their options and ``--help``. This module only finds the package (editable installs
and running from the checkout both work) and calls its ``main(argv)``; without a
checkout it says what to do, in one line.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

from ..errors import EloEnvironmentError

#: Sub-command -> (package of the checkout, the module whose ``main(argv)`` it runs, one-line help).
COMMANDS = {
    "validate": ("validation", "validation.runner", "reproduce the paper's checkable claims: figures and validation/REPORT.md "
                               "(source checkout only; 'elo-mitsuba validate --help' lists its options)"),
    "benchmark": ("benchmarks", "benchmarks", "measure the speed/accuracy trade: benchmarks/RESULTS.md (source checkout "
                                "only; 'elo-mitsuba benchmark --help' lists its options)"),
}


def find_checkout_package(package: str, command: str, roots=None):
    """Import ``package`` from the source checkout this elo_mitsuba comes from (or the current
    directory); ``roots`` overrides where to look. Raises :class:`EloEnvironmentError` naming
    ``command`` where there is none."""
    candidates = [Path(__file__).resolve().parents[2], Path.cwd()] if roots is None else [Path(r) for r in roots]
    for root in candidates:
        if (root / package / "__init__.py").is_file() and (root / package / "__main__.py").is_file():
            if str(root) not in sys.path:
                sys.path.insert(0, str(root))
            try:
                found = importlib.import_module(package)
            except ModuleNotFoundError as exc:  # pragma: no cover - broken checkout
                raise EloEnvironmentError(f"cannot import the {package} package from {root}: {exc}") from None
            if Path(found.__file__).resolve().parents[1] == root.resolve():
                return found
    raise EloEnvironmentError(
        f"'elo-mitsuba {command}' needs a source checkout: the {package}/ package is not installed with "
        f"elo-mitsuba. Clone the repository, install it with 'pip install -e .', and run 'elo-mitsuba {command}' "
        f"(or 'python -m {package}') from its root.")


def run(command: str, argv: list[str], roots=None) -> int:
    """Run ``python -m <package> argv`` of ``command`` in this process; its exit status."""
    package, module, _ = COMMANDS[command]
    find_checkout_package(package, command, roots)
    entry = importlib.import_module(module)
    try:
        return int(entry.main(list(argv)) or 0)
    except SystemExit as exc:  # argparse's --help and usage errors
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)


def add_parsers(subparsers) -> None:
    """List the checkout commands in ``elo-mitsuba --help`` (their own parsers do the rest)."""
    for command, (_, _, help_text) in COMMANDS.items():
        subparsers.add_parser(command, help=help_text, add_help=False)
