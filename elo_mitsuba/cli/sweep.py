"""``elo-mitsuba sweep``: a design sweep from a TOML spec into a Zarr store (thin over
:func:`elo_mitsuba.sweeps.sweep`)."""

from __future__ import annotations

import argparse

from ._args import non_negative_int, number, positive_int

HELP = "run a design sweep (TOML spec) locally or on a Dask cluster into a Zarr store"

DESCRIPTION = """\
Render a scene over a grid of parameters (a TOML spec: the scene, fixed and swept parameters,
render settings, what to keep) and store per point the chosen detector images and design metrics
(per-detector mean and spread, share of events >= 2, masked fraction, gradient error on a test
surface) in one Zarr store: xarray.open_zarr(OUT.zarr), one variable per metric/channel, dims =
the swept parameters, named as the spec names them with '.' as '_' (right.radius: right_radius,
ds.sel(right_radius=25); a [zip.NAME] group: NAME). The spec format: examples/sweep_layouts.toml
and README ("Design sweeps").

Each worker loads a scene once per combination of load-time parameters (XML <default>s such as
layout, dh, dw, res) and re-renders it in place for spp, events, quality and detector moves
(right.center, right.normal, right.radius, detectors.radius). Re-running the same command resumes:
points done are skipped, failed ones retried; a different spec on an existing store is refused.
The spec is checked completely, every point's values against the scene, before the store is
created (exit 2 with one line); so are the cluster arguments (--workers and --threads at most the
cores, a --scheduler that answers within 10 s). A sweep whose estimate is above 4 h on this machine
or 2 million store files is refused with the estimate unless --yes. If every worker is lost (none
for --worker-wait seconds) or the scheduler is lost, the sweep stops with one line (exit 2); the
points stored stay done, and re-running the command resumes. Two clients on one store: exactly one
creates it, and each point is rendered by one of them (claims in OUT.zarr/.claims).
"""

EPILOG = """\
examples:
  elo-mitsuba sweep examples/sweep_minimal.toml -o flat.zarr                 # one local worker
  elo-mitsuba sweep examples/sweep_layouts.toml -o layouts.zarr --workers 2
  dask scheduler --port 8786 & dask worker tcp://127.0.0.1:8786 --nthreads 1 &
  elo-mitsuba sweep spec.toml -o /shared/out.zarr --scheduler tcp://127.0.0.1:8786
  elo-mitsuba sweep-plot layouts.zarr gradient_rms_eq26 -o rms.png
"""


def add_parser(subparsers):
    p = subparsers.add_parser("sweep", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("spec", metavar="SPEC.toml", help="the sweep spec")
    p.add_argument("-o", "--output", required=True, metavar="OUT.zarr", help="Zarr store to write (or resume)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=non_negative_int, metavar="N",
                       help="local Dask worker processes (default 1; 0 = in this process, without Dask)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="a running Dask scheduler: tcp://host:port, or its scheduler file (.json); the "
                       "workers must see OUT.zarr at the same path")
    p.add_argument("--threads", type=positive_int, metavar="N",
                   help="Dr.Jit threads per worker (default: the host's cores / its workers)")
    p.add_argument("--worker-wait", type=number, metavar="S",
                   help="stop (with what is stored kept) when no worker is connected for S seconds (default 60, "
                        "at most 604800, a week; not with --workers 0, which has no workers)")
    p.add_argument("--yes", action="store_true",
                   help="run a sweep whose estimate (printed when refused) is over the limits: above 4 h on this "
                        "machine or 2 million store files")
    p.add_argument("--overwrite", action="store_true", help="replace an existing store (else it is resumed)")
    p.add_argument("--quiet", "--no-progress", dest="no_progress", action="store_true",
                   help="no progress line on stderr")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from ..sweeps import sweep

    s = sweep(args.spec, args.output, workers=args.workers, scheduler=args.scheduler,
              threads_per_worker=args.threads, overwrite=args.overwrite, progress=not args.no_progress,
              force=args.yes, worker_wait_s=args.worker_wait)
    state = "created meanwhile by another client, resumed" if s.state == "joined" else s.state
    print(f"{s.path}: {s.done}/{s.points} points done, {s.failed} failed, {s.skipped} already stored "
          f"({state}); {s.points - s.skipped - s.claimed_elsewhere} rendered in {s.seconds:.1f} s on {s.workers} worker(s)"
          + (f", {s.rate:.2f} points/s" if s.points > s.skipped + s.claimed_elsewhere else ""))
    if s.claimed_elsewhere:
        print(f"{s.claimed_elsewhere} point(s) left to another client rendering this store; re-run after it ends "
              "to check them")
    if s.failed:
        print(f"failed points: see the store's 'error' variable (xarray.open_zarr('{s.path}').error); "
              "re-run the same command to retry them")
    return 1 if s.failed else 0
