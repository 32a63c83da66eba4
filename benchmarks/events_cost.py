"""What events 3 and 4 cost with the far field (issue 26, item 3), before and after, in one run.

"before": the far field as it was (the table holds events 2 .. traced and every cheap sample
looks all of them up, 16 gathers per channel; option ``far_field_later=True``); "after":
the table holds the 2nd event only, events >= 3 of the far paths are traced without a variate,
with probability ``far_roulette`` = q (whole blocks of 32 lanes, weight 1/q; q = 1: always).
The 1st and 2nd events are the
same in both. Every configuration is the ``default`` preset for the scene's resolution and
events, rendered as ``custom`` with the far field's settings changed; one scene object per
configuration (so no table is rebuilt between the interleaved renders).

Timing: warm renders (table built, kernels compiled), interleaved over the configurations,
median of ``--reps``; wall time and this process's CPU time (all threads). On shared cores the
CPU time is the steadier measure of work.

Errors (events = 4 only, ``--res`` pixels): per event and total, worst detector, per pixel
|x - ref| / max(ref, 5 % of its mean) (benchmarks/harness.py) against a reference: the
``unbiased`` preset at events 4 with ``--ref-factor`` x its spp, far field 8, q = 1, fine table
(the estimator before; unbiased: tests/test_far_field.py), its own noise (from its two halves)
subtracted in quadrature. "of total": the event's error over the total's reference, what it adds
to the total's error.

    python -m benchmarks.events_cost --res 128 --scenes athene_flat,shield_chamber
    python -m benchmarks.events_cost --res 512 --no-errors      # timing only
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from .far_field import variate_options
from .harness import DETS, FLOOR, run_module

SCENES = ("athene_flat", "shield_chamber")


def _rel(img, ref, err_ref, denom_ref):
    """(RMS relative error, RMS relative noise of the reference) with the harness's floor."""
    denom = np.maximum(denom_ref, FLOOR * max(float(denom_ref.mean()), 1e-300))
    e = (np.asarray(img, np.float64) - ref) / denom
    n = np.asarray(err_ref, np.float64) / denom if err_ref is not None else np.zeros_like(e)
    return float(np.sqrt(np.mean(e * e))), float(np.sqrt(np.mean(n * n)))


def _scene(name, res, events, before, q):
    import elo_mitsuba as em

    scene = em.load_scene(name, res=res)
    scene.set_events(events)
    spp = scene.set_quality("default")
    if events > 1 and scene.integrator.far_table:
        # this study is of the SAMPLED variate (option far_field = s, the presets before the
        # tabulated mean): s by their rule
        scene.configure(**variate_options(scene.integrator.options, "sampled"))
    if events > 2 and scene.integrator.far_field > 0:
        scene.configure(far_roulette=q, far_field_later=before)
    return scene, spp


