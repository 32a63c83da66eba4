"""The targets: athene_flat at 1500 x 1500, four detectors, events 1 + 2; brute force and the
quality presets against the reference (error, time, peak memory), and the CLI end to end."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np

from .harness import (CACHE, DETS, ROOT, athene_reference, e1_reference_quadrature, peak, preset_job, rel_error,
                      worst_error)
from .report import fmt, median, pct, table

TITLE = "Targets: 1500², four detectors, events 1 + 2 (athene_flat)"


def target_configs(b):
    """(label, job fields) of the configurations measured."""
    q = {"detector_sampling": "quadrature"}
    configs = [("brute force: independent, 7 spp", {"spp": 7, "options": {}}),
               ("brute force: independent, 8 spp", {"spp": 8, "options": {}}),
               ("brute force, stratified 4 points, 1 spp", {"spp": 1, "options": {
                   "detector_sampling": "stratified", "detector_samples": 4, "bounce_detector_samples": 1}}),
               ("preset draft", {**preset_job("draft"), "options": {}}),
               ("preset default", {**preset_job("default"), "options": {}}),
               ("default without bounce filter/top-up", {**preset_job("default"),
                                                        "options": {"bounce_filter": 0.0, "bounce_min": 0.0}}),
               ("quadrature T=4, every pixel bounces, no filter", {"spp": 1, "options": {
                   **q, "quadrature_triangles": 4}})]
    if b.settings["targets"]["reference_preset"]:
        configs.append(("preset reference", {**preset_job("reference"), "options": {}}))
    return configs


def validate_quadrature_reference(b, res):
    """Largest relative deviation of the quadrature reference from Eq. 5 by an independent disc
    quadrature, at 9 pixels x 4 detectors."""
    from elo_mitsuba.analysis.first_event import disc_integral
    from elo_mitsuba.physics import get_material

    ref = e1_reference_quadrature(b, "athene_flat", res)
    mat = get_material("Ti-6Al-4V")
    wd, field, dh, dw = 400.0, 80.0, 272.0, 127.0
    centres = {"right": (dw, 0, dh), "left": (-dw, 0, dh), "back": (0, dw, dh), "front": (0, -dw, dh)}
    worst = 0.0
    for j in (0, res // 2, res - 1):
        for i in (0, res // 2, res - 1):
            x = -field / 2 + (i + 0.5) * field / res
            y = field / 2 - (j + 0.5) * field / res
            p = np.array([x, y, 0.0])
            for d, c in centres.items():
                c = np.array(c, float)
                exact = disc_integral(p, p - np.array([0, 0, wd]), [0, 0, 1], c, -c, 25.0, mat, n_r=48, n_phi=192)
                worst = max(worst, abs(ref[d][j, i] / exact - 1))
    return worst


def _measure(b, configs, ref, res, rounds):
    """Every configuration, interleaved over ``rounds``: times, peak memory, settings, errors."""
    results = {c[0]: {"times": [], "rss": [], "err": None} for c in configs}
    for rnd in range(rounds):
        for label, how in configs:
            if label == "preset reference" and rnd > 0:
                continue
            slow = label == "preset reference" or (how.get("spp") or 1) > 8
            o, ch = b.render("target", {"kind": "render", "scene": "athene_flat", "params": {"res": res},
                                        "events": 2, **how, "seeds": [0] if slow else [0, 1, 2]})
            r = results[label]
            r["times"].append(median(o["times"]))
            r["rss"].append(peak(o))
            r["spp"], r["settings"] = o["spp"], o["settings"]
            if r["err"] is None:
                e1 = worst_error(ch, ref, lambda d: f"{d}.e1")
                tot = worst_error(ch, ref, lambda d: d)
                e2 = max(rel_error(ch[f"{d}.e2"] + ref[f"{d}.e1"], ref[d])[0] for d in DETS)
                r["err"] = (e1, tot, e2)
        b.log(f"targets round {rnd} done")
    return results


def _cli_times(qualities, res, repeat=5):
    """(quality, median seconds, exit status) of ``elo-mitsuba render`` in a new process (kernels
    cached), over ``repeat`` runs per quality taken in turn: a single run on a shared machine
    swings by 2x (a new process's first touch of fresh memory costs what other jobs left)."""
    times = {q: [] for q in qualities}
    status = {q: 0 for q in qualities}
    for _ in range(repeat):
        for q in qualities:
            out = CACHE / f"cli_{q}.exr"
            t = time.perf_counter()
            p = subprocess.run([sys.executable, "-m", "elo_mitsuba", "render", "athene_flat", "-o", str(out),
                                "--resolution", str(res), "--quality", q, "--overwrite", "--quiet"],
                               cwd=ROOT, capture_output=True, text=True)
            times[q].append(time.perf_counter() - t)
            status[q] = status[q] or p.returncode
    return [(q, median(times[q]), status[q]) for q in qualities]


def _settings_text(st):
    """The options a configuration rendered with, in a few words."""
    return (f"{st['detector_sampling']}"
            + (f" T={st['quadrature_triangles']}" if st["detector_sampling"] == "quadrature" else "")
            + f", f={st['bounce_fraction']:.3g}, k={st['bounce_samples']}"
            + (f", filter {st['bounce_filter']:g} mm" if st["bounce_filter"] else "")
            + (f", min {st['bounce_min']:g}" if st["bounce_min"] else ""))


def run(b):
    """Measure the configurations (results kept in ``b.target_results``); the section's Markdown."""
    cfg, refs = b.settings["targets"], b.settings["references"]
    res, rounds = cfg["res"], cfg["rounds"]
    ref = athene_reference(b, res)
    val = validate_quadrature_reference(b, res)
    configs = target_configs(b)
    results = b.target_results = _measure(b, configs, ref, res, rounds)
    cli = _cli_times(cfg["cli_qualities"], res)
    rows = []
    for label, _ in configs:
        r = results[label]
        (e1, tot, e2) = r["err"]
        rows.append([label, r["spp"], _settings_text(r["settings"]), fmt(median(r["times"]), 3), fmt(max(r["rss"])),
                     pct(e1[0]), pct(e1[1]), pct(tot[0]), pct(tot[1]), pct(e2)])
    text = [f"athene_flat (flat plate in the chamber), {res}x{res}, four detectors, events 1 + 2 in one pass. "
            f"Reference: 1st event by the Appendix-A quadrature with 96 triangles (no detector can be occluded from "
            f"the plate, checked by the integrator's occlusion analysis; deviation from an independent disc "
            f"quadrature of Eq. 5 at 9 pixels x 4 detectors: {val:.1e}); events 2 from a "
            f"{refs['e2_res']}² render with {refs['e2_spp']} spp, bilinearly interpolated. "
            "Time = median render time (EloScene.render, scene loaded, kernels cached) over "
            f"{rounds} interleaved round(s) of 1-3 renders; memory = peak RSS of one render (in a process that has "
            "imported Mitsuba and loaded the scene).", "",
            table(["configuration", "spp", "settings", "time (s)", "peak RSS (MB)", "1st event RMS", "1st event p99",
                   "total RMS", "total p99", "events 2 error (RMS, of total)"], rows), "",
            "Command line end to end (new process: import, scene load, kernels from the cache, render, EXR; "
            "median of 5 runs): " +
            ", ".join(f"`--quality {q}` {t:.1f} s (exit {rc})" for q, t, rc in cli), "",
            table(["command line, new process", "end to end (s)", "warm render (s)", "ratio (target <= 2)"],
                  _cli_rows(cli, results))]
    return "\n".join(text)


def _cli_rows(cli, results):
    """``elo-mitsuba render athene_flat --quality Q`` in a new process against the warm render of
    the same preset (EloScene.render with the scene loaded): the cost of the command line itself."""
    rows = []
    for q, t, rc in cli:
        warm = results.get(f"preset {q}")
        w = median(warm["times"]) if warm else None
        rows.append([f"`render athene_flat --quality {q}`" + ("" if rc == 0 else f" (exit {rc})"), fmt(t, 3),
                     fmt(w, 3) if w else "-", f"{t / w:.1f}" if w else "-"])
    return rows
