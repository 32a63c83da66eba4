"""Figs. 6, 7, 11 (and Fig. 3b) on the synthetic melt plate: M_x, Eq. 26, beam blur, height maps."""

from __future__ import annotations

import numpy as np

from .report import Row, StudyResult, fmt, verdict_from
from .tools import FWHM_PER_SIGMA, check_melt_resolution, facet_gradient, fit_gaussian_blur, line_fit

TITLE = "Figs. 6, 7, 11: M_x and the Eq. 26 gradient on the melt plate, beam blur, reconstruction"
DH, DW = 272.0, 127.0
FULL_FIELD = 80.0
FWHM = 0.27


def _full(ctx):
    import elo_mitsuba.analysis as A
    from elo_mitsuba.objects.melt_plate import in_squares, melt_plate_height

    cfg = ctx.settings["melt_plate"]
    res, spp = cfg["full_res"], cfg["full_spp"]
    check_melt_resolution(FULL_FIELD, res)
    r = ctx.renderer
    # the ATHENE beam profile (at least 1.5 pixels): the images then average the 0.2 mm mesh facets
    # between pixel centres as the experiment does; point samples would alias them
    fwhm = max(FWHM, 1.5 * FULL_FIELD / res)
    obj = r.render("melt_plate", spp=spp, seed=51, res=res, field=FULL_FIELD, fwhm=fwhm)
    flat = r.render("flat_plate", spp=spp, seed=52, res=res, field=FULL_FIELD)
    g = A.surface_gradient(obj.channels, flat.channels, FULL_FIELD, DH, DW)
    x, y = A.pixel_coordinates((res, res), FULL_FIELD)
    scene = r.scene("melt_plate", res=res, field=FULL_FIELD)
    tgx, tgy = facet_gradient(scene, x, y, scene.sensor.wd)
    return dict(g=g, x=x, y=y, tgx=tgx, tgy=tgy, z=melt_plate_height(x, y), res=res, spp=spp, fwhm=fwhm,
                blank=~in_squares(x, y, inset_mm=-1.0), inside=in_squares(x, y),
                settings=f"melt_plate + flat_plate, events 1, {res}² px over {FULL_FIELD:g} mm "
                         f"({1000 * FULL_FIELD / res:.0f} µm), beam FWHM {fwhm:.2f} mm, {spp} spp")


def _zoom(ctx):
    import elo_mitsuba.analysis as A
    from elo_mitsuba.objects.melt_plate import in_squares, melt_plate_gradient

    cfg = ctx.settings["melt_plate"]
    field, res = cfg["zoom_field"], cfg["zoom_res"]
    check_melt_resolution(field, res)
    r = ctx.renderer
    # the 1st event by the deterministic quadrature: the sharp images are noise-free, so that the
    # blur fit of row 7b is not pulled towards wider Gaussians (which would smooth their noise)
    quad = {"detector_sampling": "quadrature", "quadrature_triangles": 24}
    sharp = r.render("melt_plate", spp=1, seed=53, res=res, field=field, options=quad)
    beam = r.render("melt_plate", spp=cfg["beam_spp"], seed=54, res=res, field=field, fwhm=FWHM, options=quad)
    flat = r.render("flat_plate", spp=1, seed=55, res=res, field=field, options=quad)
    gs = A.surface_gradient(sharp.channels, flat.channels, field, DH, DW)
    gb = A.surface_gradient(beam.channels, flat.channels, field, DH, DW)
    x, y = A.pixel_coordinates((res, res), field)
    scene = r.scene("melt_plate", res=res, field=field)
    tgx, tgy = facet_gradient(scene, x, y, scene.sensor.wd)
    agx, agy = melt_plate_gradient(x, y)
    inside = in_squares(x, y) & (np.abs(x) < 10) & (np.abs(y) < 10)
    # the beam profile convolves each detector image (linear); M_x, a ratio of images, is not
    # a convolution of the sharp M_x, so the blur is fitted on an image: R - L
    contrast = {k: img.channels["right"].astype(float) - img.channels["left"] for k, img in
                (("sharp", sharp), ("beam", beam))}
    return dict(gs=gs, gb=gb, contrast=contrast, x=x, y=y, tgx=tgx, tgy=tgy, agx=agx, agy=agy, inside=inside, field=field,
                res=res, px=field / res,
                settings=f"middle square: {res}² px over {field:g} mm ({1000 * field / res:.0f} µm), events 1, "
                         f"triangle quadrature (24), 1 spp; beam: FWHM {FWHM} mm, {cfg['beam_spp']} spp")


