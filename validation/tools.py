"""Numerical helpers the studies need that elo_mitsuba.analysis does not provide.

* :func:`half_asymmetry` — (top - bottom)/mean of an image with its Monte Carlo standard error;
* :func:`triangle_solid_angle_printed` — Van Oosterom-Strackee (Eq. A1) as printed;
* :func:`triangle_solid_angle_quadrature` — the solid angle of a triangle by midpoint quadrature;
* :func:`facet_gradient` — the gradient of the mesh the electrons actually hit (ray cast);
* :func:`fit_gaussian_blur` — FWHM of the Gaussian that maps a sharp image onto a blurred one;
* :func:`line_fit` — least-squares slope/intercept with the slope's standard error;
* :func:`centres_on_vertex_grid`, :func:`check_melt_resolution` — keep pixel centres off the
  melt-plate mesh's vertex grid (row E7).

Eq. 5 by quadrature over a disc detector (the exact 1st-event reference) is
:func:`elo_mitsuba.analysis.first_event.flat_plate_signal`.
"""

from __future__ import annotations

import numpy as np

from elo_mitsuba.schema import FWHM_PER_SIGMA  # re-exported for the studies


def half_asymmetry(img_a, img_b, y):
    """Asymmetry about the x-axis of the mean of two independent renders ``img_a``, ``img_b``.

    A = (mean over y > 0 - mean over y < 0) / mean, and its standard error from the pixel noise,
    estimated from the difference of the two renders (Var[(a+b)/2] = Var[a-b]/4 per pixel).
    """
    a = np.asarray(img_a, float)
    b = np.asarray(img_b, float)
    img = 0.5 * (a + b)
    diff = a - b
    top, bot = y > 0, y < 0
    mean = img.mean()
    asym = (img[top].mean() - img[bot].mean()) / mean
    se = np.sqrt(diff[top].var() / 4 / top.sum() + diff[bot].var() / 4 / bot.sum()) / mean
    return float(asym), float(se)


def triangle_solid_angle_printed(v1, v2, v3):
    """Solid angle of a plane triangle seen from the origin by Eq. A1 **as printed**: the last
    term of the denominator is (v1.v3)|v1| instead of (v2.v3)|v1| (docs/paper-notes.md §2). The
    corrected formula is :func:`elo_mitsuba.physics.triangle_solid_angle`."""
    v1, v2, v3 = (np.asarray(v, float) for v in (v1, v2, v3))
    n1, n2, n3 = (np.linalg.norm(v, axis=-1) for v in (v1, v2, v3))
    num = np.sum(v1 * np.cross(v2, v3), axis=-1)
    den = (n1 * n2 * n3 + np.sum(v1 * v2, axis=-1) * n3 + np.sum(v1 * v3, axis=-1) * n2
           + np.sum(v1 * v3, axis=-1) * n1)
    return np.abs(2.0 * np.arctan2(num, den))


def triangle_solid_angle_quadrature(v1, v2, v3, n=600):
    """Reference: int cos(psi)/r^2 dA over the triangle by midpoint rule on n^2 sub-triangles."""
    v1, v2, v3 = (np.asarray(v, float) for v in (v1, v2, v3))
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    keep = i + j < n
    # centroids of the "upright" sub-triangles and of the "inverted" ones
    u1, w1 = (i[keep] + 1 / 3) / n, (j[keep] + 1 / 3) / n
    keep2 = i + j < n - 1
    u2, w2 = (i[keep2] + 2 / 3) / n, (j[keep2] + 2 / 3) / n
    u = np.concatenate([u1, u2])
    w = np.concatenate([w1, w2])
    pts = v1 + u[:, None] * (v2 - v1) + w[:, None] * (v3 - v1)
    normal = np.cross(v2 - v1, v3 - v1)
    area = 0.5 * np.linalg.norm(normal)
    normal /= 2 * area
    r2 = np.sum(pts * pts, axis=-1)
    cos_psi = np.abs(pts @ normal) / np.sqrt(r2)
    return float(np.sum(cos_psi / r2) * area / n ** 2)


