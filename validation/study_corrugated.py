"""Fig. 10: the corrugated sheet (Sec. 4.2): M_x, the Eq. 26 gradient and the true +-1 along y = 0."""

from __future__ import annotations

import numpy as np

from .report import Row, StudyResult, fmt, verdict_from
from .tools import facet_gradient, line_fit

TITLE = "Fig. 10: corrugated sheet, M_x vs Eq. 26 vs the true gradient, Eq. 24"
DH, DW = 272.0, 127.0


def _profile(ctx):
    import elo_mitsuba.analysis as A

    cfg = ctx.settings["corrugated"]
    field, res, spp, band = cfg["field"], cfg["res"], cfg["spp"], cfg["band_mm"]
    r = ctx.renderer
    obj = r.render("corrugated_sheet", spp=spp, seed=31, res=res, field=field)
    flat = r.render("flat_plate", spp=spp, seed=32, res=res, field=field)
    g = A.surface_gradient(obj.channels, flat.channels, field, DH, DW)
    x, y = A.pixel_coordinates((res, res), field)
    rows = np.abs(y[:, 0]) <= band
    xs = x[0]
    prof = {
        "x": xs,
        "mx": g.mx[rows].mean(axis=0),
        "nsx": -g.dzdx[rows].mean(axis=0),          # Eq. 26: n_Sx = -dZ/dx
        "masked": g.mask[rows].mean(axis=0),
        "rows": int(rows.sum()),
    }
    # the true slope where each beam ray hits the sheet (ray cast: the perspective beam from the
    # pivot sees ridges shifted outwards by x Z / w_d, up to 35 um at the field edge)
    scene = r.scene("corrugated_sheet", res=res, field=field)
    tgx, _, zhit = facet_gradient(scene, xs, np.zeros_like(xs), scene.sensor.wd, return_height=True)
    slope = np.round(tgx)                                   # exactly +-1 on the 45 deg flanks
    prof["z"] = zhit
    prof["true_nsx"] = -slope
    px = field / res
    m = max(1, int(np.ceil(0.08 / px)))                     # core: >= 80 um from a ridge or valley
    same = np.ones(xs.size, bool)
    for k in range(1, m + 1):
        same[k:] &= slope[k:] == slope[:-k]
        same[:-k] &= slope[:-k] == slope[k:]
    same[:m] = same[-m:] = False
    prof["core"] = same
    seg = np.cumsum(np.concatenate([[0], slope[1:] != slope[:-1]]))
    prof["seg"] = seg
    # the simplified point-detector model (Sec. 4.1) on the same profile: Lambert (Eq. 24 exactly)
    # and the full g_BSE of Eq. 13 with the beam from the pivot, as the renderer
    for model, beam in (("lambert", "vertical"), ("g_bse", "pivot")):
        dzdx = slope[None, :]
        imgs = A.point_detector_images(dzdx, np.zeros_like(dzdx), (field, px), DH, DW, model=model, beam=beam)
        flats = A.flat_plate_images(dzdx.shape, (field, px), DH, DW, model=model, beam=beam)
        corr, _ = A.stsa_correct(imgs, flats)
        mx, _, _ = A.normalised_differences(corr)
        prof[f"mx_{model}"] = mx[0]
    prof["eq24"] = A.eq24_differences(prof["true_nsx"], 0.0, xs, 0.0, DH, DW)[0]
    # flank means (core pixels only)
    flanks = []
    for k in np.unique(seg[prof["core"]]):
        sel = prof["core"] & (seg == k)
        if sel.sum() >= 2:
            flanks.append({key: float(np.mean(prof[key][sel])) for key in
                           ("x", "mx", "nsx", "true_nsx", "mx_g_bse", "mx_lambert", "eq24")})
    prof["flanks"] = {key: np.array([f[key] for f in flanks]) for key in flanks[0]} if flanks else {}
    prof["settings"] = (f"corrugated_sheet + flat_plate (STSA), events 1, {res}² px over {field:g} mm "
                        f"({1000 * px:.0f} µm), {spp} spp, rows |y| ≤ {band:g} mm averaged")
    prof["field"] = field
    return prof