def _material(ctx, field):
    import elo_mitsuba.analysis as A

    cfg = ctx.settings["melt_plate"]
    res, spp = cfg["material_res"], cfg["material_spp"]
    check_melt_resolution(field, res)
    r = ctx.renderer
    out = {}
    for mat in ("Ti-6Al-4V", "Cu"):
        o = r.render("melt_plate", spp=spp, seed=56, res=res, field=field, material=mat)
        f = r.render("flat_plate", spp=spp, seed=57, res=res, field=field, material=mat)
        out[mat] = A.surface_gradient(o.channels, f.channels, field, DH, DW)
    return out, f"middle square, {res}² px over {field:g} mm, {spp} spp, same seeds"


def run(ctx):
    import elo_mitsuba.analysis as A
    from elo_mitsuba.objects.melt_plate import in_squares

    st = StudyResult("melt_plate", "Figs. 6, 7, 11 (and 3b) — the melt plate: M_x, Eq. 26, beam blur, "
                                   "reconstruction (Secs. 3.2, 4.2)")
    F = _full(ctx)
    Z = _zoom(ctx)

    # 6a: M_x = 0 on the blank plate in the model
    mx_blank = F["g"].mx[F["blank"]]
    st.add(Row(
        "6a", "Fig. 6, Sec. 3.2: aside the melt surfaces (n_S ∥ z) M_x should be 0; the experiment's deviation is "
        "misalignment or calibration", "0 expected (experiment ≠ 0)",
        f"mean M_x on the blank plate = {fmt(mx_blank.mean(), 2)}, rms {fmt(np.sqrt(np.mean(mx_blank ** 2)), 2)} "
        "(Monte Carlo noise)", F["settings"], verdict_from(abs(mx_blank.mean()) < 2e-3),
        "the model has no misalignment: the experiment's offset is an experimental effect the model omits "
        "by construction", {"mx_blank_mean": mx_blank.mean()}, "fig06_mx_full"))

    sharp, beam = Z["gs"], Z["gb"]
    ins = Z["inside"] & ~sharp.mask
    t_nsx = -Z["tgx"][ins]
    a_mx, _, se_mx, r_mx = line_fit(t_nsx, sharp.mx[ins])
    st.add(Row(
        "7a", "Fig. 7: the modelled M_x does not reach the magnitude of the true gradient ∂Z/∂x", "|M_x| < |∂Z/∂x|",
        f"M_x = {a_mx:.3f} × (−∂Z/∂x) inside the middle square (r = {r_mx:.3f}); d_w/d_h = {DW / DH:.3f}",
        Z["settings"], verdict_from(a_mx < 0.7), "slope of a least-squares fit against the gradient of the mesh "
        "facets the beam hits", {"mx_slope": a_mx, "mx_r": r_mx}, "fig07_mx_zoom"))

    # beam blur: fitted Gaussian between the sharp and the blurred M_x
    region = np.zeros_like(Z["inside"])
    m = max(2, int(round(1.0 / Z["px"])))
    region[m:-m, m:-m] = True
    fwhm_fit, c_fit, c0 = fit_gaussian_blur(Z["contrast"]["sharp"], Z["contrast"]["beam"], Z["px"], region)
    # the fit itself, on the sharp image blurred by exactly the beam's Gaussian
    from scipy.ndimage import gaussian_filter

    synthetic = gaussian_filter(Z["contrast"]["sharp"], FWHM / FWHM_PER_SIGMA / Z["px"], mode="nearest")
    fwhm_self, _, _ = fit_gaussian_blur(Z["contrast"]["sharp"], synthetic, Z["px"], region)
    st.add(Row(
        "7b", "Fig. 7a, Sec. 3.2: the experimental M_x appears blurred against the model because of the beam "
        "profile (Gaussian, ≈ 270 µm FWHM), which the paper's model lacks", "blur ≈ 0.27 mm FWHM",
        f"with fwhm = 0.27 the rendered image R − L is the sharp one blurred by a Gaussian of {fwhm_fit:.3f} mm "
        f"FWHM (fit; misfit drops {c0 / max(c_fit, 1e-30):.1f}×)", Z["settings"],
        verdict_from(abs(fwhm_fit / FWHM - 1) < 0.2), "our beam profile is a scene parameter (the paper's model "
        "has a single ray); fitted on R − L, which the beam convolves (M_x, a ratio, it does not), against the "
        f"noise-free sharp image. The fit recovers {fwhm_self:.4f} mm from the sharp image blurred by exactly "
        "0.27 mm, and the beam's aim points have exactly that profile (tests/test_grid.py): the excess depends on "
        "the scene (on the corrugated sheet's 0.7 mm flanks the same fit gives 0.274 mm), i.e. on the image's "
        "structure at the scale of the beam and the pixels, not on the beam", {"fwhm_fit_mm": fwhm_fit,
                                                                          "fwhm_fit_synthetic_mm": fwhm_self},
        "fig07_mx_zoom"))

    a_g, _, se_g, r_g = line_fit(t_nsx, -sharp.dzdx[ins])
    st.add(Row(
        "11a", "Fig. 11a, Sec. 4.2: the gradient from Eq. 26 matches the magnitude of the true ∂Z/∂x without any "
        "calibration", "same magnitude", f"−∂Z/∂x (Eq. 26) = {a_g:.3f} × true (r = {r_g:.3f}) inside the middle "
        "square", Z["settings"], verdict_from(abs(a_g - 1) < 0.1, approx=abs(a_g - 1) >= 0.05),
        "slope within 10 % of 1" + (f"; the {100 * (a_g - 1):+.0f} % is the specular lobe of Eq. 13 "
                                      "(Eq. 26 assumes Lambert; see 10e)" if abs(a_g - 1) >= 0.05 else ""),
        {"eq26_slope": a_g, "eq26_r": r_g}, "fig11_gradient_zoom"))

    # profiles along y = 0 (rows within +-0.1 mm) inside the square
    rows = np.abs(Z["y"][:, 0]) <= max(0.1, 0.51 * Z["px"])
    cols = np.abs(Z["x"][0]) < 7.5
    prof_t = -Z["tgx"][rows][:, cols].mean(axis=0)
    prof_s = -sharp.dzdx[rows][:, cols].mean(axis=0)
    from scipy.ndimage import gaussian_filter

    blur_t = gaussian_filter(-Z["tgx"], FWHM / FWHM_PER_SIGMA / Z["px"], mode="nearest")
    prof_bt = blur_t[rows][:, cols].mean(axis=0)
    prof_b = -beam.dzdx[rows][:, cols].mean(axis=0)
    rel_s = float(np.sqrt(np.mean((prof_s - prof_t) ** 2)) / np.sqrt(np.mean(prof_t ** 2)))
    rel_b = float(np.sqrt(np.mean((prof_b - prof_bt) ** 2)) / np.sqrt(np.mean(prof_bt ** 2)))
    st.add(Row(
        "11b", "Fig. 11b: the line profiles along x at y = 0 of the modelled and the true gradient match closely",
        "close match", f"rms(Eq. 26 − true)/rms(true) along y = 0: {100 * rel_s:.0f} % (sharp beam), "
        f"{100 * rel_b:.0f} % (0.27 mm beam vs. the true gradient blurred alike)", Z["settings"] + "; profile = "
        f"mean of rows |y| ≤ {max(0.1, 0.51 * Z['px']):.2f} mm, |x| < 7.5 mm", verdict_from(max(rel_s, rel_b) < 0.25),
        "criterion < 25 % (includes Monte Carlo noise)", {"profile_rel_rms_sharp": rel_s, "profile_rel_rms_beam": rel_b},
        "fig11_gradient_zoom"))

    # digitisation: facet gradient vs the analytic surface
    d_dig = float(np.sqrt(np.mean((Z["tgx"][ins] - Z["agx"][ins]) ** 2)) / np.sqrt(np.mean(Z["agx"][ins] ** 2)))
    e_facet = float(np.sqrt(np.mean((sharp.dzdx[ins] - Z["tgx"][ins]) ** 2)))
    e_analytic = float(np.sqrt(np.mean((sharp.dzdx[ins] - Z["agx"][ins]) ** 2)))
    st.add(Row(
        "11c", "Secs. 3.2, 4.2: the digitisation of the height map (mesh) has a slight averaging effect without "
        "significant influence; model−microscope differences come from it", "slight",
        f"mesh facets vs. the exact surface: rms ∂Z/∂x difference {100 * d_dig:.0f} % of rms ∂Z/∂x; Eq. 26 error "
        f"vs. facets {fmt(e_facet, 2)}, vs. exact surface {fmt(e_analytic, 2)}", Z["settings"] + "; mesh: 0.2 mm grid",
        verdict_from(e_facet <= e_analytic and d_dig < 0.35), "", {"digitisation_rel": d_dig,
                                                                  "eq26_err_facet": e_facet, "eq26_err_exact": e_analytic},
        "fig11_gradient_zoom"))

    # height reconstruction (full field) from Eq. 26 against 'M_x as gradient'
    g = F["g"]
    ztrue = F["z"]
    recs = {}
    for name, (gx, gy) in (("Eq. 26", (g.dzdx, g.dzdy)),
                           ("M_x as gradient", A.raw_gradient(g.mx, g.my)),
                           ("M_x · d_h/d_w", A.raw_gradient(g.mx, g.my, DH, DW))):
        zr, _ = A.integrate_gradient(gx, gy, FULL_FIELD, method="dct", mask=g.mask if g.mask.any() else None)
        zr = zr - np.mean(zr - ztrue)
        recs[name] = (zr, float(np.sqrt(np.mean((zr - ztrue) ** 2))))
    pv = float(ztrue.max() - ztrue.min())
    from scipy.ndimage import gaussian_filter as _gf

    zblur = _gf(ztrue, F["fwhm"] / FWHM_PER_SIGMA / (FULL_FIELD / F["res"]), mode="nearest")
    e_blur = float(np.sqrt(np.mean((recs["Eq. 26"][0] - np.mean(recs["Eq. 26"][0] - zblur) - zblur) ** 2)))
    e26, eraw, escaled = (recs[k][1] for k in recs)
    st.add(Row(
        "3b", "Abstract, Secs. 1, 4.2: gradients from Eq. 26 serve as input of normal integration to reconstruct the "
        "build surface (Fig. 3b) — better than the earlier calibrated M_x", "no number",
        f"height RMSE {1e3 * e26:.1f} µm (Eq. 26) vs {1e3 * eraw:.1f} µm (M_x as gradient), {1e3 * escaled:.1f} µm "
        f"(M_x · d_h/d_w); relief peak-to-valley {1e3 * pv:.0f} µm; Eq. 26 vs. the true map blurred by the beam: "
        f"{1e3 * e_blur:.1f} µm", F["settings"] + "; DCT least-squares integration",
        verdict_from(e26 < 0.1 * pv and e26 < eraw and e26 <= escaled * 1.05), "criterion: RMSE < 10 % of P-V and "
        "below the M_x-based reconstructions", {"rmse_eq26_um": 1e3 * e26, "rmse_raw_um": 1e3 * eraw,
                                                 "rmse_scaled_um": 1e3 * escaled, "pv_um": 1e3 * pv}, "fig03_height"))

    mats, mset = _material(ctx, Z["field"])
    a, b = mats["Ti-6Al-4V"], mats["Cu"]
    xm, ym = A.pixel_coordinates(a.mx.shape, Z["field"])
    insm = in_squares(xm, ym) & ~a.mask & ~b.mask
    dmat = float(np.sqrt(np.mean((a.mx[insm] - b.mx[insm]) ** 2)) / np.sqrt(np.mean(a.mx[insm] ** 2)))
    st.add(Row(
        "6b", "Sec. 2.1.4: normalised difference images do not depend on the beam current nor on η (material "
        "contrast removed)", "independent", f"M_x(Cu) vs. M_x(Ti-6Al-4V): rms difference {fmt(100 * dmat, 2)} % of "
        "rms M_x", mset, verdict_from(dmat < 0.1, approx=dmat >= 0.03),
        "the Lambert part cancels exactly; the specular lobe's share (η(θ) − η0)/η differs between materials"
        if dmat >= 0.03 else "same random numbers for both materials, so the difference is systematic: the specular lobe's share "
        "(η(θ) − η0)/η depends on the material but is small at these slopes (< 15°)", {"material_rel_diff": dmat}))

    if ctx.figures:
        _fig6(ctx, st, F)
        _fig7_11(ctx, st, Z, prof=(cols, prof_t, prof_s, prof_b, prof_bt))
        _fig3(ctx, st, F, recs)
    st.text = (
        "The synthetic melt plate (3 × 3 squares, see scenes_xml/README.md) under the validation detectors, "
        "STSA-corrected with flat-plate renders of the same geometry. 'True' gradients are those of the mesh "
        "facets the beam hits (ray cast), the paper's 'microscope' gradient after digitisation. M_x falls short "
        "of the slope by about d_w/d_h; Eq. 26 restores it. With the ATHENE beam profile (Gaussian, 0.27 mm "
        "FWHM) the images blur as the paper's experiment does. The height map integrated from the Eq. 26 "
        "gradients reproduces the true one.")
    return st


