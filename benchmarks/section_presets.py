"""The quality presets on every shipped scene: time, error per event channel and total, and the
accuracy of the render's own error estimate.

Each scene runs in its own process (a ``presets`` job of :mod:`benchmarks.worker`, the function
:func:`measure_scene`): draft, default, reference and unbiased at the section's resolution, each
against a reference of the unbiased preset with ``REFERENCE_FACTOR`` x its samples, 96 quadrature
triangles and no filter (independent seed). Errors per pixel as everywhere in benchmarks/
(|x - ref| / max(ref, 5 % of the mean)); the reference's own noise (its error estimate) is
listed. "estimate / actual" is sqrt(sum err_est^2 / (sum (x - ref)^2 - sum err_ref^2)) over the
pixels of the channel: 1 when the per-render estimate is right on average.
Alone: ``python -m benchmarks --only presets``.
"""

from __future__ import annotations

import time

import numpy as np

from elo_mitsuba.schema import event_channel

from .harness import DETS, rel_error
from .report import fmt, pct, table

TITLE = "Presets on every scene: error per event and total, and the error estimate's own accuracy"
#: The shipped scenes and their default events (the chamber scenes: the 2nd event on relief).
SCENES = ("flat_plate", "athene_flat", "corrugated_sheet", "melt_plate", "corrugated_chamber", "melt_chamber",
          "shield_chamber")
PRESETS = ("draft", "default", "reference", "unbiased")
#: The reference renders the unbiased preset with this many times its samples.
REFERENCE_FACTOR = 8


def measure_scene(job):
    """One scene: every preset timed (a warm-up render first) and compared with the reference."""
    import elo_mitsuba as em

    em.ensure_variant()
    scene = em.load_scene(job["scene"], res=job["res"])
    out = {"scene": job["scene"], "res": job["res"], "presets": {}}
    spp_ref = scene.set_quality("unbiased") * REFERENCE_FACTOR
    # the far field's mean SAMPLED in the reference (unbiased): the presets' tabulated one is an
    # integral whose small error the comparison must see, not share
    far = dict(far_table=False, far_field=4) if scene.options.far_table else {}
    scene.configure(quadrature_triangles=96, **far)
    t = time.perf_counter()
    ref = scene.render(spp=spp_ref, seed=90001, progress=False)
    out["reference_s"] = time.perf_counter() - t
    names = list(ref.channels)
    out["reference_noise"] = {n: ref.error_summary()[n].get("rms_rel") for n in names}
    for preset in PRESETS:
        scene.render(quality=preset, seed=7, progress=False)  # compile and warm up
        t = time.perf_counter()
        r = scene.render(quality=preset, seed=11, progress=False)
        seconds = time.perf_counter() - t
        row = {"seconds": seconds, "spp": r.metadata["spp"], "bounce_filter": scene.options.bounce_filter,
               "channels": {}}
        for n in names:
            x = r.channels[n].astype(np.float64)
            f = ref.channels[n].astype(np.float64)
            rms, p99 = rel_error(x, f)
            floor = np.maximum(f, 0.05 * max(float(f.mean()), 1e-300))
            worst = float(np.max(np.abs(x - f) / floor))
            s = r.error_summary()[n]
            c = {"rms": rms, "p99": p99, "max": worst, "status": s["status"], "est_rms": s.get("rms_rel")}
            if n in r.errors and n in ref.errors:
                actual = float(np.sum((x - f) ** 2) - np.sum(ref.errors[n].astype(np.float64) ** 2))
                est = float(np.sum(r.errors[n].astype(np.float64) ** 2))
                c["est_over_actual"] = float(np.sqrt(est / actual)) if actual > 0 else None
            row["channels"][n] = c
        out["presets"][preset] = row
    return out


def _worst(row, suffix):
    """Worst detector of a channel kind ('' = total, '.e1', ...): (rms, p99, max, estimate/actual range)."""
    cs = [row["channels"][f"{d}{suffix}"] for d in DETS if f"{d}{suffix}" in row["channels"]]
    ratios = [c["est_over_actual"] for c in cs if c.get("est_over_actual") is not None]
    return (max(c["rms"] for c in cs), max(c["p99"] for c in cs), max(c["max"] for c in cs),
            (min(ratios), max(ratios)) if ratios else None, cs[0]["status"])


def run(b):
    """Measure the presets on every scene; the section's Markdown."""
    res = b.settings["presets"]["res"]
    results = []
    for scene in SCENES:
        b.log(f"presets on {scene} ...")
        results.append(b.job({"kind": "presets", "scene": scene, "res": res}, timeout=7200))
    b.facts["presets"] = results
    out = [f"Each shipped scene at {res}x{res} (80 mm field, zeta25), its default events, the presets as "
           "`render --quality` chooses them for that scene (relief under the beam: no bounce filter, unless "
           "the far field's mean is tabulated and events 1 + 2 are traced, where the filter averages the "
           "residual about it), seed 11, "
           f"after a warm-up render. Reference: the unbiased preset with {REFERENCE_FACTOR}x its samples, "
           "96 triangles, no filter, the far field's mean sampled (far_field = 4) where the presets tabulate it. Error per pixel relative to the reference (floor 5 % of its mean), worst "
           "detector: RMS, 99th percentile, worst pixel. 'estimate/actual': the render's own error estimate "
           "(two independent halves) over the actual RMS error, range over detectors (1 = right; deterministic "
           "channels have no sampling error and say so).", ""]
    rows = []
    for r in results:
        for preset in PRESETS:
            p = r["presets"][preset]
            kinds = [("total", "")] + [(f"e{k}", event_channel("", k)) for k in range(1, 5)
                                       if event_channel("right", k) in p["channels"]]
            for label, suffix in kinds:
                rms, p99, worst, ratio, status = _worst(p, suffix)
                est = ("deterministic" if status == "deterministic" else
                       "-" if ratio is None else f"{ratio[0]:.2f}-{ratio[1]:.2f}")
                rows.append([r["scene"], preset, label, fmt(p["seconds"]) + " s" if label == "total" else "",
                             pct(rms), pct(p99), pct(worst), est])
    out.append(table(["scene", "preset", "channel", "time", "RMS", "99 %", "worst pixel", "estimate/actual"], rows))
    worst_rows = []
    for preset in PRESETS:
        w = max(((_worst(r["presets"][preset], "")[0], r["scene"]) for r in results))
        worst_rows.append([preset, w[1], pct(w[0])])
    out += ["", "Worst scene per preset (the figure README and `render --help` quote):", "",
            table(["preset", "worst scene", "total RMS"], worst_rows)]
    noise = max(v for r in results for v in r["reference_noise"].values() if v is not None)
    out += ["", f"The references' own estimated noise: at most {pct(noise)} RMS per pixel (in the channel above)."]
    return "\n".join(out)