def run(ctx):
    st = StudyResult("corrugated", "Fig. 10 — corrugated sheet: M_x, Eq. 26 and Eq. 24 (Sec. 4.2)")
    p = _profile(ctx)
    fl = p["flanks"]
    settings = p["settings"]
    ratio0 = DW / DH
    core = p["core"]

    frac_below = float(np.mean(np.abs(p["mx"][core]) < np.abs(p["true_nsx"][core])))
    st.add(Row(
        "10a", "Fig. 10a: M_x is always lower than the true analytical gradient (±1)", "|M_x| < 1 everywhere",
        f"|M_x| < |n_Sx| on {100 * frac_below:.1f} % of the flank pixels; max |M_x| = {np.abs(p['mx'][core]).max():.3f}",
        settings, verdict_from(frac_below == 1.0), "", {"fraction_below": frac_below}, "fig10_corrugated"))

    centre = np.abs(fl["x"]) < 2.0
    m0 = float(np.mean(np.abs(fl["mx"][centre])))
    m0_g = float(np.mean(np.abs(fl["mx_g_bse"][centre])))
    dev = m0 / ratio0 - 1
    st.add(Row(
        "10b", "Sec. 4.2: at x = 0, M_x takes the value d_w/d_h ≈ 0.47", f"{ratio0:.3f}",
        f"|M_x| = {m0:.3f} (flanks within 2 mm of x = 0; {100 * dev:+.1f} %); point-detector model with the "
        f"full g_BSE: {m0_g:.3f}", settings,
        verdict_from(abs(dev) < 0.08, approx=abs(dev) >= 0.02),
        "d_w/d_h is exact for Lambert's law (Eq. 24); the specular lobe of Eq. 13 sends extra electrons to the "
        "detector on the far side of the tilted flank and raises |M_x| — the point-detector model with the full "
        "g_BSE predicts the same value" if abs(dev) >= 0.02 else "",
        {"mx0": m0, "mx0_point_gbse": m0_g, "mx0_rel_dev": dev}, "fig10_corrugated"))

    # position dependence: slope of M_x along x for each flank orientation
    fits = {}
    for name, sgn in (("n+", 1.0), ("n-", -1.0)):
        sel = np.sign(fl["true_nsx"]) == sgn
        fits[name] = {key: line_fit(fl["x"][sel], fl[key][sel])[0] for key in ("mx", "eq24", "mx_g_bse")}
    s_ours = np.mean([fits[n]["mx"] for n in fits])
    s_eq24 = np.mean([fits[n]["eq24"] for n in fits])
    s_g = np.mean([fits[n]["mx_g_bse"] for n in fits])
    rr = s_ours / s_eq24
    same_sign = all(fits[n]["mx"] * fits[n]["eq24"] > 0 for n in fits)
    st.add(Row(
        "10c", "Fig. 10, Eq. 24: M_x depends on the position x: n_+ is measured as d_w/(d_h − x), n_− as "
        "−d_w/(d_h + x)", f"dM_x/dx = d_w/d_h² = {1e3 * DW / DH ** 2:.2f}e-3 /mm (Eq. 24)",
        f"dM_x/dx = {1e3 * s_ours:.2f}e-3 /mm ({rr:.2f} × Eq. 24); point-detector model with the full g_BSE: "
        f"{1e3 * s_g:.2f}e-3 /mm", settings,
        "agrees" if same_sign and 0.8 < rr < 1.25 else ("partly" if same_sign else "disagrees"),
        "" if 0.8 < rr < 1.25 else "the position dependence exists with Eq. 24's sign but is weaker: the specular "
        "lobe (its weight depends on the beam tilt across the field) is outside Eq. 24's Lambert assumption; the "
        "point-detector model with the full g_BSE reproduces our slope, so it is the model's physics, not the "
        "renderer",
        {"slope_ours": s_ours, "slope_eq24": s_eq24, "slope_point_gbse": s_g, "slope_ratio": rr}, "fig10_corrugated"))

    d_pm = float(np.sqrt(np.mean((fl["mx"] - fl["mx_g_bse"]) ** 2)))
    st.add(Row(
        "10d", "Conclusions: the ray-tracing model verifies the simplified point-detector model (Sec. 4.1)",
        "consistent", f"rms(M_x ray tracing − M_x point model with full g_BSE) = {fmt(d_pm, 2)} over "
        f"{len(fl['x'])} flanks (vs. |M_x| ≈ 0.5)", settings + "; point model: 1 ray per pixel, exact",
        verdict_from(d_pm < 0.01), "the remaining difference is the 50 mm disc against a point and MC noise",
        {"rms_point_model": d_pm}, "fig10_corrugated"))

    g_ratio = np.abs(fl["nsx"]) / np.abs(fl["true_nsx"])
    g0 = float(np.mean(g_ratio[centre]))
    gmin, gmax = float(g_ratio.min()), float(g_ratio.max())
    rms = float(np.sqrt(np.mean((p["nsx"][core] - p["true_nsx"][core]) ** 2)))
    worst = max(abs(gmin - 1), abs(gmax - 1))
    st.add(Row(
        "10e", "Fig. 10, Sec. 4.2: the gradient computed by Eq. 26 follows the analytical ±1 to a very high degree",
        "≈ ±1", f"|n_Sx| = {g0:.3f} near x = 0; flank means {gmin:.3f}…{gmax:.3f} across the field; "
        f"pixel rms error {rms:.3f}", settings,
        "agrees" if worst < 0.05 else ("agrees approx." if worst < 0.2 else "disagrees"),
        "" if worst < 0.05 else "Eq. 26 inverts Lambert's law exactly; with the full g_BSE (Eq. 13) the "
        "specular lobe leaves a few % at the centre and more at the field edges on 45° flanks — the same "
        "in the point-detector model with the full g_BSE, and 0 with Lambert (not a renderer defect)",
        {"grad_centre": g0, "grad_min": gmin, "grad_max": gmax, "grad_rms": rms}, "fig10_corrugated"))

    if ctx.figures:
        _figure(ctx, st, p)
    st.text = (
        "A corrugated Ti-6Al-4V sheet of 1 mm flanks at ±45° (normals n_± = [±1, 0, 1]) under the validation "
        "detectors (d_h = 272 mm, d_w = 127 mm), STSA-corrected with a flat plate rendered with the same "
        "geometry. M_x measures the slope scaled by about d_w/d_h (Eq. 24); Eq. 26 restores the magnitude "
        "without any calibration. The dashed curves are Eq. 24; the thin dotted curves the simplified "
        "point-detector model with the full g_BSE (Eq. 13), which the ray tracing follows. Where our numbers "
        "differ from Eq. 24 / Eq. 26 it is the specular lobe of Eq. 13, outside the Lambert assumption of "
        "the derivation (Sec. 4.1).")
    return st