def _fig6(ctx, st, F):
    import matplotlib.pyplot as plt

    import elo_mitsuba.analysis as A

    from .plotting import CMAP_DIVERGING, CMAP_ERROR, image, save

    g = F["g"]
    from scipy.ndimage import gaussian_filter

    pred, _ = A.eq24_differences(-F["tgx"], -F["tgy"], F["x"], F["y"], DH, DW)
    pred = gaussian_filter(pred, F["fwhm"] / FWHM_PER_SIGMA / (FULL_FIELD / F["res"]), mode="nearest")
    vmax = float(np.nanpercentile(np.abs(g.mx), 99.8))
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.3))
    image(fig, axs[0], g.mx, FULL_FIELD, title="(a) M_x, modelled (Eq. 15)", label="M_x", cmap=CMAP_DIVERGING,
          vmin=-vmax, vmax=vmax)
    image(fig, axs[1], pred, FULL_FIELD, title="(b) Eq. 24 from the true normals, same blur", label="M_x",
          cmap=CMAP_DIVERGING, vmin=-vmax, vmax=vmax)
    image(fig, axs[2], g.mx - pred, FULL_FIELD, title="(c) (a) − (b)", label="ΔM_x", cmap=CMAP_ERROR, symmetric=True)
    fig.suptitle("Fig. 6 analogue: STSA-corrected normalised difference image M_x of the melt plate")
    fig.tight_layout()
    save(fig, ctx, "fig06_mx_full", f"Fig. 6 analogue: M_x of the whole melt plate ({F['settings']}); (b) the "
         "point-detector prediction of Eq. 24 from the true facet normals; (c) their difference (the specular "
         "lobe and noise).", st)


