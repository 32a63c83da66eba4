"""``elo-mitsuba optimize``: the Pareto front of detector systems from a TOML spec into a Zarr store
(thin over :func:`elo_mitsuba.design.optimize.optimize` and :mod:`elo_mitsuba.design.results`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._args import add_yes, non_negative_int, positive_int

HELP = "design a detector system: a Pareto front of gradient precision, masking, signal (TOML spec) into a Zarr store"

DESCRIPTION = """\
Search detector centres, normals (the point of the z-axis they face), radii and, where the spec
allows, their count for the Pareto front of the spec's objectives: sigma_worst (the Cramer-Rao
bound of the gradient at the worst field point for slopes up to s_max, slope units), masked_share
(facets up to s_mask that hide a detector), signal_min, e2_share (the chamber's 2nd-event share,
rendered) and more; inside the ATHENE-like chamber, clear of the beam's cone, the gun column, the
radiation sheet and each other. Optuna (multi-objective TPE or NSGA-II) asks for designs; each is
evaluated as a task on a Dask cluster (as 'sweep'); every evaluated design is stored
(xarray.open_zarr(OUT.zarr)). Re-running the same command resumes a killed run without evaluating
a stored design again. Bounds that hold no feasible design are refused in one line (exit 2) before
any work, and so is a run estimated above 4 h on this machine unless --yes (a run estimated above a
minute prints its estimate). Afterwards: Table 1's layouts under the same metric, the chosen design
(the front's knee) and how it compares, optionally the front as a plot and the chosen design as a
scene XML.
Spec format: examples/optimize_athene.toml and README ("Designing a detector system").
"""

EPILOG = """\
examples:
  elo-mitsuba optimize examples/optimize_athene.toml -o front.zarr --workers 2 --plot front.png --scene best.xml
  elo-mitsuba optimize examples/optimize_athene.toml -o front.zarr      # again: resumes, or only reports
  elo-mitsuba render best.xml -o best.exr --events 2
"""


def add_parser(subparsers):
    p = subparsers.add_parser("optimize", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("spec", metavar="SPEC.toml", help="the optimiser spec")
    p.add_argument("-o", "--output", required=True, metavar="OUT.zarr", help="Zarr store to write (or resume)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=non_negative_int, metavar="N",
                       help="local Dask worker processes (default 1; 0 = in this process)")
    where.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler: tcp://host:port or its file")
    p.add_argument("--threads", type=positive_int, metavar="N", help="Dr.Jit threads per worker")
    p.add_argument("--stop-after", type=positive_int, metavar="N",
                   help="stop after N evaluations in this run (re-run to go on)")
    p.add_argument("--plot", metavar="FRONT.png", help="draw the front and sketches of the chosen design and its ends")
    p.add_argument("--scene", metavar="BEST.xml", help="write the chosen design as a scene (athene_flat with its discs)")
    p.add_argument("--design", type=non_negative_int, metavar="TRIAL",
                   help="the design --scene writes (default: the front's knee)")
    p.add_argument("--second-event", action="store_true",
                   help="also render the 2nd-event share of the chosen design and of Table 1's layouts in the "
                        "chamber ([render] resolution and spp; a few seconds)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a store of another spec, and existing --plot/--scene files")
    p.add_argument("--quiet", "--no-progress", dest="no_progress", action="store_true", help="no progress line")
    add_yes(p)
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from ..design.optimize import optimize
    from ..design.results import (
        choose_design,
        compare_table1,
        design_of,
        export_scene,
        plot_front,
        table1_records,
    )
    from ..design.spec import load_spec
    from ..design.store import read_designs
    from ..errors import EloInputError
    from ..files import check_output

    spec = load_spec(args.spec, second_event=args.second_event)  # --second-event renders with [render]
    # the files asked for, and the design asked for, are checked before any work: the store holds the
    # designs 0 .. trials - 1 once the run is done (a resumed store counts towards the same trials)
    if args.design is not None:
        held = spec.trials
        if Path(args.output).exists() and not args.overwrite:
            try:  # a store resumed from a run that asked for more trials keeps them
                held = max(held, int(read_designs(args.output).sizes["design"]))
            except Exception:  # not a store yet: optimize() says why
                pass
        if not args.design < held:
            raise EloInputError(f"--design {args.design}: the run stores designs 0 .. {held - 1} "
                                f"(optimizer.trials = {spec.trials} in {args.spec})")
    if args.plot:
        check_output(args.plot, (".png",), overwrite=args.overwrite, what="--plot")
    if args.scene:
        check_output(args.scene, (".xml",), overwrite=args.overwrite, what="--scene")
    s = optimize(spec, args.output, workers=args.workers, scheduler=args.scheduler, threads_per_worker=args.threads,
                 overwrite=args.overwrite, progress=not args.no_progress, max_evaluations=args.stop_after,
                 force=args.yes)
    print(f"{s.path}: {s.trials} designs stored ({s.state}); {s.evaluated} evaluated in {s.seconds:.1f} s"
          + (f", {s.recovered} told from a killed run's log" if s.recovered else "") + f"; {s.front} on the Pareto front")
    ds = read_designs(args.output)
    if not ds.pareto.any():
        print("no feasible design yet: nothing to compare")
        return 0
    objectives = list(ds.attrs["objectives"])
    chosen = choose_design(ds) if args.design is None else args.design
    if chosen not in set(int(t) for t in ds.design.values):
        raise EloInputError(f"--design {chosen}: the store has no such design (0 .. {int(ds.design.max())})")
    d = ds.sel(design=chosen)
    params = ", ".join(f"{k}={float(d[k]):.4g}" for k in spec.parameter_names(int(d["count"])) if k in ds)
    print(f"chosen design {chosen} (count {int(d['count'])}): {params}")
    print("  " + ", ".join(f"{o}={float(d[o]):.4g}" for o in objectives))
    table1 = table1_records(spec)
    print("Table 1 layouts (same metric), and the chosen design / layout per objective:")
    for row in compare_table1(ds, table1):
        vals = ", ".join(f"{o}={v:.4g}" for o, v in row["values"].items())
        # a ratio to 0 says nothing: then the difference
        ratio = ", ".join(f"{o} x{r:.3g}" if row["values"][o] else f"{o} {float(d[o]) - row['values'][o]:+.3g}"
                          for o, r in row["chosen_ratio"].items())
        dom = "not dominated by the front"
        if row["dominated_by"] is not None:
            dv = row["dominating_values"]
            dom = f"dominated by front design {row['dominated_by']} (" + ", ".join(
                f"{o}={v:.4g}" for o, v in dv.items()) + ")"
        print(f"  {row['layout']}: {vals}{'' if row['feasible'] else ' (infeasible here)'}; chosen: {ratio}; {dom}")
    if args.second_event:
        from ..design.evaluate import second_event_share
        from ..design.geometry import design_discs

        m, r = spec.metric, spec.render
        kw = dict(resolution=r["resolution"], spp=r["spp"], work_distance_mm=m["wd"], field_mm=m["field"],
                  material=m["material"])
        shares = {name: second_event_share(design_discs(rec["params"], 4), **kw) for name, rec in table1.items()}
        if int(d["count"]) == 4 and bool(d["feasible"]):
            shares = {f"design {chosen}": second_event_share(design_of(ds, chosen), **kw), **shares}
        print("2nd-event share (largest of the four detectors, flat plate in the chamber): "
              + ", ".join(f"{k} {100 * v:.2f} %" for k, v in shares.items()))
    if args.plot:
        print(f"wrote {plot_front(ds, args.plot, table1=table1, chosen=chosen, overwrite=args.overwrite)}")
    if args.scene:
        print(f"wrote {export_scene(design_of(ds, chosen), args.scene, overwrite=args.overwrite)}")
    return 0
