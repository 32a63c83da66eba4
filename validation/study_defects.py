"""Heights at the defects (issue 25): a rough layer with pores and bumps, a layer with steps, and
whether the error bars cover the error.

For each surface, rendered with the ATHENE beam blur (0.27 mm FWHM) and 1 % Gaussian noise on every
object and flat pixel: the height RMSE (mean removed) of Eq. 26 + integration, the model gradient +
integration (the inversion's start) and ``invert`` (with its local refinement), overall, within
1 mm of the defects (a pore's or bump's rim, a cliff) and beyond; the steps as recovered; the slope
bias over the flat areas (mean gradient error of the model gradient, absolute); and the calibration
of ``height_error`` and of the model gradient's ``dzdx_sigma``/``dzdy_sigma``: the share of pixels
whose actual error lies within 1x and 2x the stated one (a calibrated Gaussian error bar: 68 % and
95 %).

Rows D1-D4 of validation/REPORT.md (``python -m validation --only defects``; about 3 min on 2 cores,
a figure per surface). ``python -m validation.study_defects [--res 400] [--out out/defects.md]`` writes
the same measurements as a table with the steps and every region's outcome; ``--seeds 1,2,3`` repeats
each surface under other noise seeds (one render) and tabulates the steps and the rough layer per
seed, and, with three seeds or more, what they say of the rough layer in expectation
(:func:`expected_change`); ``--noise 0.0025`` measures at another noise level (sixteen recordings
averaged), and ``--shared-noise`` how much of each seed's near ratio is the start's integrated noise
that the inversion keeps (:func:`shared_noise_lines`).
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import numpy as np

from .tools import coverage

NAMES = ("right", "left", "back", "front")
#: Samples per pixel of the object's render, the synthetic measurement. A real measurement has no
#: Monte Carlo error, and the simulated one must not carry more than the 1 % noise added to it where
#: it is judged: at the pores of the rough layer (1500², 0.27 mm beam, default preset, stratified)
#: 16 spp leave 3.6 % per pixel (5.9 % with independent samples), four times the spp halve that.
#: Measured there: within 1 mm of the defects ``invert`` ends at 0.56 of its start on 16-spp
#: renders and at 0.47 on 64-spp ones. The flat plate, smooth, keeps the preset's count (0.17 %).
MEASUREMENT_SPP = 64
#: Where around each defect of the rough layer the seeds' mean change is shown (mm from its rim,
#: outwards; up to 0: inside): the rim, where the beam blur mixes the normals, and beyond it, where
#: the start is already close and a refinement's heights can only add their own noise.
RINGS_MM = ((-np.inf, 0.0), (0.0, 0.2), (0.2, 0.4), (0.4, 1.0))


def _rmse(h, truth, sel=None):
    e = (h - np.mean(h)) - (truth - np.mean(truth))
    if sel is not None:
        e = e[sel]
    return float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")


@functools.lru_cache(maxsize=1)
def _render_pair(xml, res, layout):
    """The object's and the flat plate's renders (the noise is added by the caller): the last pair is
    kept (keyed on the scene's path, resolution and layout; the objects' meshes are deterministic), so
    that measuring one surface under several noise seeds renders it once."""
    import elo_mitsuba as em

    out = []
    for scene, spp in ((xml, MEASUREMENT_SPP), ("flat_plate", None)):
        s = em.load_scene(scene, res=res, fwhm=0.27, layout=layout)
        out.append(s.render(quality="default", spp=spp, events=1, seed=3, progress=False))
        del s  # a live scene slows the next one's renders (docs/rendering.md)
    return out


def step_ok(step: dict) -> bool:
    """A step recovered within 10 % of the truth's step (issue 25), both measured by the same medians
    (:func:`elo_mitsuba.objects.stepped_layer.step_height`; the truth's differs from the nominal
    cliff by the dome and the roughness, up to +3 %).

    Examples
    --------
    >>> step_ok({"truth": 0.516, "invert": 0.56}), step_ok({"truth": 0.516, "invert": 0.577})
    (True, False)
    """
    return bool(abs(step["invert"] - step["truth"]) <= 0.1 * abs(step["truth"]))


def seed_table(results) -> list[str]:
    """Markdown lines: each step as ``invert`` recovers it under each noise seed, with the mean, the
    spread (sample standard deviation) over the seeds, and the mean's error in proportion to the
    truth's step (negative: recovered too small): what the noise moves and what it does not.

    Examples
    --------
    >>> r = [{"seed": k, "steps": [{"nominal": 0.5, "truth": 0.516, "invert": v}]} for k, v in ((1, 0.57), (2, 0.58))]
    >>> seed_table(r)[-1]
    '| +0.5 | +0.516 | +0.570 | +0.580 | +0.575 | 0.007 | +11.4 % |'
    """
    seeds = [r["seed"] for r in results]
    lines = ["| step (mm) | truth | " + " | ".join(f"seed {k}" for k in seeds) + " | mean | spread | mean vs truth |",
             "|---" * (len(seeds) + 5) + "|"]
    for j, p in enumerate(results[0]["steps"]):
        v = np.array([r["steps"][j]["invert"] for r in results])
        spread = float(np.std(v, ddof=1)) if len(v) > 1 else float("nan")
        lines.append(f"| {p['nominal']:+.1f} | {p['truth']:+.3f} | " + " | ".join(f"{x:+.3f}" for x in v)
                     + f" | {v.mean():+.3f} | {spread:.3f} | {100 * (v.mean() - p['truth']) / p['truth']:+.1f} % |")
    return lines


def run_surface(kind: str, res: int, tmp: Path, *, layout: str, noise: float = 0.01, seed: int = 7) -> dict:
    """Render one surface (``rough``, ``steps``, ``hills`` or ``melt``), add noise, and measure."""
    from elo_mitsuba.analysis import surface_gradient
    from elo_mitsuba.analysis.inversion import invert_heights, start_heights
    from elo_mitsuba.analysis.model_gradient import model_gradient_refined
    from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    from elo_mitsuba.mesh import mesh_surface_height
    from elo_mitsuba.objects import melt_plate as mp
    from elo_mitsuba.objects import rough_layer as rl
    from elo_mitsuba.objects import stepped_layer as sl
    from elo_mitsuba.objects.hills import hills_height, hills_mesh
    from elo_mitsuba.scene_files import scenes_dir, write_object_scene

    if kind == "melt":
        heights = np.load(scenes_dir() / "meshes" / "melt_plate_height.npy").astype(float)

        def truth_fn(x, y):
            return mesh_surface_height(heights, mp.PIXEL_SIZE_MM, x, y)
        xml = "melt_plate"
    else:
        mesh, truth_fn = {"rough": (rl.rough_mesh, rl.rough_height), "steps": (sl.stepped_mesh, sl.stepped_height),
                          "hills": (hills_mesh, hills_height)}[kind]
        xml = write_object_scene(tmp, kind, mesh(80.0, res), overwrite=True)
    obj, flat = _render_pair(xml, res, layout)
    shape = obj.channels["right"].shape
    geo = ScanGeometry.from_metadata(obj.metadata, shape)
    truth = geo.landing_heights(truth_fn)
    pts, _ = geo.beam(truth)
    X, Y = pts[..., 0], pts[..., 1]
    rng = np.random.default_rng(seed)
    img = {n: obj.channels[n] * (1 + noise * rng.standard_normal(shape)) for n in NAMES}
    fl = {n: flat.channels[n] * (1 + noise * rng.standard_normal(shape)) for n in NAMES}
    pores = None
    if kind == "rough":
        near = rl.near_defects(X, Y)
        pores = rl.near_defects(X, Y, 0.0, kind="pore")
    elif kind == "steps":
        near = np.zeros(shape, bool)
        for p in sl.steps():
            near |= np.abs(sl.cliff_distance(p, X, Y)) <= 1.0
    else:
        near = np.zeros(shape, bool)
    e26 = surface_gradient(img, fl, geo.field_mm, *geo.symmetric_layout())
    mg = model_gradient_refined(img, fl, geo)  # the start `invert` takes
    h_start = start_heights(mg, geo)
    t0 = time.perf_counter()
    inv = invert_heights(img, fl, geo, start=mg, fwhm_mm=0.27)
    seconds = time.perf_counter() - t0
    out = {"kind": kind, "res": res, "layout": layout, "seed": seed, "noise": noise, "seconds": seconds,
           "stopped": inv.stopped,
           "near_share": float(near.mean())}
    for name, h in (("eq26", start_heights(e26, geo)), ("start", h_start), ("invert", inv.height)):
        out[name] = {"all": _rmse(h, truth), "near": _rmse(h, truth, near) if near.any() else float("nan"),
                     "far": _rmse(h, truth, ~near)}
    out["near_ratio"] = out["invert"]["near"] / out["start"]["near"] if near.any() else float("nan")
    if pores is not None:  # inside the pores, where the beam blur leaves least
        out["pores"] = {name: _rmse(h, truth, pores) for name, h in (("start", h_start), ("invert", inv.height))}
    # the heights' gain against the truth (a slope-response error of the model scales every height)
    t_c = truth - truth.mean()
    out["gain"] = float(np.sum(((inv.height - inv.height.mean()) - t_c) * t_c) / np.sum(t_c * t_c))
    # never worse than the start: the largest RMSE increase over 4 mm tiles. Heights are known up to
    # a constant; both are put on the truth's level by the start's mean error over the pixels the
    # inversion left as they were (where it left a tenth of the field or more; else each by its own
    # mean error), so that a tile it did not touch compares equal: the inversion's own mean would
    # move every such tile by the mean of what a refined pore changed (0.004 µm on the rough layer)
    same = np.abs(inv.height - h_start) <= 1e-9
    if same.mean() >= 0.1:
        e_st = h_start - truth - np.mean((h_start - truth)[same])
        e_inv = inv.height - truth - np.mean((h_start - truth)[same])
    else:
        e_st = h_start - truth - np.mean(h_start - truth)
        e_inv = inv.height - truth - np.mean(inv.height - truth)
    t = max(int(round(4.0 / (80.0 / res))), 1)
    hh, ww = (shape[0] // t) * t, (shape[1] // t) * t

    def tiles(e):
        return np.sqrt((e[:hh, :ww] ** 2).reshape(hh // t, t, ww // t, t).mean(axis=(1, 3)))
    change = tiles(e_inv) - tiles(e_st)
    worst = np.unravel_index(int(np.argmax(change)), change.shape)
    out["worst_tile_um"] = float(1e3 * change[worst])
    out["worst_tile_start_um"] = float(1e3 * tiles(e_st)[worst])
    out["tiles_worse"], out["tiles"] = int(np.sum(change > 1e-9)), int(change.size)  # > 1e-6 µm
    # each tile's mean squared error (um^2), for what several noise seeds say of it (expected_change)
    out["tile_mse"] = (1e6 * tiles(e_st) ** 2, 1e6 * tiles(e_inv) ** 2)
    if kind == "rough":  # each defect on its own (its rim and 1 mm around), errors on the same level
        # the errors with their means removed, for what a noise-free run shares with them (shared_noise_lines)
        out["_errors"] = (h_start - h_start.mean() - (truth - truth.mean()),
                          inv.height - inv.height.mean() - (truth - truth.mean()), near)
        out["defects"] = []
        for dd in rl.defects():
            beyond = np.hypot(X - dd["x"], Y - dd["y"]) - dd["radius"]  # distance from the rim, outwards
            m = beyond <= 1.0
            rings = [(beyond > lo) & (beyond <= hi) for lo, hi in RINGS_MM]
            # ... and on its own level (the neighbourhood's mean error removed): its shape, without
            # the start's long-wavelength offset there, which no local refinement can see
            out["defects"].append({"kind": dd["kind"], "radius_mm": float(dd["radius"]),
                                   "start": float(np.sqrt(np.mean(e_st[m] ** 2))),
                                   "invert": float(np.sqrt(np.mean(e_inv[m] ** 2))),
                                   "start_shape": float(np.std(e_st[m])), "invert_shape": float(np.std(e_inv[m])),
                                   "rings": [(1e6 * float(np.mean(e_st[k] ** 2)), 1e6 * float(np.mean(e_inv[k] ** 2)))
                                             if k.any() else None for k in rings]})
    # error bars (errors relative to the trusted field's level where parts float)
    d = inv.height - truth
    ref = ~inv.floating if inv.floating is not None and inv.floating.any() else np.ones(shape, bool)
    d = d - np.median(d[ref])
    every = np.ones(shape, bool)
    out["height_error"] = {"stated_rms_um": 1e3 * inv.height_error_rms,
                           "all": coverage(d, inv.height_error, every),
                           "near": coverage(d, inv.height_error, near) if near.any() else (np.nan, np.nan),
                           "noise_only": coverage(d, inv.height_error_noise, every),
                           **({"pores": coverage(d, inv.height_error, pores)} if pores is not None else {}),
                           "bias_rms_um": 1e3 * float(np.sqrt(np.mean(inv.height_error_bias ** 2)))}
    eps = 1e-3
    gx = (truth_fn(X + eps, Y) - truth_fn(X - eps, Y)) / (2 * eps)
    gy = (truth_fn(X, Y + eps) - truth_fn(X, Y - eps)) / (2 * eps)
    ok = ~mg.mask
    out["gradient_sigma"] = {"dzdx": coverage(mg.dzdx - gx, mg.dzdx_sigma, ok),
                             "dzdy": coverage(mg.dzdy - gy, mg.dzdy_sigma, ok)}
    flat_area = ok & ~near & (np.hypot(gx, gy) < 1e-3) if kind == "steps" else None
    if flat_area is not None and flat_area.any():
        out["slope_bias"] = (float(np.mean((mg.dzdx - gx)[flat_area])), float(np.mean((mg.dzdy - gy)[flat_area])))
    if kind == "steps":
        from elo_mitsuba.objects.stepped_layer import step_height, steps

        out["steps"] = [{"nominal": p["height_mm"],
                         **{k: step_height(h, geo.field_mm, p, coordinates=(X, Y)) for k, h in
                            (("truth", truth), ("start", h_start), ("invert", inv.height))}} for p in steps()]
    out["regions"] = [r.as_dict() for r in inv.regions]
    out["lifted"] = [p.as_dict() for p in inv.steps if p.status == "lifted"]
    out["searched"] = len(inv.steps)
    out["figure"] = (truth, h_start, inv)
    return out


def _worse(d, shape=False) -> int:
    key = "_shape" if shape else ""
    return sum(x["invert" + key] > x["start" + key] for x in d)


def defects_line(r) -> str:
    """Each defect of the rough layer on its own (its rim and 1 mm around) against the start: how many
    ``invert`` left worse, the range of the ratios and the worst defect; then how many are worse on
    their own level (the neighbourhood's mean error removed: the start's long-wavelength offset
    there, which a local refinement cannot see).

    Examples
    --------
    >>> d = [{"kind": "pore", "radius_mm": 0.3, "start": 0.02, "invert": 0.01, "start_shape": 0.02,
    ...       "invert_shape": 0.01},
    ...      {"kind": "bump", "radius_mm": 0.58, "start": 0.01336, "invert": 0.0135, "start_shape": 0.00466,
    ...       "invert_shape": 0.00363}]
    >>> defects_line({"defects": d})
    'each defect (rim + 1 mm) against the start: 1 of 2 worse, ratios 0.50-1.01 (the highest a bump of 0.58 mm radius, 13.4 -> 13.5 µm); on its own level (its mean error removed) 0 of 2 worse'
    """
    d = r["defects"]
    ratios = [x["invert"] / x["start"] for x in d]
    k = int(np.argmax(ratios))
    return (f"each defect (rim + 1 mm) against the start: {_worse(d)} of {len(d)} "
            f"worse, ratios {min(ratios):.2f}-{max(ratios):.2f} (the highest a {d[k]['kind']} of "
            f"{d[k]['radius_mm']:.2f} mm radius, {1e3 * d[k]['start']:.1f} -> {1e3 * d[k]['invert']:.1f} µm); "
            f"on its own level (its mean error removed) {_worse(d, True)} of {len(d)} worse")


def rough_seed_table(results) -> list[str]:
    """Markdown lines: the rough layer under each noise seed: the near ratio, the worst 4 mm tile and
    the defects left worse than the start, as they are and on their own level (:func:`defects_line`).

    Examples
    --------
    >>> r = {"seed": 1, "start": {"near": 0.012}, "invert": {"near": 0.006}, "near_ratio": 0.5,
    ...      "worst_tile_um": 0.006, "tiles_worse": 3, "tiles": 400, "defects": [
    ...      {"kind": "pore", "radius_mm": 0.3, "start": 0.02, "invert": 0.01, "start_shape": 0.02,
    ...       "invert_shape": 0.01}]}
    >>> rough_seed_table([r])[-1]
    '| 1 | 12.0 -> 6.0 µm | 0.50 | +0.006 µm (3 of 400 worse) | 0 of 1 | 0.50 | 0 of 1 |'
    """
    lines = ["| noise seed | within 1 mm of the defects | near ratio | worst 4 mm tile vs start | defects worse | "
             "highest defect ratio | defects worse on their own level |", "|---|---|---|---|---|---|---|"]
    for r in results:
        d = r["defects"]
        lines.append(f"| {r['seed']} | {1e3 * r['start']['near']:.1f} -> {1e3 * r['invert']['near']:.1f} µm | "
                     f"{r['near_ratio']:.2f} | {_tile(r, True)} | {_worse(d)} of {len(d)} | "
                     f"{max(x['invert'] / x['start'] for x in d):.2f} | {_worse(d, True)} of {len(d)} |")
    return lines


def expected_change(results) -> list[str]:
    """Markdown lines: what several noise seeds say of "nowhere worse" in expectation. One seed's
    worst tile is one draw of the noise: a tile holding a few pixels of a refined defect's rim gets
    worse under one seed and better under the next. Over the seeds, each 4 mm tile's change of the
    mean squared error (``invert`` less the start, µm²) has a mean and a standard error; a tile is
    worse in expectation where the mean lies above 0 by more than two of them. The same around each
    defect, ring by ring (:data:`RINGS_MM`).

    Examples
    --------
    >>> z = np.zeros((2, 2))
    >>> rs = [{"tile_mse": (z + 10.0, z + np.array([[10.0, 4.0], [10.0, 10.0 + d]])), "defects": [
    ...        {"kind": "pore", "radius_mm": 0.3, "rings": [(900.0, 90.0 + d), None, (9.0, 15.0 + d), None]}]}
    ...       for d in (0.5, -0.5, 0.4, -0.2)]
    >>> lines = expected_change(rs)
    >>> print(lines[0])
    Over 4 noise seeds, each 4 mm tile's mean squared error, `invert` less the start (mean ± standard error): 2 of 4 tiles changed under some seed, 1 with a mean above 0, 0 of them beyond two standard errors; the largest mean +0.05 ± 0.24 µm² of the start's 10.0 µm².
    >>> print(lines[-1])
    | pore, 0.30 mm | -810.0 ± 0.2 (900.0) | · | +6.0 ± 0.2 (9.0) **worse** | · |
    """
    tiles = np.array([np.asarray(r["tile_mse"][1]) - np.asarray(r["tile_mse"][0]) for r in results])
    k = len(results)
    mean, se = tiles.mean(axis=0), tiles.std(axis=0, ddof=1) / np.sqrt(k)
    changed = np.any(np.abs(tiles) > 1e-9, axis=0)
    above = changed & (mean > 0)
    worse = above & (mean > 2 * se)

    def largest(where):
        t = np.unravel_index(int(np.argmax(np.where(where, mean, -np.inf))), mean.shape)
        return (f"{_um2(mean[t])} ± {_um2(se[t], sign=False)} µm² of the start's "
                f"{np.mean([np.asarray(r['tile_mse'][0])[t] for r in results]):.1f} µm²")
    lines = [f"Over {k} noise seeds, each 4 mm tile's mean squared error, `invert` less the start (mean ± standard "
             f"error): {int(changed.sum())} of {mean.size} tiles changed under some seed, {int(above.sum())} with a "
             f"mean above 0, {int(worse.sum())} of them beyond two standard errors"
             + (f" (the largest {largest(worse)})" if worse.any() else "") + f"; the largest mean {largest(changed)}.",
             ""]

    def ring(lo, hi):
        return "inside" if lo == -np.inf else f"{lo:g}-{hi:g} mm beyond the rim"
    lines += ["Around each defect, ring by ring (squared error, µm²: `invert` less the start, mean ± standard error "
              "over the seeds; in brackets the start's; **worse**: above 0 by more than two standard errors):", "",
              "| defect | " + " | ".join(ring(lo, hi) for lo, hi in RINGS_MM) + " |",
              "|---" * (len(RINGS_MM) + 1) + "|"]
    for j, d in enumerate(results[0]["defects"]):
        cells = []
        for i in range(len(RINGS_MM)):
            got = [r["defects"][j]["rings"][i] for r in results]
            if any(g is None for g in got):  # a ring beyond the field's edge
                cells.append("·")
                continue
            dm = np.array([g[1] - g[0] for g in got])
            m, e = dm.mean(), dm.std(ddof=1) / np.sqrt(k)
            cells.append(f"{_um2(m, decimals=1)} ± {_um2(e, False, 1)} ({np.mean([g[0] for g in got]):.1f})"
                         + (" **worse**" if m > 2 * e else ""))
        lines.append(f"| {d['kind']}, {d['radius_mm']:.2f} mm | " + " | ".join(cells) + " |")
    return lines


def shared_noise_lines(results, clean, sigma_mm: float = 1.0) -> list[str]:
    """Markdown lines: how much of each seed's near ratio is the start's integrated noise that the
    inversion keeps. ``clean``: the same surface without noise (the same renders). Per seed, the
    noise's part of each error (the noisy run's less the noise-free run's), its wavelengths beyond
    ``sigma_mm`` (a Gaussian of that sigma) and within 1 mm of the defects: the start's and
    ``invert``'s, their correlation, and the near ratio with that shared part set aside from both,
    sqrt(I² - L_i²) / sqrt(S² - L_s²).

    Examples
    --------
    >>> z = np.zeros((40, 40)); near = np.zeros((40, 40), bool); near[10:30, 10:30] = True
    >>> base = {"res": 40, "_errors": (z + 0.0, z + 0.0, near)}
    >>> wave = 0.004 * np.cos(np.arange(40) / 40 * np.pi)[None, :] * np.ones((40, 1))
    >>> r = {**base, "seed": 1, "start": {"near": 0.012}, "invert": {"near": 0.006}, "near_ratio": 0.5,
    ...      "_errors": (wave, wave, near)}
    >>> shared_noise_lines([r], base)[-1]
    '| 1 | 12.0 -> 6.0 µm | 0.50 | 1.7 µm | 1.7 µm | 1.00 | 0.48 |'
    """
    from scipy.ndimage import gaussian_filter

    s0, i0, _ = clean["_errors"]
    sigma = sigma_mm * clean["res"] / 80.0  # the studies' field is 80 mm
    lines = [f"| noise seed | within 1 mm of the defects | near ratio | start's noise beyond {sigma_mm:g} mm | "
             "invert's | correlation | near ratio without it |", "|---|---|---|---|---|---|---|"]
    for r in results:
        s1, i1, near = r["_errors"]
        ls, li = (gaussian_filter(a - b, sigma)[near] for a, b in ((s1, s0), (i1, i0)))
        big_s, big_i = r["start"]["near"], r["invert"]["near"]
        rms_s, rms_i = float(np.sqrt(np.mean(ls ** 2))), float(np.sqrt(np.mean(li ** 2)))
        corr = float(np.corrcoef(ls, li)[0, 1]) if np.std(ls) > 0 and np.std(li) > 0 else float("nan")
        without = np.sqrt(max(big_i ** 2 - rms_i ** 2, 0.0) / max(big_s ** 2 - rms_s ** 2, 1e-30))
        lines.append(f"| {r['seed']} | {1e3 * big_s:.1f} -> {1e3 * big_i:.1f} µm | {r['near_ratio']:.2f} | "
                     f"{1e3 * rms_s:.1f} µm | {1e3 * rms_i:.1f} µm | {corr:.2f} | {without:.2f} |")
    return lines


def _um2(v, sign=True, decimals=2) -> str:
    """A change of squared error (µm²) to ``decimals`` decimals, or two digits where it is smaller.

    >>> _um2(-1258.21, decimals=1), _um2(2.4e-4), _um2(0.05, sign=False)
    ('-1258.2', '+2.4e-04', '0.05')
    """
    sign = "+" if sign else ""
    return f"{v:{sign}.{decimals}f}" if abs(v) >= 10.0 ** -decimals or v == 0 else f"{v:{sign}.1e}"


def _tile(r, brief=False) -> str:
    """The worst 4 mm tile against the start, to the precision that decides "nowhere worse"."""
    d = r["worst_tile_um"]
    if brief:
        return f"{d:+.3f} µm ({r['tiles_worse']} of {r['tiles']} worse)"
    rel = f", {100 * d / r['worst_tile_start_um']:.1f} % of its {r['worst_tile_start_um']:.1f} µm" if d > 0 else ""
    return f"{d:+.3f} µm against the start ({r['tiles_worse']} of {r['tiles']} tiles worse{rel})"


def _figure(kind, truth, start, inv, save_to):
    """Truth, the start's and the inversion's errors, the stated error bar; ``save_to(fig)`` saves."""
    from .plotting import plt

    fig, axes = plt.subplots(1, 4, figsize=(16.0, 3.6), constrained_layout=True)
    e0 = 1e3 * ((start - start.mean()) - (truth - truth.mean()))
    e1 = 1e3 * ((inv.height - inv.height.mean()) - (truth - truth.mean()))
    lim = float(np.percentile(np.abs(e0), 99))
    for ax, img, title, cmap, vlim in (
            (axes[0], 1e3 * (truth - truth.mean()), "truth (um)", "viridis", None),
            (axes[1], e0, "start: error (um)", "RdBu_r", lim), (axes[2], e1, "invert: error (um)", "RdBu_r", lim),
            (axes[3], 1e3 * inv.height_error, "height_error (um)", "magma", None)):
        kw = {} if vlim is None else {"vmin": -vlim, "vmax": vlim}
        im = ax.imshow(img, cmap=cmap, **kw)
        ax.set_title(title)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(im, ax=ax, shrink=0.8)
    save_to(fig)


TITLE = "Heights at the defects: pores, bumps, steps, and error bars that cover the error (issue 25)"
#: Each surface's layout (the steep ones under detectors 40 deg up, as in the inversion study).
LAYOUTS = {"rough": "zeta25", "steps": "zeta50", "hills": "zeta50", "melt": "zeta25"}


def run(ctx):
    """The validation study: one row per surface, its calibration, one figure each."""
    from .plotting import save
    from .report import Row, StudyResult, verdict_from

    cfg = ctx.settings["defects"]
    st = StudyResult("defects", TITLE)
    for kind in cfg["surfaces"]:
        res = cfg["res"].get(kind, 400)
        r = run_surface(kind, res, Path(ctx.tmp_dir), layout=LAYOUTS[kind])
        s, i, he, g = r["start"], r["invert"], r["height_error"], r["gradient_sigma"]
        calibrated = 0.60 <= he["all"][0] <= 0.75 and he["all"][1] >= 0.90
        g_ok = all(0.60 <= g[a][0] <= 0.75 and g[a][1] >= 0.90 for a in ("dzdx", "dzdy"))
        # the heights' part of the claim (issue 25): near the defects <= 1/2 of the start and nowhere
        # worse; each step within 10 %; elsewhere not worse than the start
        if kind == "rough":
            heights_ok = r["near_ratio"] <= 0.5 and r["worst_tile_um"] <= 0.0
        elif "steps" in r:
            heights_ok = all(step_ok(p) for p in r["steps"])
        else:
            heights_ok = r["invert"]["all"] <= r["start"]["all"]
        verdict = (verdict_from(True) if heights_ok and calibrated and g_ok
                   else "partly" if heights_ok or (calibrated and g_ok) else verdict_from(False))
        cal = (f"height_error within 1x / 2x: {100 * he['all'][0]:.0f} / {100 * he['all'][1]:.0f} % of pixels "
               f"(noise part alone {100 * he['noise_only'][0]:.0f} / {100 * he['noise_only'][1]:.0f} %; stated "
               f"{he['stated_rms_um']:.1f} µm RMS); dzdx_sigma {100 * g['dzdx'][0]:.0f} / {100 * g['dzdx'][1]:.0f} %, "
               f"dzdy_sigma {100 * g['dzdy'][0]:.0f} / {100 * g['dzdy'][1]:.0f} %")
        near = ""
        if np.isfinite(r["near_ratio"]):
            near = (f", within 1 mm of the defects {1e3 * s['near']:.1f} -> {1e3 * i['near']:.1f} µm "
                    f"(ratio {r['near_ratio']:.2f}; the issue asks <= 0.5), beyond {1e3 * s['far']:.1f} -> "
                    f"{1e3 * i['far']:.1f} µm")
        if "pores" in r:
            near += (f"; inside the pores {1e3 * r['pores']['start']:.1f} -> {1e3 * r['pores']['invert']:.1f} µm, "
                     f"height_error within 1x / 2x there on {100 * he['pores'][0]:.0f} / {100 * he['pores'][1]:.0f} % "
                     "of their pixels")
        ours = (f"height RMSE: Eq. 26 + integration {1e3 * r['eq26']['all']:.1f} µm, start {1e3 * s['all']:.1f} µm, "
                f"invert {1e3 * i['all']:.1f} µm{near}; worst 4 mm tile {_tile(r)}; "
                + (f"{defects_line(r)}; " if "defects" in r else "")
                + f"{len(r['regions'])} region(s) above the noise; {r['seconds']:.0f} s. {cal}")
        why = ""
        if "steps" in r:
            why = ("steps recovered (nominal, the truth's step as the same median measures it: start, invert; mm; "
                   "within 10 % of the truth's: " + ", ".join(f"{p['nominal']:+.1f}" for p in r["steps"] if step_ok(p))
                   + "): " + "; ".join(f"{p['nominal']:+.1f} ({p['truth']:+.3f}): {p['start']:+.3f}, "
                                       f"{p['invert']:+.3f}" for p in r["steps"]))
            why += (f". Slope bias of the model gradient over the flat powder: {r['slope_bias'][0]:+.1e}, "
                    f"{r['slope_bias'][1]:+.1e} (absolute). {len(r['lifted'])} of {r['searched']} floating parts "
                    "lifted to the step their shadows show (analysis/step_offsets.py; step, mm: "
                    + ", ".join(f"{p['step_before']:+.3f} -> {p['step_after']:+.3f} ± {p['error']:.3f} ({p['wall']})"
                                for p in r["lifted"])
                    + "); a part not lifted keeps the slopes' step and its offset is in height_error (the 0.1 mm "
                    "steps cast shadows of 0.12 mm at 40 degrees of elevation, about half a pixel)")
        elif kind == "rough":
            why = ("the regions at the pores and bumps are refined, where it explains more than noise alone (a "
                   "bootstrap test) with a robust curvature penalty on 2x2 sub-pixel facets (docs/inversion.md), "
                   "which takes the pores from a third of their depth to most of it and leaves the smooth bumps "
                   "to the quadratic one; a region's heights are taken where its misfit lies (around it the field's "
                   "fit to the noise); "
                   "what is left within 1 mm is mostly the field's own long-wavelength noise in the rings around the "
                   "defects (as beyond 1 mm) and the narrowest pore (0.26 mm radius, 6 pixels inside); the "
                   "tiles worse lie at a refined defect's rim, where its window's heights are taken and the start "
                   "was closer; under other noise seeds the ratio moves with that long-wavelength noise "
                   "(python -m validation.study_defects --only rough --seeds 1,2,3,4,5,6,7; docs/inversion.md); at "
                   "1500^2 (pores 12 pixels wide) see "
                   "docs/inversion.md. Inside the pores the error bars hold the depth the images leave to the "
                   "penalty (the robust and the quadratic penalty's difference), which no noise draw shows")
        elif kind == "melt":
            why = ("the start fits to the noise and is kept; the regions flagged lie at the melt squares' rims, "
                   "their refinement fits the images a little better and leaves the heights as they were")
        elif kind == "hills":
            from elo_mitsuba.analysis.inversion import MODEL_SLOPE_GAIN

            why = (f"the inversion's heights come out {100 * r['gain']:+.2f} % off in proportion to the relief (the "
                   "model's slope gain, as row G1's facet slopes), a bias the misfit cannot see: height_error holds "
                   f"it as height_error_model, {100 * MODEL_SLOPE_GAIN:.1f} % of the height about the mean (without "
                   f"it: the noise part alone above)")
        st.add(Row(f"D{len(st.rows) + 1}", f"{kind}: heights at the defects, and error bars within 1x on 60-75 % and "
                   "2x on >= 90 % of pixels", "—", ours,
                   f"{kind}, {res}², layout {LAYOUTS[kind]}, fwhm 0.27 mm, 1 % noise on object and flat, --quality "
                   "default, events 1", verdict, why,
                   {"start": s["all"], "invert": i["all"], "cover1": he["all"][0], "cover2": he["all"][1],
                    **({"near_ratio": r["near_ratio"]} if np.isfinite(r["near_ratio"]) else {})}))
        if ctx.figures:
            truth, h0, inv = r["figure"]
            _figure(kind, truth, h0, inv, lambda fig, kind=kind: save(
                fig, ctx, f"defects_{kind}", f"{kind}, {res}²: the truth, the start's and the inversion's height "
                "errors (same colour scale) and the stated height_error.", st))
    return st


def report(results) -> str:
    lines = ["# Heights at the defects (issue 25)", "",
             "Generated by `python -m validation.study_defects`; 0.27 mm FWHM beam, "
             f"{100 * results[0]['noise']:g} % noise on object and flat, "
             "quality default, events 1, noise seed(s) " + ", ".join(str(k) for k in dict.fromkeys(r["seed"] for r in results))
             + ". RMSE with the mean removed; \"near\": within 1 mm of a defect's rim or "
             "a cliff. Coverage: share of pixels whose actual error lies within 1x / 2x the stated error bar "
             "(68 % / 95 % for a calibrated Gaussian one; the issue asks 60-75 % and >= 90 %).", "",
             "| surface | Eq. 26 + int. (all) | start all / near / far | invert all / near / far | near ratio | worst 4 mm tile vs start | time | height_error within 1x / 2x (near) | noise-only bar | dzdx_sigma 1x / 2x |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        s, i = r["start"], r["invert"]
        he, g = r["height_error"], r["gradient_sigma"]
        lines.append(
            f"| {r['kind']} {r['res']}², {r['layout']} | {1e3 * r['eq26']['all']:.1f} µm | {1e3 * s['all']:.1f} / "
            f"{1e3 * s['near']:.1f} / {1e3 * s['far']:.1f} µm | {1e3 * i['all']:.1f} / {1e3 * i['near']:.1f} / "
            f"{1e3 * i['far']:.1f} µm | {r['near_ratio']:.2f} | {_tile(r, True)} | {r['seconds']:.0f} s | "
            f"{100 * he['all'][0]:.0f} / {100 * he['all'][1]:.0f} % ({100 * he['near'][0]:.0f} / "
            f"{100 * he['near'][1]:.0f} %) | {100 * he['noise_only'][0]:.0f} / {100 * he['noise_only'][1]:.0f} % | "
            f"{100 * g['dzdx'][0]:.0f} / {100 * g['dzdx'][1]:.0f} % |")
    for r in results:
        if "steps" in r:
            lines += ["", f"Steps recovered ({r['kind']} {r['res']}², {r['layout']}, noise seed {r['seed']}; mm, "
                      "nominal (truth): start, invert):", ""]
            lines += [f"- {p['nominal']:+.1f} ({p['truth']:+.3f}): {p['start']:+.3f}, {p['invert']:+.3f}"
                      f"{'' if step_ok(p) else ' (beyond 10 %)'}" for p in r["steps"]]
        if "slope_bias" in r:
            lines += ["", f"Slope bias of the model gradient over the flat powder ({r['kind']}): "
                      f"dZ/dx {r['slope_bias'][0]:+.2e}, dZ/dy {r['slope_bias'][1]:+.2e} (absolute)"]
        lines += ["", f"Regions of {r['kind']}: {len(r['regions'])}; " + "; ".join(
            f"{g['status']} ({g['misfit_start']:.2f} -> {g['misfit_end']:.2f}"
            + (f", returned {g['misfit_taken']:.2f})" if g["misfit_taken"] is not None else ")")
            for g in r["regions"][:12])]
    return "\n".join(lines + [""])


def main(argv=None):
    import json
    import tempfile

    ap = argparse.ArgumentParser(prog="python -m validation.study_defects", description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=400, help="resolution of the rough and stepped layers (default 400)")
    ap.add_argument("--out", default="out/defects.md", help="the table (markdown; default out/defects.md here)")
    ap.add_argument("--only", nargs="*", default=["rough", "steps", "hills", "melt"], choices=list(LAYOUTS))
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    ap.add_argument("--noise", type=float, default=0.01, metavar="SIGMA",
                    help="relative Gaussian noise on every object and flat pixel (default 0.01, the REPORT's and "
                         "the issue's; 0.0025 is sixteen recordings averaged, 0 none: the renders' own Monte Carlo "
                         "error remains)")
    ap.add_argument("--seeds", default="7", metavar="K,K,...",
                    help="noise seeds (default 7, the REPORT's); with several, each surface is measured once per "
                         "seed (the renders are shared), the steps and the rough layer get a table per seed, and with "
                         "three or more what the seeds say in expectation (each tile's and each defect's rings' mean "
                         "change against the start; ten seeds of the rough layer take about 9 min on 2 cores)")
    ap.add_argument("--shared-noise", action="store_true",
                    help="the rough layer once more without noise (the same renders), and per seed how much of the "
                         "near ratio is the start's integrated noise beyond 1 mm that the inversion keeps")
    args = ap.parse_args(argv)
    if Path(args.out).exists() and not args.overwrite:
        ap.error(f"--out {args.out} exists: pass --overwrite to replace it")
    try:
        seeds = [int(k) for k in args.seeds.split(",")]
    except ValueError:
        seeds = []
    if not seeds or min(seeds) < 0:
        ap.error(f"--seeds {args.seeds!r}: must be integers >= 0 separated by commas, e.g. 1,2,3")
    if args.shared_noise and "rough" not in args.only:
        ap.error("--shared-noise measures the rough layer: add rough to --only")
    if not 0.0 <= args.noise < 1.0:  # NaN fails too
        ap.error(f"--noise {args.noise!r}: must be a relative noise level, 0 <= SIGMA < 1 (e.g. 0.01 for 1 %)")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind in args.only:
            res = {"hills": 256, "melt": 512}.get(kind, args.res)
            layout = LAYOUTS[kind]
            for seed in seeds:
                results.append(run_surface(kind, res, Path(tmp), layout=layout, seed=seed, noise=args.noise))
                print(json.dumps({k: v for k, v in results[-1].items()
                                  if k not in ("regions", "figure", "tile_mse") and not k.startswith("_")},
                                 default=float), flush=True)
        if args.shared_noise and "rough" in args.only:
            clean = run_surface("rough", args.res, Path(tmp), layout=LAYOUTS["rough"], seed=seeds[0], noise=0.0)
    text = report(results)
    rough = [r for r in results if "defects" in r]
    if len(seeds) > 1 and rough:
        text += "\n".join(["", f"The rough layer under {len(seeds)} noise seeds ({rough[0]['res']}²):", "",
                           *rough_seed_table(rough), ""])
        if len(rough) > 2:
            text += "\n".join(["", *expected_change(rough), ""])
    if args.shared_noise and rough:
        text += "\n".join(["", f"The rough layer's start noise that `invert` keeps ({rough[0]['res']}²; the same renders "
                           "without noise as reference; docs/inversion.md):", "", *shared_noise_lines(rough, clean), ""])
    by_seed = [r for r in results if "steps" in r]
    if len(seeds) > 1 and by_seed:
        text += "\n".join(["", f"Steps under {len(seeds)} noise seeds (steps {by_seed[0]['res']}²; mm; spread: sample "
                           "standard deviation over the seeds):", "", *seed_table(by_seed), ""])
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