def _fig7_11(ctx, st, Z, prof):
    import matplotlib.pyplot as plt

    from .plotting import CMAP_DIVERGING, image, save

    cols, prof_t, prof_s, prof_b, prof_bt = prof
    field = Z["field"]
    xs = Z["x"][0][cols]
    for fig_no, kind in ((7, "mx"), (11, "grad")):
        fig = plt.figure(figsize=(14, 7.6))
        gs = fig.add_gridspec(2, 3, height_ratios=(1.25, 1))
        if kind == "mx":
            imgs = (Z["gs"].mx, Z["gb"].mx, -Z["tgx"])
            titles = ("M_x, model (single ray)", "M_x, model with 0.27 mm beam", "true −∂Z/∂x (mesh facets)")
            labels = ("M_x", "M_x", "−∂Z/∂x")
            vm = float(np.nanpercentile(np.abs(imgs[2][Z["inside"]]), 99.5))
            lims = (vm * DW / DH, vm * DW / DH, vm)
        else:
            imgs = (-Z["gs"].dzdx, -Z["gb"].dzdx, -Z["tgx"])
            titles = ("−∂Z̄/∂x by Eq. 26, model", "−∂Z̄/∂x by Eq. 26, 0.27 mm beam", "true −∂Z/∂x (mesh facets)")
            labels = ("−∂Z/∂x",) * 3
            vm = float(np.nanpercentile(np.abs(imgs[2][Z["inside"]]), 99.5))
            lims = (vm, vm, vm)
        for j in range(3):
            ax = fig.add_subplot(gs[0, j])
            image(fig, ax, imgs[j], field, title=f"({'abc'[j]}) {titles[j]}", label=labels[j], cmap=CMAP_DIVERGING,
                  vmin=-lims[j], vmax=lims[j])
            ax.axhline(0, color="k", lw=0.5, ls=":")
        ax = fig.add_subplot(gs[1, :])
        if kind == "mx":
            mx_rows = np.abs(Z["y"][:, 0]) <= max(0.1, 0.51 * Z["px"])
            ax.plot(xs, Z["gs"].mx[mx_rows][:, cols].mean(axis=0), "C1-", lw=0.9, label="M_x, model")
            ax.plot(xs, Z["gb"].mx[mx_rows][:, cols].mean(axis=0), "C2-", lw=0.9, label="M_x, 0.27 mm beam")
            ax.plot(xs, prof_t, "k-", lw=0.9, label="true −∂Z/∂x")
            ax.plot(xs, prof_t * DW / DH, "k:", lw=0.8, label="true −∂Z/∂x × d_w/d_h")
        else:
            ax.plot(xs, prof_s, "C0-", lw=0.9, label="Eq. 26, model")
            ax.plot(xs, prof_b, "C2-", lw=0.9, label="Eq. 26, 0.27 mm beam")
            ax.plot(xs, prof_t, "k-", lw=0.9, label="true −∂Z/∂x")
            ax.plot(xs, prof_bt, "k--", lw=0.8, label="true, blurred by the beam")
        ax.axhline(0, color="0.6", lw=0.5)
        ax.set_xlabel("x (mm), y = 0")
        ax.set_ylabel("−∂Z/∂x, M_x")
        ax.set_xlim(xs[0], xs[-1])
        ax.set_title(f"({'d' if kind == 'mx' else 'd'}) profiles along x at y = 0 (middle square)")
        ax.legend(ncol=4, loc="upper center", fontsize=7.5)
        what = "M_x" if kind == "mx" else "the Eq. 26 gradient"
        fig.suptitle(f"Fig. {fig_no} analogue: {what} of the middle surface of the melt plate against the true gradient")
        fig.tight_layout()
        save(fig, ctx, f"fig{fig_no:02d}_{'mx' if kind == 'mx' else 'gradient'}_zoom",
             f"Fig. {fig_no} analogue: {what} of the middle surface ({Z['settings']}) against the true −∂Z/∂x "
             "of the mesh facets; bottom: profiles along y = 0.", st)