def measure(name, res, qs, reps, errors, ref_factor):
    import elo_mitsuba as em

    em.ensure_variant()
    out = {"scene": name, "res": res, "rows": [], "load_start": os.getloadavg()[0]}
    configs = [("before", k, True, 1.0) for k in (1, 2, 3, 4)]
    configs += [(f"after q={q:g}", k, False, q) for q in qs for k in (3, 4)]
    scenes = {}
    for label, k, before, q in configs:
        scene, spp = _scene(name, res, k, before, q)
        t = time.perf_counter()
        scene.render(seed=1, spp=spp, progress=False, quality="custom")  # compile, build the table
        scenes[(label, k)] = (scene, spp, time.perf_counter() - t)
    walls = {c: [] for c in scenes}
    cpus = {c: [] for c in scenes}
    for rep in range(reps):
        for c, (scene, spp, _) in scenes.items():
            w, p = time.perf_counter(), time.process_time()
            scene.render(seed=100 + rep, spp=spp, progress=False, quality="custom")
            cpus[c].append(time.process_time() - p)
            walls[c].append(time.perf_counter() - w)
    for (label, k), (scene, spp, first) in scenes.items():
        o = scene.integrator.options
        out["rows"].append({"label": label, "events": k, "wall": float(np.median(walls[(label, k)])),
                            "cpu": float(np.median(cpus[(label, k)])), "first": first, "spp": spp,
                            "far_field": o.far_field, "far_roulette": o.far_roulette,
                            "bounce_samples": o.bounce_samples})
    out["load_end"] = os.getloadavg()[0]
    if errors:
        ref_scene = em.load_scene(name, res=res)
        ref_scene.set_events(4)
        spp_ref = ref_scene.set_quality("unbiased") * ref_factor
        ref_scene.configure(far_table=False, far_field=8, far_roulette=1.0, far_field_later=True)
        t = time.perf_counter()
        ref = ref_scene.render(spp=spp_ref, seed=90001, progress=False, quality="custom")
        out["reference_s"] = time.perf_counter() - t
        out["errors"] = []
        for label in ["before"] + [f"after q={q:g}" for q in qs]:
            scene, spp, _ = scenes[(label, 4)]
            r = scene.render(seed=7, spp=spp, progress=False, quality="custom")
            row = {"label": label}
            for key in ["total"] + [f"e{e}" for e in (1, 2, 3, 4)]:
                worst, worst_tot, worst_est, worst_ref = 0.0, 0.0, 0.0, 0.0
                for d in DETS:
                    ch = d if key == "total" else f"{d}.{key}"
                    rv = ref.channels[ch].astype(np.float64)
                    rms, noise = _rel(r.channels[ch], rv, ref.errors.get(ch), rv)
                    worst = max(worst, float(np.sqrt(max(rms**2 - noise**2, 0.0))))
                    worst_ref = max(worst_ref, noise)
                    tot = ref.channels[d].astype(np.float64)
                    rms_t, noise_t = _rel(r.channels[ch], rv, ref.errors.get(ch), tot)
                    worst_tot = max(worst_tot, float(np.sqrt(max(rms_t**2 - noise_t**2, 0.0))))
                    est = r.errors.get(ch)
                    if est is not None:
                        worst_est = max(worst_est, _rel(r.channels[ch], rv, est, rv)[1])
                row[key] = worst
                row[key + "_of_total"] = worst_tot
                row[key + "_est"] = worst_est
                row[key + "_ref_noise"] = worst_ref
            out["errors"].append(row)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.events_cost", description=__doc__.split("\n\n")[0])
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--q", default="0.5,0.25", help="far_roulette values of the 'after' rows (comma-separated)")
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--ref-factor", type=int, default=8)
    p.add_argument("--no-errors", action="store_true")
    p.add_argument("--one", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    qs = [float(x) for x in a.q.split(",") if x]
    if a.one:
        print("RESULT " + json.dumps(measure(a.one, a.res, qs, a.reps, not a.no_errors, a.ref_factor)))
        return 0
    print(f"machine: {os.cpu_count()} cores (shared with other jobs), load average at start "
          f"{os.getloadavg()[0]:.2f}\n")
    for name in a.scenes.split(","):
        try:
            r = run_module("benchmarks.events_cost", ["--one", name, "--res", str(a.res), "--q", a.q, "--reps",
                                                      str(a.reps), "--ref-factor", str(a.ref_factor)]
                           + (["--no-errors"] if a.no_errors else []))
        except RuntimeError as exc:
            print(f"{name}: failed\n{exc}", file=sys.stderr)
            return 1
        print(f"### {name}, {a.res}x{a.res}, `default` preset (load average {r['load_start']:.1f} -> "
              f"{r['load_end']:.1f})\n")
        print("| configuration | events | far_field, q | warm wall (s) | warm CPU (s) | CPU / events=1 | "
              "CPU / events=2 | first render (s) |")
        print("|---|---|---|---|---|---|---|---|")
        cpu1 = next(x["cpu"] for x in r["rows"] if x["events"] == 1)
        cpu2 = next(x["cpu"] for x in r["rows"] if x["events"] == 2)
        for x in r["rows"]:
            print(f"| {x['label']} | {x['events']} | {x['far_field']}, {x['far_roulette']:g} | {x['wall']:.3f} | "
                  f"{x['cpu']:.3f} | {x['cpu'] / cpu1:.2f} | {x['cpu'] / cpu2:.2f} | {x['first']:.1f} |")
        if "errors" in r:
            print(f"\nevents = 4, RMS error per pixel, worst detector, against the reference "
                  f"({r['reference_s']:.0f} s; its own noise subtracted); of the event's own value, "
                  "[of the total], (the render's own estimate)\n")
            keys = ["total", "e1", "e2", "e3", "e4"]
            print("| configuration | " + " | ".join(keys) + " |")
            print("|---|" + "---|" * len(keys))
            for e in r["errors"]:
                cells = [f"{100 * e[k]:.2f} % [{100 * e[k + '_of_total']:.3f} %] ({100 * e[k + '_est']:.2f} %)"
                         for k in keys]
                print(f"| {e['label']} | " + " | ".join(cells) + " |")
            e = r["errors"][0]
            print("\nreference's own noise: " + ", ".join(f"{k} {100 * e[k + '_ref_noise']:.2f} %" for k in keys))
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
