"""The Dr.Jit kernels of the height model's linear maps against their numpy definitions: the beam
blur against scipy's gaussian_filter, the corner stencil and the sub-pixel mean against
height_model's numpy maps, each transpose against its map, and the Gauss-Newton products of the
inversion (J^T W J v with the scale projected out, J^T W r) against the same products written
out in numpy (float64) on a linearisation whose model ratios, weights and scales are far from 1."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from elo_mitsuba.analysis.grid_kernels import GridKernels, gaussian_taps
from elo_mitsuba.analysis.height_model import STENCIL, blur, corner, corner_t, sub_pixel_mean

#: float32 products of float64 data: a few units of float32's 6e-8 of the largest value.
F32 = 1e-6


def _dr(k, a):
    return k.mi.Float(np.ascontiguousarray(a, np.float32).ravel())


def _np(a, shape):
    return np.asarray(a, np.float64).reshape(shape)


@pytest.mark.parametrize("shape, sigma", [((40, 33), (2.15, 3.0)), ((7, 5), (2.5, 0.7)), ((3, 3), (5.0, 5.0)),
                                          ((12, 9), (0.0, 1.5)), ((9, 12), (1.2, 0.0))])
def test_blur_is_scipys_gaussian_filter(mi, shape, sigma):
    """Anisotropic, one axis unblurred, and taps reaching past the far edge (multiple mirroring)."""
    rng = np.random.default_rng(0)
    k = GridKernels(shape, sigma)
    x = rng.standard_normal((2,) + shape)
    got = np.stack([_np(v, shape) for v in k.blur([_dr(k, a) for a in x])])
    ref = np.stack([gaussian_filter(a, sigma, mode="reflect", truncate=4.0) for a in x])
    assert np.max(np.abs(got - ref)) < F32 * np.max(np.abs(ref))
    assert np.allclose(got, np.stack([blur(a, sigma) for a in x]), rtol=0, atol=F32 * np.max(np.abs(ref)))


def test_taps_are_scipys():
    from scipy.ndimage import correlate1d

    from scipy.ndimage import gaussian_filter1d

    for s in (0.43, 2.15, 7.0):
        w = gaussian_taps(s)
        impulse = np.zeros(2 * len(w) + 1)
        impulse[len(w)] = 1.0
        ref = gaussian_filter1d(impulse, s, truncate=4.0, mode="constant")
        assert np.allclose(correlate1d(impulse, w, mode="constant"), ref, rtol=0, atol=1e-15)


@pytest.mark.parametrize("shape", [(5, 8), (1, 4), (6, 1)])
def test_corners_and_their_transpose(mi, shape):
    rng = np.random.default_rng(1)
    k = GridKernels(shape, (0.0, 0.0))
    g = rng.standard_normal((shape[0] + 1, shape[1] + 1))
    got = [_np(c, shape) for c in k.corners(_dr(k, g))]
    for c, name in zip(got, STENCIL):
        assert np.allclose(c, corner(g, name), rtol=0, atol=F32)
    v = [rng.standard_normal(shape) for _ in STENCIL]
    got_t = _np(k.corners_t([_dr(k, a) for a in v]), g.shape)
    assert np.allclose(got_t, sum(corner_t(a, name) for a, name in zip(v, STENCIL)), rtol=0, atol=10 * F32)


def test_sub_pixel_mean_and_spread(mi):
    rng = np.random.default_rng(2)
    fine, f = (12, 9), 3
    k = GridKernels(fine, (0.0, 0.0))
    x = rng.standard_normal(fine)
    got = _np(k.sub_pixel_mean([_dr(k, x)], f)[0], (4, 3))
    assert np.allclose(got, sub_pixel_mean(x, f), rtol=0, atol=F32)
    v = rng.standard_normal((4, 3))
    spread = _np(k.sub_pixel_spread([_dr(k, v)], f)[0], fine)
    assert abs(np.sum(got * v) - np.sum(x * spread)) < F32 * np.sum(np.abs(got * v))


def test_gauss_newton_products_against_numpy(mi):
    """J^T W J v and J^T W r of the inversion, the scale s projected out per pixel (Kaufman's
    variable projection), against numpy's composition of the definitions. Ratios m, weights and
    scales far from 1: with m ~ 1 and W ~ 1 a product that squares m or drops W agrees anyway."""
    from elo_mitsuba.analysis import height_solver as inv
    from elo_mitsuba.analysis.height_model import HeightModel, corners_from_pixels
    from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    from elo_mitsuba.grid import pixel_coordinates
    from elo_mitsuba.objects.hills import hills_height

    shape = (36, 44)
    geo = ScanGeometry.nominal(shape, 80, 272, 127)
    x, y = pixel_coordinates(shape, geo.field_mm)
    heights = 0.5 * hills_height(x, y)
    model = HeightModel(geo, fwhm_mm=3.0)
    flat = HeightModel(geo, fwhm_mm=3.0, shadows=False).images(np.zeros(shape))
    rng = np.random.default_rng(4)
    images = {n: v * (1 + 0.05 * rng.standard_normal(shape)) for n, v in model.images(heights).items()}
    data = inv.ScaleData(images, flat, None, None, None, None)
    setup = inv._set_up(data, geo, fwhm_mm=3.0, alpha=None, noise=0.01, shadows=True, nodes=inv.NODES)
    problem = setup.problem
    g = corners_from_pixels(0.7 * heights)  # not the truth: residuals too
    lin0 = problem.model.evaluate(g)
    _, r, s, m = problem.cost(g, lin0, 0.01)
    assert np.ptp(m) > 0.3 and np.ptp(s) > 0.1  # the case is not the trivial one
    lin = problem.model.evaluate(g, derivatives=True, visible=lin0.visible)
    weights = np.clip(rng.uniform(-0.5, 1.5, r.shape), 0.0, 1.0)  # Huber's weights, some 0
    eq = inv._NormalEquations(problem, lin, s, m, weights)
    wt, gain = problem.w * weights, s / problem.bf
    wmm = np.sum(wt * m * m, axis=0)
    wmm = np.where(wmm > 0, wmm, 1.0)

    def project(u):
        return u - m * (np.sum(wt * m * u, axis=0) / wmm)

    def jac(v):
        return np.stack([blur(d, problem.model.sigma_px)
                         for d in sum(lin.partials[i] * corner(v, c) for i, c in enumerate(STENCIL))])

    def jac_t(v):
        bv = np.stack([blur(a, problem.model.sigma_px) for a in v])
        return sum(corner_t(np.sum(lin.partials[i] * bv, axis=0), c) for i, c in enumerate(STENCIL))

    v = rng.standard_normal(g.shape)
    ref = jac_t(gain * wt * project(gain * jac(v))) + eq.regulariser_gradient(v)
    assert np.max(np.abs(eq.apply(v) - ref)) < 10 * F32 * np.max(np.abs(ref))
    ref_rhs = jac_t(gain * wt * project(r))
    assert np.max(np.abs(eq.data_rhs(r) - ref_rhs)) < 10 * F32 * np.max(np.abs(ref_rhs))

    # the projection does not depend on m's scale: faint model images (m ~ 1e-25, m^2 below float32's
    # range) give the same products, not NaN
    faint = inv._NormalEquations(problem, lin, s, m * 1e-25, weights)
    got = faint.apply(v)
    assert np.all(np.isfinite(got))
    assert np.max(np.abs(got - ref)) < 10 * F32 * np.max(np.abs(ref))
