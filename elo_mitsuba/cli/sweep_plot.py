"""``elo-mitsuba sweep-plot``: one metric of a sweep store as a line plot or heat map (PNG)."""

from __future__ import annotations

import argparse

from ..errors import EloInputError

HELP = "plot a sweep metric over one or two swept parameters (PNG)"

DESCRIPTION = """\
Plot a metric of a sweep store (elo-mitsuba sweep): over one swept parameter a line (one per
detector for per-detector metrics), over two a heat map (per-detector metrics: --detector, or
the mean over detectors). Axes are labelled with the parameters and their units; failed or
missing points are left out. Further swept dimensions are fixed with --select DIM=VALUE. A
dimension is named as in the store, the spec key with '.' as '_' (right_radius, the name
xarray's ds.sel(right_radius=25) takes), or as the spec writes it (right.radius); --x likewise.
"""

EPILOG = """\
examples:
  elo-mitsuba sweep-plot layouts.zarr gradient_rms_eq26 -o rms.png
  elo-mitsuba sweep-plot layouts.zarr signal_mean -o mean.png --detector right
  elo-mitsuba sweep-plot layouts.zarr signal_spread -o spread.png --select detectors_radius=25
"""


def _selection(text: str) -> tuple[str, str]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"{text!r} is not DIM=VALUE (e.g. --select layout=zeta50)")
    k, v = text.split("=", 1)
    return k.strip(), v.strip()


def add_parser(subparsers):
    p = subparsers.add_parser("sweep-plot", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("store", metavar="OUT.zarr", help="the sweep's Zarr store")
    p.add_argument("metric", metavar="METRIC", help="a metric variable (signal_mean, signal_spread, masked_fraction, ...)")
    p.add_argument("-o", "--output", required=True, metavar="PNG", help="figure to write")
    p.add_argument("--detector", help="one detector of a per-detector metric")
    p.add_argument("--select", type=_selection, action="append", default=[], metavar="DIM=VALUE",
                   help="fix a swept dimension: right_radius=25 or right.radius=25 (repeatable)")
    p.add_argument("--x", metavar="DIM", help="the dimension along the horizontal axis")
    p.add_argument("--overwrite", action="store_true", help="replace an existing PNG")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from ..files import check_output
    from ..sweeps import plot_metric
    from ..sweeps.extra import STORE_MODULES, require

    require("elo-mitsuba sweep-plot", STORE_MODULES)
    check_output(args.output, (".png",), overwrite=args.overwrite, what="figure")
    select = dict(args.select)
    if len(select) < len(args.select):
        raise EloInputError("--select names a dimension twice")
    out = plot_metric(args.store, args.metric, args.output, detector=args.detector, select=select, x=args.x,
                      overwrite=args.overwrite)
    print(f"wrote {out}")
    return 0
