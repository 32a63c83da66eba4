"""Events 1-4: the share of the signal each event adds, its per-pixel noise, and its cost."""

from __future__ import annotations

import numpy as np

from elo_mitsuba.schema import event_channel

from .harness import DETS
from .report import fmt, median, pct, table

TITLE = "Events 1-4: what they add and cost"
SCENES = ("athene_flat", "corrugated_sheet", "melt_plate")
OPTIONS = {"detector_sampling": "quadrature", "quadrature_triangles": 8}


def run(b):
    """Measure events 1-4 on every scene; the section's Markdown."""
    cfg = b.settings["events"]
    res, spp, cost_res = cfg["res"], cfg["spp"], cfg["cost_res"]
    out = [f"Events 1-4 at {res}x{res}, {spp} spp (quadrature T=8 for the 1st event, independent later): "
           "share of the signal (image mean over all detectors), per-pixel noise of that event at 1 spp "
           "(relative to the total, from two independent renders), and the cost of each extra event "
           f"(time at 1 spp, {cost_res}² relative to events=1).", ""]
    rows = []
    for scene in SCENES:
        runs = []
        for seed in (1, 2):
            _, ch = b.render(f"ev_{scene}_{seed}", {
                "kind": "render", "scene": scene, "params": {"res": res}, "events": 4, "spp": spp,
                "options": OPTIONS, "seeds": [seed], "warm": seed == 1})
            runs.append(ch)
        total = sum(runs[0][d].astype(np.float64) + runs[1][d] for d in DETS) / 2
        costs = []
        for events in (1, 2, 3, 4):
            o = b.job({"kind": "render", "scene": scene, "params": {"res": cost_res}, "events": events,
                       "spp": 1, "options": OPTIONS, "seeds": [0, 1, 2]})
            costs.append(median(o["times"]))
        for k in range(1, 5):
            ek = [sum(r[event_channel(d, k)].astype(np.float64) for d in DETS) for r in runs]
            share = float((ek[0] + ek[1]).mean() / 2 / total.mean())
            noise = float(np.sqrt(np.mean(((ek[0] - ek[1]) / np.sqrt(2) / total) ** 2)) * np.sqrt(spp))
            max_share = float(np.percentile((ek[0] + ek[1]) / 2 / total, 99))
            rows.append([scene, k, pct(share), pct(max_share), pct(noise), fmt(costs[k - 1] / costs[0], 3)])
        b.log(f"events {scene} done")
    out.append(table(["scene", "event", "share of signal (mean)", "share, 99th pct pixel",
                      "per-pixel noise at 1 spp (of total)", "time with events 1..k / events=1"], rows))
    return "\n".join(out)
