"""The ray-cast ceiling: Mitsuba's raw ray-cast throughput on each scene, and our integrator's
time per sample as a fraction of the time the same rays take when cast raw."""

from __future__ import annotations

from .report import fmt, median, pct, table

TITLE = "The ray-cast ceiling"
SCENES = ("flat_plate", "athene_flat", "corrugated_sheet", "melt_plate")
#: The configuration the paired (one-process) measurement and the summary use.
EVERY_RAY = "brute force, every shadow ray cast"
#: (label, job fields) of the configurations measured against the ceiling.
CONFIGS = (("brute force (independent)", {"options": {}}),
           (EVERY_RAY, {"options": {"occlusion_analysis": False}}),
           ("default preset", {"quality": "default", "options": {}}))
#: Columns of the raw ray-cast table (keys of the worker's ``raw`` rates).
RAW_COLUMNS = ("beam rays (ray_intersect)", "beam rays (preliminary)", "bounce rays (ray_intersect)",
               "shadow rays from 1st hits", "shadow rays from bounce hits")
PAIRED = ("rays only", "skeleton", "ours")


def ceiling_time(counts, rates, preliminary=False):
    """Seconds per sample the rays of one configuration take when cast raw.

    Parameters
    ----------
    counts : tuple of dict
        Rays cast per sample (``intersections``, ``shadow_rays``) with the configuration's events,
        and with the 1st event only (its shadow rays are the ones from 1st hits).
    rates : dict
        Rays per second of each kind (the worker's ``raw`` job).
    preliminary : bool
        Price intersections as bare hits (``ray_intersect_preliminary``).
    """
    all_counts, first = counts
    ni, ns = all_counts["intersections"], all_counts["shadow_rays"]
    ns1 = first["shadow_rays"]
    ns2 = max(ns - ns1, 0.0)
    kind = "preliminary" if preliminary else "ray_intersect"

    def cost(count, key):
        return count / rates[key] if count > 0 and rates[key] > 0 else 0.0

    return (cost(1.0, f"beam rays ({kind})") + cost(ni - 1.0, f"bounce rays ({kind})")
            + cost(ns1, "shadow rays from 1st hits") + cost(ns2, "shadow rays from bounce hits"))


def _interleaved(b, scene, events, cfg):
    """Raw ray casts and our renders, alternating: (median rates, ray counts, times per config)."""
    res, spp = cfg["res"], cfg["spp"]
    raws, ours, counts = [], {label: [] for label, _ in CONFIGS}, {}
    for rep in range(cfg["rounds"]):
        raws.append(b.job({"kind": "raw", "scene": scene, "params": {"res": res}, "spp": 4,
                           "repeat": cfg["raw_repeat"]}))
        for label, how in CONFIGS:
            o = b.job({"kind": "render", "scene": scene, "params": {"res": res}, "events": events, "spp": spp,
                       **how, "seeds": [0, 1, 2], "count_rays": rep == 0})
            ours[label].append(median(o["times"]) / o["spp"] * spp)  # per spp of this table
            if rep == 0:
                c1 = b.job({"kind": "render", "scene": scene, "params": {"res": res}, "events": 1, "spp": 1,
                            **how, "seeds": [0], "count_rays": True})["ray_counts"]
                counts[label] = (o["ray_counts"], c1)
    rates = {k: median([r["rates"][k] for r in raws]) for k in raws[0]["rates"]}
    return rates, counts, ours


def _paired_row(b, scene, events, cfg, counts):
    """Raw rays, then ours, the skeleton and the rays only, back to back in one process."""
    res, spp = cfg["res"], cfg["spp"]
    n = res * res * spp
    sk = b.job({"kind": "skeleton", "scene": scene, "params": {"res": res}, "events": events, "spp": spp,
                "repeat": cfg["skeleton_repeat"]})
    raw = [ceiling_time(counts, r) * n for r in sk["raw_rates"]]
    paired = {k: [c / t for c, t in zip(raw, sk["times"][k])] for k in PAIRED}
    t_sk, t_us, t_min = (median(sk["times"][k]) for k in ("skeleton", "ours", "rays only"))
    b.facts.setdefault("skeleton", {})[scene] = {k: (median(v), min(v), max(v)) for k, v in paired.items()}
    return ([scene, events, fmt(median(raw) / n * 1e9), fmt(t_min / n * 1e9), fmt(t_sk / n * 1e9),
             fmt(t_us / n * 1e9)]
            + [f"{pct(median(paired[k]))} ({pct(min(paired[k]))}-{pct(max(paired[k]))})" for k in PAIRED])