def _figure(ctx, st, p):
    import matplotlib.pyplot as plt

    from .plotting import save

    field = p["field"]
    x = p["x"]
    fl = p["flanks"]
    fig = plt.figure(figsize=(12, 7.2))
    gs = fig.add_gridspec(2, 2, height_ratios=(1.15, 1))
    ax = fig.add_subplot(gs[0, :])
    ax.plot(x, p["true_nsx"], color="k", lw=0.8, label="true −∂Z/∂x = n_Sx (±1)")
    ax.plot(x, p["nsx"], color="C0", lw=0.5, alpha=0.8, label="−∂Z/∂x by Eq. 26 (modelled images)")
    ax.plot(x, p["mx"], color="C1", lw=0.5, alpha=0.8, label="M_x (Eq. 15)")
    for s in (1, -1):
        ax.axhline(s * DW / DH, color="0.4", lw=0.8, ls=":")
        sel = np.sign(fl["true_nsx"]) == s
        ax.plot(fl["x"][sel], fl["mx"][sel], "o", ms=2.5, color="C1")
        ax.plot(fl["x"][sel], fl["nsx"][sel], "o", ms=2.5, color="C0")
    xx = np.linspace(-field / 2, field / 2, 200)
    ax.plot(xx, DW / (DH - xx), "r--", lw=1, label="Eq. 24: d_w/(d_h − x), −d_w/(d_h + x)")
    ax.plot(xx, -DW / (DH + xx), "r--", lw=1)
    for s in (1, -1):
        sel = np.sign(fl["true_nsx"]) == s
        ax.plot(fl["x"][sel], fl["mx_g_bse"][sel], "m:", lw=1, label="point-detector model, full g_BSE" if s == 1 else None)
    ax.set_xlim(-field / 2, field / 2)
    ax.set_ylim(-1.45, 1.85)
    ax.set_xlabel("x (mm), y = 0")
    ax.set_ylabel("n_Sx, M_x")
    ax.set_title("(a) profiles along x at y = 0 (dots: flank means; dotted horizontal lines: ±d_w/d_h)")
    ax.legend(loc="upper center", ncol=3, fontsize=7)
    for i, (lo, hi) in enumerate(((-field / 2, -field / 2 + 3), (field / 2 - 3, field / 2))):
        ax = fig.add_subplot(gs[1, i])
        sel = (x >= lo) & (x <= hi)
        ax.plot(x[sel], p["true_nsx"][sel], "k-", lw=1, label="true n_Sx")
        ax.plot(x[sel], p["nsx"][sel], "C0.-", lw=0.8, ms=2, label="Eq. 26")
        ax.plot(x[sel], p["mx"][sel], "C1.-", lw=0.8, ms=2, label="M_x")
        for s in (1, -1):
            ax.axhline(s * DW / DH, color="0.4", lw=0.8, ls=":")
        ax.set_ylim(-1.45, 1.45)
        ax.set_xlabel("x (mm), y = 0")
        ax.set_ylabel("n_Sx, M_x")
        ax2 = ax.twinx()
        ax2.fill_between(x[sel], p["z"][sel] * 1e3, -1500, color="0.85", zorder=-1)
        ax2.set_ylim(-1500, 2600)
        ax2.set_ylabel("height Z (µm)", color="0.4")
        ax.set_zorder(ax2.get_zorder() + 1)
        ax.patch.set_visible(False)
        ax.set_title(f"(b) close-up at the {'left' if i == 0 else 'right'} end (grey: height profile)")
        if i == 0:
            ax.legend(loc="upper left", fontsize=7)
    fig.suptitle("Fig. 10 analogue: corrugated sheet, 1 mm flanks at 45°, d_h = 272 mm, d_w = 127 mm")
    fig.tight_layout()
    save(fig, ctx, "fig10_corrugated",
         f"Fig. 10 analogue: profiles along x at y = 0 of M_x, the Eq. 26 gradient and the true ±1 "
         f"({p['settings']}); red dashed: the position dependence predicted by Eq. 24.", st)
