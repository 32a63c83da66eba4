"""The optimiser against a 1000-point grid over the same parameters (issue 27), side by side.

    python -m benchmarks.optimize_vs_grid [--workers 2] [--out FOLDER]

Four detectors in the ATHENE-like chamber, symmetric and facing the origin (Table 1's kind), dh,
dw and radius free (examples/optimize_athene.toml): a grid of 10 x 10 x 10 = 1000 designs
(``sampler = "grid"``) and 100 designs of the multi-objective TPE and of NSGA-II, each run by
``elo_mitsuba.design.optimize`` on a local Dask cluster. Compared: the hypervolume of each feasible
front (objectives log10 sigma_worst and masked_share, reference point (log10 0.01, 1)), how many
of the grid's front designs an optimiser design weakly dominates (sigma within 1 %), the best
sigma_worst among designs that hide no detector, and the time.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: Reference point of the hypervolume: (log10 sigma_worst, masked_share).
REFERENCE = (-2.0, 1.0)


def hypervolume(points, ref=REFERENCE) -> float:
    """Area dominated by 2-D points (minimised) up to ``ref``."""
    p = np.array([q for q in points if q[0] < ref[0] and q[1] < ref[1]])
    if not len(p):
        return 0.0
    p = p[np.argsort(p[:, 0])]
    area, best_y = 0.0, ref[1]
    for i, (x, y) in enumerate(p):
        if y < best_y:
            nxt = ref[0]
            area += (nxt - x) * (best_y - y)
            best_y = y
    return float(area)


def _front(ds):
    ok = ds.feasible.values
    return np.stack([np.log10(ds.sigma_worst.values[ok]), ds.masked_share.values[ok]], axis=-1)


def run(workers: int, out: Path) -> dict:
    from elo_mitsuba.design.optimize import optimize
    from elo_mitsuba.design.store import read_designs

    base = tomllib.loads((ROOT / "examples" / "optimize_athene.toml").read_text())
    runs = {"grid": {"sampler": "grid", "trials": 1000, "grid_points": 10, "batch": 16},
            "tpe": {"sampler": "tpe", "trials": 100, "batch": 8},
            "nsga2": {"sampler": "nsga2", "trials": 100, "batch": 10}}
    results = {}
    for name, opt in runs.items():
        spec = {**base, "optimizer": {**base["optimizer"], **opt}}
        t0 = time.perf_counter()
        s = optimize(spec, out / f"{name}.zarr", workers=workers, progress=False, overwrite=True)
        ds = read_designs(out / f"{name}.zarr")
        pts = _front(ds)
        zero = ds.masked_share.values == 0
        results[name] = {"evaluations": int(ds.sizes["design"]), "seconds": round(time.perf_counter() - t0, 1),
                         "evaluated_now": s.evaluated, "feasible": int(ds.feasible.sum()),
                         "front": int(ds.pareto.sum()), "hypervolume": round(hypervolume(pts), 4),
                         "best_sigma_worst": float(ds.sigma_worst.values[ds.feasible.values].min()),
                         "best_sigma_worst_unmasked": float(ds.sigma_worst.values[ds.feasible.values & zero].min())
                         if (ds.feasible.values & zero).any() else None, "_pts": pts}
    grid_pts = results["grid"]["_pts"]
    gfront = grid_pts[[not np.any(np.all(grid_pts <= p, 1) & np.any(grid_pts < p, 1)) for p in grid_pts]]
    for name in ("tpe", "nsga2"):
        pts = results[name]["_pts"]
        covered = sum(bool(np.any((pts[:, 0] <= g[0] + np.log10(1.01)) & (pts[:, 1] <= g[1]))) for g in gfront)
        results[name]["grid_front_points_matched"] = f"{covered}/{len(gfront)}"
    for r in results.values():
        r.pop("_pts")
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="folder for the three stores (default: a temporary one)")
    args = ap.parse_args(argv)
    if args.out is None:
        with tempfile.TemporaryDirectory() as d:
            res = run(args.workers, Path(d))
    else:
        args.out.mkdir(parents=True, exist_ok=True)
        res = run(args.workers, args.out)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
