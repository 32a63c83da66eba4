"""Figs. 12-13: reflectance maps of the right detector for zeta = 25 and 50 deg (Sec. 4.3)."""

from __future__ import annotations

import numpy as np

from .report import Row, StudyResult, verdict_from

TITLE = "Figs. 12-13: reflectance maps, full g_BSE and diffuse part, masking hatched"
LAYOUTS = {25: (272.0, 127.0), 50: (192.7, 229.6)}
WINDOW = (-3.0, 3.0)


def run(ctx):
    import elo_mitsuba.analysis as A

    n = ctx.settings["reflectance"]["n"]
    st = StudyResult("reflectance", "Figs. 12–13 — reflectance maps and geometric masking (Sec. 4.3)")
    maps = {}
    for zeta, (dh, dw) in LAYOUTS.items():
        d = A.detector_pq(dh, dw, "right")
        p, q, g, masked = A.reflectance_map(d, lobe=True, p_range=WINDOW, q_range=WINDOW, n=n)
        _, _, gd, _ = A.reflectance_map(d, lobe=False, p_range=WINDOW, q_range=WINDOW, n=n)
        maps[zeta] = dict(d=d, p=p, q=q, g=g, gd=gd, masked=masked, dh=dh, dw=dw)
    settings = f"Eq. 13 on a {n}×{n} grid of (p, q) ∈ [−3, 3]², vertical beam, point detector"
    step = (WINDOW[1] - WINDOW[0]) / (n - 1)

    # 12a: g_BSE vanishes exactly on the masked half-plane p <= -d_h/d_w, for every q
    worst = 0.0
    edges = {}
    for zeta, m in maps.items():
        p, g = m["p"], m["g"]
        positive = g > 0
        # first p with g > 0 in every row q
        first = np.array([p[i, np.argmax(positive[i])] for i in range(p.shape[0])])
        bound = -m["dh"] / m["dw"]
        edges[zeta] = (float(first.min()), float(first.max()), bound)
        worst = max(worst, float(np.max(np.abs(first - bound))))
        consistent = np.all(~positive[m["masked"]])
        worst = worst if consistent else np.inf
    st.add(Row(
        "12a", "Sec. 4.3: for the right detector the masking condition is n_Sx ≤ −d_h/d_w irrespective of n_Sy; "
        "there g_BSE = 0", "p ≤ −2.14 (ζ = 25°), p ≤ −0.839 (ζ = 50°)",
        "; ".join(f"ζ = {z}°: g_BSE > 0 from p = {lo:.3f}…{hi:.3f} (all q) vs −d_h/d_w = {b:.3f}"
                  for z, (lo, hi, b) in edges.items()), settings, verdict_from(worst <= step),
        "criterion: within one grid step", {"max_boundary_error": worst}, "fig12_reflectance_zeta25"))

    frac = {z: float(m["masked"].mean()) for z, m in maps.items()}
    st.add(Row(
        "12b", "Figs. 12–13: the steeper detector (ζ = 50°) masks more normal vectors than ζ = 25°",
        "more hatched area at 50°", f"masked share of the window: {100 * frac[25]:.1f} % (25°), {100 * frac[50]:.1f} % (50°)",
        settings, verdict_from(frac[50] > frac[25]), "", {f"masked_fraction_{z}": v for z, v in frac.items()},
        "fig13_reflectance_zeta50"))

    # 12c: contours differ strongly -> peak position and slope sensitivity at the flat normal
    stats = {}
    for zeta, m in maps.items():
        i, j = np.unravel_index(np.argmax(m["g"]), m["g"].shape)
        c = m["g"].shape[0] // 2
        g0 = m["g"][c, c]
        dgdp = (m["g"][c, c + 1] - m["g"][c, c - 1]) / (2 * step)
        stats[zeta] = dict(p_peak=float(m["p"][i, j]), q_peak=float(m["q"][i, j]), sens=float(dgdp / g0))
    st.add(Row(
        "12c", "Sec. 4.3: the contour lines of g_BSE for ζ = 25° and 50° differ strongly: intensity and contrast "
        "depend strongly on the detector position", "strongly different maps",
        "; ".join(f"ζ = {z}°: peak at p = {s['p_peak']:.2f}, relative slope sensitivity "
                  f"(∂g/∂p)/g at n_S = e_z = {s['sens']:.2f}" for z, s in stats.items()), settings,
        verdict_from(abs(stats[50]["sens"] / stats[25]["sens"] - 1) > 0.3 and abs(stats[50]["p_peak"] - stats[25]["p_peak"]) > 0.2),
        "criterion: sensitivities differ by > 30 % and peaks by > 0.2 in p",
        {f"sensitivity_{z}": s["sens"] for z, s in stats.items()} | {f"p_peak_{z}": s["p_peak"] for z, s in stats.items()},
        "fig13_reflectance_zeta50"))
    if ctx.figures:
        for zeta, m in maps.items():
            _figure(ctx, st, zeta, m)
    st.text = (
        "Reflectance maps (Sec. 4.3): g_BSE of Eq. 13 per steradian for every surface normal n_S = [p, q, 1] "
        "placed at the origin, vertical beam, point detector in the direction d = [d_w/d_h, 0, 1] (white "
        "cross). Left: full g_BSE; right: its diffuse (Lambert) part. Hatched: geometrically masked normals "
        "p d_x + q d_y + 1 ≤ 0, where the map is exactly 0.")
    return st


