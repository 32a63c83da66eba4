"""Design sweeps: throughput of ``elo-mitsuba sweep`` with 1 and 2 local Dask workers against a plain
in-process loop over ``EloScene.render``, the sweep's overhead per point, worker memory over a long
sweep (in place and with a reload per point), and a projection to 10 000 points on N machines.

Part of ``python -m benchmarks`` (``--only sweep``); alone, faster:
``python -m benchmarks.section_sweep [--points N] [--res R] [--out FILE]``. Every configuration runs
in its own process (``--job JSON``), one after another, on the same points.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .report import fmt, table

TITLE = "Design sweeps: throughput, overhead, memory"
ROOT = Path(__file__).resolve().parents[1]
#: The measured sweep: one scene load, the right detector's radius swept (in place).
SCENE, EVENTS, QUALITY = "corrugated_sheet", 1, "default"


def _radii(n):
    return [round(15.0 + 0.5 * k, 3) for k in range(n)]


def _spec(res, n, keep_all=True, vary=None):
    return {"scene": SCENE, "vary": vary or {"right": {"radius": _radii(n)}},
            "render": {"resolution": res, "events": EVENTS, "quality": QUALITY},
            "keep": {"channels": "all" if keep_all else []}}


def _job(kind, **kw):
    """Run one configuration in a fresh process (``--job``); its JSON result."""
    cmd = [sys.executable, "-m", "benchmarks.section_sweep", "--job", json.dumps({"kind": kind, **kw})]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800, stdin=subprocess.DEVNULL)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if p.returncode or not lines:
        raise RuntimeError(f"sweep benchmark job {kind} failed ({p.returncode}):\n{p.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def _steady_rate(finished, workers):
    """Points per second once every worker has finished its first point (warm-up: load, compile)."""
    t = np.sort(np.asarray(finished, dtype=float))
    k = max(1, min(workers, len(t) - 1))
    return (len(t) - k) / (t[-1] - t[k - 1]) if t[-1] > t[k - 1] else float("nan")


def run_job(job) -> dict:
    """One configuration, in this process."""
    kind = job["kind"]
    if kind == "loop":  # the reference: load once, warm up, then set_detector + render per point
        import drjit as dr

        import elo_mitsuba as em

        dr.set_thread_count(job["threads"])
        scene = em.load_scene(SCENE, res=job["res"])
        radii = _radii(job["points"])
        scene.set_detector("right", radius=radii[0])
        scene.render(events=EVENTS, quality=QUALITY)  # warm-up (compilation), not timed
        t0, c0 = time.perf_counter(), time.process_time()
        for r in radii[1:]:
            scene.set_detector("right", radius=r)
            scene.render(events=EVENTS, quality=QUALITY)
        dt = time.perf_counter() - t0
        return {"rate": (len(radii) - 1) / dt, "seconds": dt, "cpu": (time.process_time() - c0) / (len(radii) - 1)}
    import xarray as xr

    from elo_mitsuba import sweep

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.zarr"
        t0 = time.perf_counter()
        s = sweep(job["spec"], out, workers=job["workers"], threads_per_worker=job.get("threads"), progress=False)
        wall = time.perf_counter() - t0
        ds = xr.open_zarr(out)
        finished = ds["finished_at"].values.ravel()
        rss = ds["worker_rss_mb"].values.ravel()
        order = np.argsort(finished)
        workers_used = sorted(set(ds["worker"].values.ravel()))
        names = ds["worker"].values.ravel()[order]
        rss_by_worker = {w: rss[order][names == w].tolist() for w in workers_used}
        cpu = ds["worker_cpu_s"].values.ravel()[order]
        # CPU seconds per point after each worker's first (a shared machine slows the wall clock,
        # not the CPU time a point costs); the scheduler's and nannies' CPU is not counted
        per_point = [np.diff(cpu[names == w]).mean() for w in workers_used if (names == w).sum() > 1]
        return {"rate": _steady_rate(finished, max(job["workers"], 1)), "wall": wall, "done": s.done,
                "points": s.points, "rss": rss_by_worker, "cpu": float(np.mean(per_point))}


def measure(res=512, points=17, long_points=120, reload_points=24, rounds=2) -> dict:
    """Every configuration, one after another; returns the numbers the section reports."""
    cores = os.cpu_count() or 1
    out = {"res": res, "points": points, "cores": cores}
    # interleaved rounds, best rate of each: other jobs on the machine slow some runs down
    for _ in range(rounds):
        runs = {"loop": _job("loop", res=res, points=points, threads=cores)}
        for w in (0, 1, 2):
            runs[f"sweep{w}"] = _job("sweep", spec=_spec(res, points), workers=w)
        for k, r in runs.items():
            if k not in out or r["rate"] > out[k]["rate"]:
                out[k] = {**r, "cpus": out.get(k, {}).get("cpus", [])}
            out[k]["cpus"] = out[k]["cpus"] + [r["cpu"]]
    out["long"] = _job("sweep", spec=_spec(64, long_points, keep_all=False), workers=1)
    out["reload"] = _job("sweep", spec=_spec(64, reload_points, keep_all=False,
                                             vary={"dh": [200.0 + 2 * k for k in range(reload_points)]}), workers=1)
    return out


def _growth(rss_lists, skip=10):
    """MB of resident memory gained from point ``skip`` to the last, worst worker."""
    return max(v[-1] - v[min(skip, len(v) - 1)] for v in rss_lists.values())


def markdown(m) -> str:
    loop = m["loop"]["rate"]
    cpu_loop = float(np.median(m["loop"]["cpus"]))
    rows = [["plain loop over EloScene.render (in process)", f"{m['cores']} Dr.Jit threads", fmt(loop, 3), "1.00",
             fmt(cpu_loop, 3), "1.00", "-"]]
    for w in (0, 1, 2):
        r = m[f"sweep{w}"]
        cpu = float(np.median(r["cpus"]))
        what = "in process, no Dask (--workers 0)" if w == 0 else f"{w} local Dask worker{'s' if w > 1 else ''}"
        rows.append([f"elo-mitsuba sweep, {what}", f"{m['cores'] // max(w, 1)} Dr.Jit thread(s) each",
                     fmt(r["rate"], 3), fmt(r["rate"] / loop, 3), fmt(cpu, 3), fmt(cpu / cpu_loop, 3), f"{r['wall']:.1f} s"])
    over = 1 / (m["sweep1"]["rate"] / loop) - 1
    over_cpu = float(np.median(m["sweep1"]["cpus"])) / cpu_loop - 1
    best = max(m["sweep1"]["rate"], m["sweep2"]["rate"])
    lines = [
        f"{SCENE}, {m['res']}², events {EVENTS}, quality {QUALITY}, all four channels stored per point "
        f"(4 x {m['res'] ** 2 * 4 / 1e6:.1f} MB) plus the metrics; the right detector's radius swept over "
        f"{m['points']} values (one scene load per worker). Rates are steady-state (after each worker's first "
        "point: load and compilation); the wall time includes starting the local cluster.", "",
        table(["configuration", "threads", "points/s (best round)", "vs plain loop", "CPU s per point (median)",
               "vs plain loop", "wall (all points)"], rows), "",
        f"Overhead of the sweep per point, 1 worker against the loop with the same threads: {100 * over_cpu:+.1f} % "
        f"in CPU time, {100 * over:+.1f} % in wall-clock rate (without Dask, metrics and the Zarr write, which "
        f"overlap the next render: {100 * (loop / m['sweep0']['rate'] - 1):+.1f} %). On a shared machine the "
        "CPU time is the robust figure: other jobs stretch the wall clock of whichever run they meet.", "",
        f"Memory: {m['long']['points']} points at 64², in place: the worker's resident set grows by "
        f"{_growth(m['long']['rss']):.1f} MB from point 10 to the last "
        f"({min(min(v) for v in m['long']['rss'].values()):.0f}-{max(max(v) for v in m['long']['rss'].values()):.0f} MB). "
        f"With a reload per point (dh swept, {m['reload']['points']} values, the worker's cache of "
        f"3 scenes): {_growth(m['reload']['rss']):+.1f} MB, i.e. "
        f"{_growth(m['reload']['rss']) / max(m['reload']['points'] - 10, 1):+.2f} MB per load.", "",
        f"Projection for 10 000 points of this size: {10000 / best / 3600:.2f} h on one such machine "
        f"({best:.2f} points/s); on N machines 10 000 / (N x {best:.2f}) s plus ~10 s to start: "
        + ", ".join(f"N = {n}: {10000 / (n * best) / 60:.0f} min" for n in (4, 16, 64))
        + " (renders are independent; the Zarr store must be on a file system the machines share).",
    ]
    return "\n".join(lines)


def run(b):
    """The section for ``python -m benchmarks``."""
    q = b.quick
    m = measure(res=128 if q else 512, points=9 if q else 17, long_points=40 if q else 120,
                reload_points=14 if q else 24, rounds=1 if q else 2)
    return markdown(m)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.section_sweep", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--job", help=argparse.SUPPRESS)
    ap.add_argument("--res", type=int, default=512)
    ap.add_argument("--points", type=int, default=17)
    ap.add_argument("--long-points", type=int, default=120)
    ap.add_argument("--rounds", type=int, default=2, help="interleaved repetitions (best rate of each)")
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args(argv)
    if args.job:
        print("RESULT " + json.dumps(run_job(json.loads(args.job))))
        return 0
    m = measure(res=args.res, points=args.points, long_points=args.long_points, rounds=args.rounds)
    text = markdown(m)
    print(text)
    print(json.dumps(m), file=sys.stderr)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
