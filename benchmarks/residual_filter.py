"""The bounce filter on the residual about the far field's tabulated mean (issue 26), side by side
with the presets before it, and its bias.

* ``--res 1500`` (default): per scene, in its own process, `default` as it is and as it was before
  (400 paths per window instead of 1600; on relief no window, per-pixel paths), two rounds
  interleaved after a warm-up render each; the faster time, the render's own error estimate of the
  total and of e2 (worst detector, per pixel relative to the render's values with a floor of 5 % of
  their mean), peak RSS of the process.
* ``--bias N,M``: melt_chamber at ``--bias-res`` (128), N `default` renders (the residual
  filtered) against M of `unbiased` (the same tabulated mean, no window), per detector the RMS
  per-pixel difference of the two means less the noise of both (each pixel's variance over its
  renders), relative to e2's mean; with ``--whole`` the whole 2nd event is filtered instead.

    python -m benchmarks.residual_filter                       # 1500², athene_flat, shield_chamber, melt_chamber
    python -m benchmarks.residual_filter --bias 64,160         # the bias (about 2 min)
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time

import numpy as np

from .harness import DETS, estimated_rel, mean_difference, run_module

SCENES = ("athene_flat", "shield_chamber", "melt_chamber")
#: `default`'s budget per window before the residual filter.
BEFORE_BUDGET = 400


def _set(options_module, budget, angle):
    options_module.QUALITY_PRESETS["default"]["bounce_budget"] = budget
    options_module.RESIDUAL_FILTER_ANGLE_DEG = angle


def side_by_side(name, res):
    import elo_mitsuba as em
    from elo_mitsuba import options as o

    em.ensure_variant()
    now = (o.QUALITY_PRESETS["default"]["bounce_budget"], o.RESIDUAL_FILTER_ANGLE_DEG)
    before = (BEFORE_BUDGET, o.FILTER_ANGLE_DEG)  # the filter angle on relief: per-pixel paths
    scene = em.load_scene(name, res=res)
    rows = {}
    for rnd in range(2):
        for label, (budget, angle) in (("now", now), ("before", before)):
            _set(o, budget, angle)
            spp = scene.set_quality("default")
            if rnd == 0:
                scene.render(quality="custom", spp=spp, seed=7, progress=False)
            t = time.perf_counter()
            r = scene.render(quality="custom", spp=spp, seed=11 + rnd, progress=False)
            dt = time.perf_counter() - t
            rows.setdefault(label, []).append(
                (dt, max(estimated_rel(r, d) for d in DETS), max(estimated_rel(r, f"{d}.e2") for d in DETS)))
    _set(o, *now)
    out = {label: {"seconds": min(x[0] for x in v), "total": float(np.mean([x[1] for x in v])),
                   "e2": float(np.mean([x[2] for x in v]))} for label, v in rows.items()}
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def bias(res, n_filtered, n_per_pixel, whole=False):
    import elo_mitsuba as em

    em.ensure_variant()
    scene = em.load_scene("melt_chamber", res=res)
    if whole:  # the whole 2nd event through the same windows
        type(scene.integrator)._filters_residual = lambda self: False

    def stack(quality, n, seed0):
        spp = scene.set_quality(quality)
        return np.array([np.stack([scene.render(quality="custom", spp=spp, seed=seed0 + k, progress=False)
                                   .channels[f"{d}.e2"] for d in DETS]).astype(np.float64) for k in range(n)])

    f, g = stack("default", n_filtered, 1000), stack("unbiased", n_per_pixel, 5000)
    return {d: mean_difference(f[:, i], g[:, i]) for i, d in enumerate(DETS)}


def _positive(text):
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number >= 1")
    return int(text)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.residual_filter", description=__doc__.split("\n\n")[0])
    p.add_argument("--res", type=_positive, default=1500)
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--bias", help="N,M: N filtered against M per-pixel renders (melt_chamber)")
    p.add_argument("--bias-res", type=_positive, default=128)
    p.add_argument("--whole", action="store_true", help="with --bias: filter the whole 2nd event")
    p.add_argument("--one", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    chamber = SCENES + ("corrugated_chamber",)
    unknown = [n for n in a.scenes.split(",") if n not in chamber]
    if unknown:
        p.error(f"--scenes: {', '.join(unknown)}; choose among {', '.join(chamber)}")
    if a.bias:
        parts = a.bias.split(",")
        if len(parts) != 2 or not all(x.strip().isdigit() and int(x) >= 2 for x in parts):
            p.error(f"--bias {a.bias!r}: give N,M, two whole numbers >= 2 (renders of each side)")
        n, m = (int(x) for x in parts)
        what = "the whole 2nd event" if a.whole else "the residual about the tabulated mean"
        print(f"melt_chamber {a.bias_res}², {n} `default` renders ({what} filtered) against {m} per-pixel ones:\n")
        print("| detector | bias, RMS per pixel (of e2) | worst pixel (of e2) | pixels beyond 4 standard errors |")
        print("|---|---|---|---|")
        for d, v in bias(a.bias_res, n, m, a.whole).items():
            print(f"| {d} | {100 * v['bias']:.2f} % | {100 * v['worst']:.1f} % | {100 * v['beyond4']:.2f} % |")
        return 0
    if a.one:
        print("RESULT " + json.dumps(side_by_side(a.one, a.res)))
        return 0
    print(f"{a.res}², `default`, events 1 + 2, before (400 paths per window; relief per pixel) and now; "
          "the faster of two renders, the render's own error estimate (worst detector):\n")
    print("| scene | before: warm time, total, e2 | now: warm time, total, e2 | peak RSS (MB) |")
    print("|---|---|---|---|")
    for name in a.scenes.split(","):
        r = run_module("benchmarks.residual_filter", ["--one", name, "--res", str(a.res)])
        cells = [f"{r[k]['seconds']:.2f} s, {100 * r[k]['total']:.3f} %, {100 * r[k]['e2']:.2f} %"
                 for k in ("before", "now")]
        print(f"| {name} | {cells[0]} | {cells[1]} | {r['peak_rss_mb']:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