def facet_gradient(escene, x, y, wd, return_height=False):
    """dZ/dx, dZ/dy of the facet each beam ray hits (the gradient the electrons see).

    Rays from the gun pivot (0, 0, wd) towards (x, y, 0) (perspective projection, as the
    ``elo_beam`` sensor); returns arrays of the shape of ``x`` (NaN where nothing is hit), and with
    ``return_height`` also the height z of the hit point.
    """
    mi = escene.mi
    import drjit as dr

    xs = np.asarray(x, float).ravel()
    ys = np.asarray(y, float).ravel()
    d = np.stack([xs, ys, -np.full_like(xs, wd)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    ray = mi.Ray3f(mi.Point3f(0.0, 0.0, float(wd)),
                   mi.Vector3f(*(np.ascontiguousarray(d[:, i]).astype(np.float32) for i in range(3))))
    si = escene.scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    n = np.stack([np.array(si.n.x), np.array(si.n.y), np.array(si.n.z)], axis=-1).astype(float)
    dr.eval()
    nz = np.where(valid, n[:, 2], np.nan)
    gx = -n[:, 0] / nz
    gy = -n[:, 1] / nz
    shape = np.shape(x)
    if return_height:
        z = np.where(valid, np.array(si.p.z, dtype=float), np.nan)
        return gx.reshape(shape), gy.reshape(shape), z.reshape(shape)
    return gx.reshape(shape), gy.reshape(shape)


def fit_gaussian_blur(sharp, blurred, pixel_mm, region=None, max_fwhm_mm=1.0):
    """FWHM (mm) of the isotropic Gaussian G minimising |G * sharp - blurred|^2 over ``region``."""
    from scipy.ndimage import gaussian_filter
    from scipy.optimize import minimize_scalar

    sharp = np.asarray(sharp, float)
    blurred = np.asarray(blurred, float)
    region = np.ones(sharp.shape, bool) if region is None else region

    def cost(fwhm):
        s = fwhm / FWHM_PER_SIGMA / pixel_mm
        b = gaussian_filter(sharp, s, mode="nearest") if s > 1e-6 else sharp
        return float(np.mean((b - blurred)[region] ** 2))

    res = minimize_scalar(cost, bounds=(0.0, max_fwhm_mm), method="bounded", options={"xatol": 1e-4})
    return float(res.x), cost(res.x), cost(0.0)


def line_fit(x, y):
    """Least squares y = a x + b: returns (a, b, se_a, r)."""
    x = np.asarray(x, float).ravel()
    y = np.asarray(y, float).ravel()
    a, b = np.polyfit(x, y, 1)
    resid = y - (a * x + b)
    n = x.size
    se = np.sqrt(np.sum(resid ** 2) / max(n - 2, 1) / np.sum((x - x.mean()) ** 2)) if n > 2 else np.nan
    r = np.corrcoef(x, y)[0, 1] if n > 1 else np.nan
    return float(a), float(b), float(se), float(r)


def centres_on_vertex_grid(field_mm, res, pitch_mm=0.2, first_mm=-49.9, tol=1e-6):
    """True if some pixel centre of a ``res``-pixel scan of ``field_mm`` lies on a vertex line of the
    melt-plate mesh (vertices every ``pitch_mm`` from ``first_mm``). Such beam rays can slip through
    the mesh (see row E7), so the studies avoid these resolutions."""
    centres = -field_mm / 2 + (np.arange(res) + 0.5) * field_mm / res
    k = (centres - first_mm) / pitch_mm
    return bool(np.any(np.abs(k - np.round(k)) < tol / pitch_mm))


def check_melt_resolution(field_mm, res):
    if centres_on_vertex_grid(field_mm, res):
        raise ValueError(f"{res} px over {field_mm} mm puts pixel centres on the melt-plate mesh's 0.2 mm vertex "
                         "grid, where beam rays can slip through (row E7); choose another resolution")


def coverage(err, stated, sel=None):
    """Shares of the pixels ``sel`` (all by default) whose actual error ``err`` lies within 1x and
    2x the stated one ``stated`` (68 % and 95 % for a calibrated Gaussian error bar)."""
    err, stated = np.abs(np.asarray(err)), np.asarray(stated)
    if sel is not None:
        err, stated = err[sel], stated[sel]
    return float(np.mean(err <= stated)), float(np.mean(err <= 2 * stated))