def _figure(ctx, st, zeta, m):
    import matplotlib.pyplot as plt
    from matplotlib import rc_context

    from .plotting import CMAP_SEQUENTIAL, save

    p, q = m["p"], m["q"]
    ext = (p.min(), p.max(), q.min(), q.max())
    vmax = max(m["g"].max(), m["gd"].max())
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.6))
    for ax, g, name in ((axs[0], m["g"], "full g_BSE (Eq. 13)"), (axs[1], m["gd"], "diffuse part only")):
        im = ax.imshow(g, extent=ext, origin="upper", cmap=CMAP_SEQUENTIAL, vmin=0, vmax=vmax, interpolation="bilinear")
        ax.contour(p, q, g, levels=np.linspace(0, vmax, 12)[1:], colors="k", linewidths=0.5, alpha=0.7)
        side = p * m["d"][0] + q * m["d"][1] + 1.0
        with rc_context({"hatch.color": "w", "hatch.linewidth": 0.8}):
            ax.contourf(p, q, side, levels=[side.min() - 1.0, 0.0], colors="none", hatches=["///"])
        ax.contour(p, q, side, levels=[0.0], colors="w", linewidths=1.0)
        ax.plot([m["d"][0]], [m["d"][1]], marker="x", color="w", ms=10, mew=2.5)
        ax.set_xlabel("p = n_Sx = −∂Z/∂x")
        ax.set_ylabel("q = n_Sy = −∂Z/∂y")
        ax.set_title(name)
        ax.set_aspect("equal")
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
        cb.set_label("g_BSE (1/sr)")
    fig_no = 12 if zeta == 25 else 13
    fig.suptitle(f"Fig. {fig_no} analogue: reflectance maps, right detector d_r = [{m['dw']:g}/{m['dh']:g}, 0, 1] "
                 f"(ζ = {zeta}°), Ti-6Al-4V")
    fig.tight_layout()
    save(fig, ctx, f"fig{fig_no}_reflectance_zeta{zeta}",
         f"Fig. {fig_no} analogue: reflectance maps for a right detector d_r = [{m['dw']:g}/{m['dh']:g}, 0, 1] "
         f"(white cross, ζ = {zeta}°); left full g_BSE, right diffuse part; hatched: masked normals "
         f"p ≤ −{m['dh'] / m['dw']:.3f}.", st)
