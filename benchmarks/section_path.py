"""The alternative a user has: four renders of Mitsuba's built-in ``path`` integrator (one
detector emitting each), and how much faster ours is at equal error."""

from __future__ import annotations

import numpy as np

from .harness import DETS, athene_reference, rel_error
from .report import fmt, median, pct, table

TITLE = "The alternative: four renders of Mitsuba's `path` integrator"


def run(b):
    """Measure ``path`` against the reference; compare with ``b.target_results``. The Markdown."""
    cfg = b.settings["path"]
    res, spps = cfg["res"], cfg["spp_list"]
    ref = athene_reference(b, res)
    rows, per_spp = [], {}
    for spp in spps:
        times, errs = [], []
        for d in DETS:
            o, ch = b.render(f"path_{d}", {"kind": "path", "scene": "athene_flat", "params": {"res": res},
                                           "events": 2, "detector": d, "spp": spp, "seeds": [0, 1, 2]})
            times.append(median(o["times"]))
            errs.append(rel_error(ch[d], ref[d]))
        t = sum(times)
        rms = max(e[0] for e in errs)
        per_spp[spp] = (t, rms)
        rows.append([spp, fmt(t, 3), fmt(t * 1500 * 1500 / (res * res), 3), pct(rms), pct(max(e[1] for e in errs))])
        b.log(f"path spp {spp} done")
    # error ~ a / sqrt(spp): fit on the largest spp
    spp_max = spps[-1]
    a = per_spp[spp_max][1] * np.sqrt(spp_max)
    spp_1pct = (a / 0.01) ** 2
    t_per_spp_1500 = per_spp[spp_max][0] / spp_max * 1500 * 1500 / (res * res)
    t_path_1pct = t_per_spp_1500 * spp_1pct
    ours = [(label, r) for label, r in b.target_results.items() if r["err"] and r["err"][1][0] <= 0.01]
    best = min(ours, key=lambda x: median(x[1]["times"])) if ours else None
    text = [f"athene_flat, Mitsuba's `path` integrator (max_depth 3, no Russian roulette before depth 1000, "
            f"MIS), one render per detector with only that detector emitting (on both faces: two back-to-back emitter discs), {res}x{res}; error of the total "
            "channel (events 1 + 2) against the same reference as 'targets' (at this resolution). "
            "Time = sum of the four renders; scaled to 1500² by pixel count.", "",
            table(["spp", f"time {res}² (s, 4 renders)", "time scaled to 1500² (s)", "total RMS (worst detector)",
                   "total p99"], rows), "",
            f"Fit RMS = {a:.3f}/sqrt(spp): `path` needs {spp_1pct:.0f} spp for 1% RMS on the total channels, "
            f"i.e. {t_path_1pct:.1f} s for four renders at 1500²."]
    if best is not None:
        res_targets = b.settings["targets"]["res"]
        t_ours = median(best[1]["times"]) * (1500 * 1500 / (res_targets * res_targets))
        ratio = t_path_1pct / t_ours
        b.facts["path"] = {"ratio": ratio, "t_path": t_path_1pct, "t_ours": t_ours, "label": best[0],
                           "spp_path": spp_1pct}
        text.append(f"Ours at <= 1% total RMS: '{best[0]}' in {t_ours:.2f} s at 1500² "
                    f"(total RMS {pct(best[1]['err'][1][0])}): **{ratio:.0f}x faster** than the four `path` renders.")
    return "\n".join(text)
