"""Accuracy against time, 1st event: per-pixel error against a converged reference for spp and the
detector strategies (independent, stratified, Appendix-A quadrature) on three scenes."""

from __future__ import annotations

from .harness import e1_reference, worst_error
from .report import fmt, median, pct, table

TITLE = "Accuracy against time (1st event)"
SCENES = ("flat_plate", "corrugated_sheet", "melt_plate")
_QUAD = {"detector_sampling": "quadrature"}
#: (label, spp, options) of the strategies after the independent ones.
STRATEGIES = (("stratified N=4", 1, {"detector_sampling": "stratified", "detector_samples": 4}),
              ("stratified N=4", 4, {"detector_sampling": "stratified", "detector_samples": 4}),
              ("stratified N=16", 1, {"detector_sampling": "stratified", "detector_samples": 16}),
              ("quadrature T=4", 1, {**_QUAD, "quadrature_triangles": 4}),
              ("quadrature T=8", 1, {**_QUAD, "quadrature_triangles": 8}),
              ("quadrature T=24", 1, {**_QUAD, "quadrature_triangles": 24}),
              ("quadrature T=8", 4, {**_QUAD, "quadrature_triangles": 8}),
              ("quadrature T=8, ray per triangle", 1, {**_QUAD, "quadrature_triangles": 8,
                                                       "quadrature_visibility": "triangle"}))


def run(b):
    """Measure every strategy on every scene; the section's Markdown."""
    cfg = b.settings["accuracy"]
    res = cfg["res"]
    out = [f"1st event only (events=1), {res}x{res} (per-pixel errors do not depend on the resolution when "
           "the beam is a single ray; time scales with pixels x spp, see Scaling). Reference: stratified, "
           f"16 points per detector, {b.settings['references']['e1_spp']} spp. Time = median of 3 renders.", ""]
    configs = [("independent", spp, {}) for spp in cfg["independent_spp"]] + list(STRATEGIES)
    for scene in SCENES:
        ref = e1_reference(b, scene, res)
        rows = []
        for label, spp, opts in configs:
            o, ch = b.render(f"acc_{scene}", {"kind": "render", "scene": scene, "params": {"res": res}, "events": 1,
                                              "spp": spp, "options": opts, "seeds": [0, 1, 2]})
            rms, p99 = worst_error(ch, ref, lambda d: d)
            t = median(o["times"])
            rows.append([label, spp, fmt(t, 3), fmt(t * (1500 * 1500) / (res * res), 3), pct(rms), pct(p99)])
        out += [f"**{scene}**", "", table(["detector integration (1st event)", "spp", f"time {res}² (s)",
                                             "time scaled to 1500² (s)", "RMS error", "p99 error"], rows), ""]
        b.log(f"accuracy {scene} done")
    return "\n".join(out)
