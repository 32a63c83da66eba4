"""``elo-mitsuba validate``: run the validation against the paper (the ``validation`` package).

The validation package lives at the top of a source checkout (``validation/``), next to
``elo_mitsuba/``; it is not installed with the package. This command finds it (editable installs
and running from the checkout both work) and runs it; otherwise it explains what to do.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

from ..errors import EloEnvironmentError

HELP = "reproduce the paper's checkable claims: figures and validation/REPORT.md (source checkout only)"

DESCRIPTION = """\
Run every study of the validation against Renner et al. 2023 (Fig. 4 STSA contrast, Fig. 10
corrugated sheet, Figs. 12-13 reflectance maps, Table 1 and Figs. 14-15 masking, Figs. 6/7/11 on the
melt plate, convergence, energy and symmetry checks) and write PNG figures and REPORT.md, a table with
the paper's number beside ours and a verdict for every claim. Default settings take about 10 minutes
on 2 cores and write validation/REPORT.md; --quick takes about a minute (tiny resolutions, for CI) and
writes out/validation-quick/. Needs a source checkout: the validation/ package is not installed.
"""

EPILOG = """\
examples:
  elo-mitsuba validate                       # full run -> validation/REPORT.md, validation/figures/
  elo-mitsuba validate --quick --output-dir /tmp/val
  elo-mitsuba validate --only stsa corrugated
  python -m validation --quick               # the same, from the repository root
"""

STUDIES_HINT = "checks, stsa, corrugated, reflectance, masking, melt_plate, convergence"


def find_checkout_module(package: str, module: str, command: str, roots=None):
    """Import ``package.module`` from the source checkout this elo_mitsuba comes from (or the
    current directory): ``validation/`` and ``benchmarks/`` live there and are not installed.
    ``roots`` overrides where to look; a clear error names ``command`` where none is found."""
    candidates = [Path(__file__).resolve().parents[2], Path.cwd()] if roots is None else [Path(r) for r in roots]
    for root in candidates:
        if (root / package / "__init__.py").is_file() and (root / package / f"{module}.py").is_file():
            if str(root) not in sys.path:
                sys.path.insert(0, str(root))
            try:
                found = importlib.import_module(f"{package}.{module}")
            except ModuleNotFoundError as exc:  # pragma: no cover - broken checkout
                raise EloEnvironmentError(f"cannot import the {package} package from {root}: {exc}") from None
            if Path(found.__file__).resolve().parents[1] == root.resolve():
                return found
    raise EloEnvironmentError(
        f"'elo-mitsuba {command}' needs a source checkout: the {package}/ package is not installed with "
        f"elo-mitsuba. Clone the repository, install it with 'pip install -e .', and run 'elo-mitsuba {command}' "
        f"(or 'python -m {package}') from its root.")


def _find_validation(roots=None):
    return find_checkout_module("validation", "runner", "validate", roots)


def add_parser(subparsers):
    import argparse

    p = subparsers.add_parser("validate", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="tiny resolutions (about a minute; for CI); default: full settings (~10 min on 2 cores)")
    p.add_argument("--output-dir", metavar="DIR", default=None,
                   help="where REPORT.md and figures/ go (default: validation/ for the full default run, "
                        "out/validation-quick/ with --quick, out/validation-partial/ with --only)")
    p.add_argument("--only", nargs="+", metavar="STUDY", default=None, help=f"run only these studies ({STUDIES_HINT})")
    p.add_argument("--json", metavar="FILE", default=None, help="also write the rows as JSON")
    p.add_argument("--no-figures", action="store_true", help="numbers only, no PNG figures")
    p.add_argument("--list", action="store_true", help="list the studies and exit")
    p.set_defaults(run=_run)
    return p


def _run(args) -> int:
    from ..errors import EloInputError

    runner = _find_validation()
    if args.only:
        from validation import STUDIES

        unknown = [s for s in args.only if s not in STUDIES]
        if unknown:
            raise EloInputError(f"unknown study {unknown[0]!r}; choose from {', '.join(STUDIES)}")
    return runner.run_from_args(args)
