"""The far-field control variate (issue 26) in its two forms, side by side in one run, on the
chamber scenes (athene_flat, corrugated_chamber, melt_chamber, shield_chamber): off, with its mean
sampled per pixel (option ``far_field`` = s, as the presets had it on scenes without relief) and
tabulated (option ``far_table``, the presets now, where the near share is small); error per event
and total, time warm and of the first render, peak memory, and the render's own estimate.

Each scene runs in its own process (peak RSS per scene). Reference: the unbiased preset with
``--ref-factor`` x its spp, 96 quadrature triangles and the far field at ``--ref-far`` strata
(unbiased: tests/test_far_field.py), independent seed; its own estimated noise is listed and the
errors are corrected for it (sqrt(err^2 - noise_ref^2), per channel). Errors per pixel as
everywhere in benchmarks/ (|x - ref| / max(ref, 5 % of its mean)), worst detector.

    python -m benchmarks.far_field --res 128                 # a table in Markdown on stdout
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import time

import numpy as np

from .harness import DETS, rel_error, run_module

SCENES = ("athene_flat", "corrugated_chamber", "melt_chamber", "shield_chamber")
#: (label, quality, variate: None = as the preset chooses, "off", "sampled" = the mean sampled with
#: s x s >= 8 x the traced paths per sample, s >= 2: the presets' rule before the tabulated mean,
#: "tabulated")
CONFIGS = (("default, no variate", "default", "off"), ("default, sampled mean", "default", "sampled"),
           ("default, tabulated mean", "default", "tabulated"), ("default (as the preset chooses)", "default", None),
           ("unbiased, no variate", "unbiased", "off"), ("unbiased, sampled mean", "unbiased", "sampled"),
           ("unbiased, tabulated mean", "unbiased", "tabulated"),
           ("unbiased (as the preset chooses)", "unbiased", None))


def variate_options(options, variate):
    """The options of a configuration's ``variate`` on top of a preset's ``options``."""
    if variate == "off":
        return dict(far_table=False, far_field=0)
    if variate == "tabulated":
        return dict(far_table=True, far_field=0)
    per_sample = options.bounce_fraction * options.bounce_samples
    return dict(far_table=False, far_field=min(32, max(2, math.ceil(math.sqrt(8 * per_sample)))))


def measure(scene_name, res, ref_factor, ref_far):
    import elo_mitsuba as em

    em.ensure_variant()
    scene = em.load_scene(scene_name, res=res)
    spp_ref = scene.set_quality("unbiased") * ref_factor  # its options, then made "custom" below
    scene.configure(quadrature_triangles=96, far_table=False, far_field=ref_far)  # sampled: unbiased, not the table
    t = time.perf_counter()
    ref = scene.render(spp=spp_ref, seed=90001, progress=False, quality="custom")
    out = {"scene": scene_name, "res": res, "reference_s": time.perf_counter() - t, "rows": []}
    noise = {n: ref.error_summary()[n].get("rms_rel") or 0.0 for n in ref.channels}
    out["reference_noise"] = max(noise[f"{d}.e2"] for d in DETS)
    for label, quality, variate in CONFIGS:
        spp = scene.set_quality(quality)
        if variate is not None:  # the preset's options with the variate set: rendered as "custom"
            scene.configure(**variate_options(scene.integrator.options, variate))
        how = dict(quality="custom", spp=spp) if variate is not None else dict(quality=quality)
        t = time.perf_counter()
        scene.render(seed=7, progress=False, **how)  # compile, build the tables, warm up
        first = time.perf_counter() - t
        times = []
        for seed in (11, 12):
            t = time.perf_counter()
            r = scene.render(seed=seed, progress=False, **how)
            times.append(time.perf_counter() - t)
        row = {"label": label, "seconds": min(times), "first": first, "builds": scene.integrator.far_field_builds,
               "far_field": scene.integrator.far_field, "far_table": scene.integrator.far_table}
        for kind, key in (("total", lambda d: d), ("e1", lambda d: f"{d}.e1"), ("e2", lambda d: f"{d}.e2")):
            errs, ests, ests_ref = [], [], []
            for d in DETS:
                rms = rel_error(r.channels[key(d)], ref.channels[key(d)])[0]
                errs.append(float(np.sqrt(max(rms**2 - noise[key(d)] ** 2, 0.0))))
                ests.append(r.error_summary()[key(d)].get("rms_rel") or 0.0)
                if key(d) in r.errors:  # the same per-pixel errors, relative to the reference's values
                    ests_ref.append(rel_error(ref.channels[key(d)] + r.errors[key(d)], ref.channels[key(d)])[0])
            row[kind] = max(errs)
            row[kind + "_est"] = max(ests)
            row[kind + "_est_ref"] = max(ests_ref, default=0.0)
        row["e2_nonpositive"] = max(float(np.mean(r.channels[f"{d}.e2"] <= 0)) for d in DETS)
        out["rows"].append(row)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.far_field", description=__doc__.split("\n\n")[0])
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--ref-factor", type=int, default=8)
    p.add_argument("--ref-far", type=int, default=4)
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--one", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.one:
        print("RESULT " + json.dumps(measure(a.one, a.res, a.ref_factor, a.ref_far)))
        return 0
    rows = []
    for name in a.scenes.split(","):
        try:
            r = run_module("benchmarks.far_field", ["--one", name, "--res", str(a.res), "--ref-factor",
                                                    str(a.ref_factor), "--ref-far", str(a.ref_far)])
        except RuntimeError as exc:
            print(f"{name}: failed\n{exc}", file=sys.stderr)
            return 1
        print(f"{name}: reference {r['reference_s']:.1f} s, its e2 noise {100 * r['reference_noise']:.2f} %, "
              f"peak RSS {r['peak_rss_mb']:.0f} MB", file=sys.stderr)
        for row in r["rows"]:
            how = "tabulated" if row["far_table"] else (f"s = {row['far_field']}" if row["far_field"] else "off")
            rows.append(f"| {name} | {row['label']} ({how}) | {row['seconds']:.2f} | {row['first']:.2f} | "
                        f"{100 * row['total']:.2f} % "
                        f"({100 * row['total_est']:.2f} %) | {100 * row['e1']:.2f} % | {100 * row['e2']:.1f} % "
                        f"({100 * row['e2_est']:.1f} %) | {100 * row['e2_est_ref']:.1f} % | "
                        f"{100 * row['e2_nonpositive']:.2f} % | {r['peak_rss_mb']:.0f} |")
    print(f"{a.res}x{a.res}, events 1 + 2, worst detector; in brackets the render's own error estimate "
          "(relative to the render's own values). 'e2 estimate, reference's values': the same per-pixel "
          "errors relative to the reference's values; 'e2 <= 0': share of e2 pixels at or below zero.\n")
    print("| scene | configuration | warm time (s) | first render (s) | total RMS (estimate) | e1 RMS | "
          "e2 RMS (estimate) | e2 estimate, reference's values | e2 <= 0 | peak RSS of the scene's process (MB) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