def _fig3(ctx, st, F, recs):
    import matplotlib.pyplot as plt

    from .plotting import CMAP_ERROR, CMAP_HEIGHT, image, save

    z = F["z"] * 1e3
    fig, axs = plt.subplots(1, 4, figsize=(18, 4.2))
    image(fig, axs[0], z, FULL_FIELD, title="(a) true height Z", label="Z (µm)", cmap=CMAP_HEIGHT)
    zr, e = recs["Eq. 26"]
    image(fig, axs[1], zr * 1e3, FULL_FIELD, title=f"(b) from Eq. 26 (RMSE {1e3 * e:.1f} µm)", label="Z (µm)",
          cmap=CMAP_HEIGHT, vmin=z.min(), vmax=z.max())
    image(fig, axs[2], (zr - F["z"]) * 1e3, FULL_FIELD, title="(c) error of (b)", label="ΔZ (µm)", cmap=CMAP_ERROR,
          symmetric=True)
    zr2, e2 = recs["M_x as gradient"]
    image(fig, axs[3], zr2 * 1e3, FULL_FIELD, title=f"(d) from M_x as gradient (RMSE {1e3 * e2:.1f} µm)",
          label="Z (µm)", cmap=CMAP_HEIGHT, vmin=z.min(), vmax=z.max())
    fig.suptitle("Fig. 3b analogue: height map of the melt plate reconstructed from modelled ELO images "
                 "(DCT least-squares normal integration)")
    fig.tight_layout()
    save(fig, ctx, "fig03_height", f"Height reconstruction ({F['settings']}): (a) the true height map (cf. Fig. 3b), "
         "(b) integrated from the Eq. 26 gradients, (c) its error, (d) integrated from M_x, M_y taken as the "
         "gradient (no Eq. 26).", st)