def run(b):
    """Measure the ceiling on every scene; the section's Markdown."""
    cfg = b.settings["ceiling"]
    res, spp = cfg["res"], cfg["spp"]
    n = res * res * spp
    rows, raw_rows, skel_rows = [], [], []
    for scene in SCENES:
        events = 2 if scene == "athene_flat" else 1
        rates, counts, ours = _interleaved(b, scene, events, cfg)
        raw_rows.append([scene] + [fmt(rates[k] / 1e6) if rates[k] > 0 else "-" for k in RAW_COLUMNS])
        for label, _ in CONFIGS:
            all_counts = counts[label][0]
            t_ceiling = ceiling_time(counts[label], rates)
            t_pre = ceiling_time(counts[label], rates, preliminary=True)
            t_ours = median(ours[label]) / n
            rows.append([scene, events, label, fmt(all_counts["intersections"], 3),
                         fmt(all_counts["shadow_rays"], 3), fmt(t_ours * 1e9), fmt(t_ceiling * 1e9),
                         pct(t_ceiling / t_ours), pct(t_pre / t_ours)])
            b.facts.setdefault("ceiling", {})[(scene, label)] = t_ceiling / t_ours
            if label == EVERY_RAY:
                b.facts.setdefault("ceiling_ns", {})[scene] = t_ceiling * 1e9
        skel_rows.append(_paired_row(b, scene, events, cfg, counts[EVERY_RAY]))
        b.log(f"ceiling {scene} done")
    text = [f"Raw ray casting (M rays/s, median of interleaved repeats), {res}x{res}, 4 rays per pixel:",
            "", table(["scene", "beam (ray_intersect)", "beam (preliminary)", "bounce (ray_intersect)",
                       "shadow from 1st hits", "shadow from bounce hits"], raw_rows), "",
            f"Our integrator ({res}x{res}, {spp} spp; time per sample = render time / samples, median of 3 renders "
            "x repeats); the ceiling is the time the same rays take when cast raw "
            "(`ray_intersect` with the surface interaction we use; 'vs preliminary' = bare hits only):", "",
            table(["scene", "events", "configuration", "intersections/sample", "shadow rays/sample",
                   "ns/sample", "ceiling ns/sample", "fraction of ceiling", "vs preliminary"], rows), "",
            "The same measured in ONE process, every shadow ray cast (configuration 'brute force, every shadow "
            "ray cast'): each repetition casts the raw rays and then renders, so that every ratio pairs two "
            f"timings taken seconds apart under the same machine load ({cfg['skeleton_repeat']} repetitions; "
            "ns per sample are medians, fractions are the median (min-max) of the paired ratios). This is the "
            "figure of the summary; the table above pairs separate processes minutes apart and swings by "
            "+-15% between runs. Columns: the raw ceiling (rays cast in separate kernels from rays "
            "held in memory); the same rays in ONE kernel (beam, one shadow ray per detector and event to a "
            "point on it, a cosine bounce; no sampler object, no emitter pdf, one output channel): the cost "
            "of tracing inside a megakernel; a skeleton of our integrator in Mitsuba's render loop (same rays, "
            "Mitsuba's sampler, emitter sampling with pdf, the same film channels; no g_BSE, no BSDF sampling): "
            "Mitsuba's per-sample cost an integrator plugin cannot remove; ours:", "",
            table(["scene", "events", "raw ceiling", "rays only, one kernel", "skeleton in mi.render", "ours",
                   "one kernel / ceiling", "skeleton / ceiling", "ours / ceiling"],
                  skel_rows)]
    return "\n".join(text)
