"""``elo-mitsuba benchmark``: measure speed against accuracy (the ``benchmarks`` package).

Like ``validate``, the benchmarks live at the top of a source checkout (``benchmarks/``) and are not
installed; this command finds them and runs ``python -m benchmarks`` with the same options.
"""

from __future__ import annotations

import argparse

from .validate import find_checkout_module

HELP = "measure the speed/accuracy trade: benchmarks/RESULTS.md (source checkout only)"

DESCRIPTION = """\
Measure, side by side in one run, what a render costs and how accurate it is: the ray-cast ceiling
of this machine and our fraction of it; accuracy against time for spp, detector sampling
(independent, stratified, the Appendix-A triangle quadrature) and events 1-4; the 1500 x 1500
targets of the quality presets; Mitsuba's own 'path' integrator at equal error; scaling with
resolution, spp and mesh size. Every timed configuration runs in its own process. The full run
takes about 40 minutes on 2 cores and writes benchmarks/RESULTS.md; --quick takes a few minutes
and writes out/bench_cache/RESULTS-quick.md. Run it on a quiet machine: absolute times are only
as good as the machine is idle; ratios are measured interleaved.
"""

EPILOG = """\
examples:
  elo-mitsuba benchmark --quick                       # a few minutes, smaller sizes
  elo-mitsuba benchmark --only targets path           # the 1500^2 targets and the path comparison
  python -m benchmarks                                # the same, from the repository root
"""


def add_parser(subparsers):
    p = subparsers.add_parser("benchmark", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smaller resolutions and fewer samples (minutes)")
    p.add_argument("--out", metavar="FILE", default=None,
                   help="markdown file to write (default benchmarks/RESULTS.md; with --quick "
                        "out/bench_cache/RESULTS-quick.md)")
    p.add_argument("--only", nargs="+", metavar="SECTION", default=None,
                   help="run only these sections (ceiling, accuracy, events, targets, path, scaling)")
    p.add_argument("--fresh", action="store_true", help="recompute the cached references")
    p.set_defaults(run=_run)
    return p


def _run(args) -> int:
    from ..errors import EloInputError

    run = find_checkout_module("benchmarks", "run", "benchmark")
    unknown = [s for s in (args.only or []) if s not in run.SECTIONS]
    if unknown:
        raise EloInputError(f"unknown benchmark section {unknown[0]!r}; choose from {', '.join(run.SECTIONS)}")
    argv = (["--quick"] if args.quick else []) + (["--fresh"] if args.fresh else [])
    argv += (["--out", args.out] if args.out else []) + (["--only", *args.only] if args.only else [])
    return int(run.main(argv) or 0)
