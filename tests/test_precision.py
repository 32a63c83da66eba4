"""The Cramér-Rao bound of the gradient (issue 27) against the spread of model-gradient fits.

Noisy corrected images of the 1st-event model (Gaussian noise of a stated level on each of the
four corrected images: the case the fit's unweighted least squares is efficient for) are fitted
per pixel by :func:`~elo_mitsuba.analysis.model_gradient.model_gradient`; each pixel is one noise
draw. The measured spread of the fitted dZ/dx, dZ/dy must match the bound within 10 %.
"""

import numpy as np
import pytest

from elo_mitsuba.analysis.detector_model import model_images
from elo_mitsuba.analysis.model_gradient import model_gradient
from elo_mitsuba.analysis.precision import SignalNoise, bound_from_signals, design_metrics, gradient_bound
from elo_mitsuba.analysis.scan_geometry import ScanGeometry
from elo_mitsuba.errors import EloInputError

NOISE = 0.01
SHAPE = (64, 64)


def _fit_spread(dzdx, dzdy, field_mm, seed):
    g = ScanGeometry.nominal(SHAPE, field_mm, 272.0, 127.0)
    flats = model_images(g)
    obj = model_images(g, np.full(SHAPE, dzdx), np.full(SHAPE, dzdy))
    rng = np.random.default_rng(seed)
    corrected = {k: obj[k] / flats[k] + rng.normal(0.0, NOISE, SHAPE) for k in obj}
    res = model_gradient(corrected, None, g, noise=NOISE)
    bound = gradient_bound(g, dzdx, dzdy, noise=NOISE)
    ok = ~res.mask
    return res, bound, ok


@pytest.mark.parametrize("dzdx, dzdy", [(0.0, 0.0), (0.3, -0.2)], ids=["flat", "tilted"])
def test_bound_matches_the_spread_of_model_fits(dzdx, dzdy):
    # a 4 mm field: the bound is nearly the same at every pixel (within 5 %), so 4096 pixels are
    # 4096 draws of one estimate
    res, bound, ok = _fit_spread(dzdx, dzdy, 4.0, seed=1)
    assert ok.mean() > 0.99
    assert np.ptp(bound.sigma_dzdx) < 0.05 * bound.sigma_dzdx.mean()
    for fitted, true, sig in ((res.dzdx, dzdx, bound.sigma_dzdx), (res.dzdy, dzdy, bound.sigma_dzdy)):
        err = fitted[ok] - true
        assert abs(err.mean()) < 4 * sig.mean() / np.sqrt(ok.sum())  # unbiased: the bound applies
        ratio = err.std() / sig[ok].mean()
        assert 0.9 < ratio < 1.1, ratio


def test_bound_matches_the_fits_over_a_whole_field():
    """The 80 mm field, where the bound changes from pixel to pixel: errors over their own bound."""
    res, bound, ok = _fit_spread(0.2, 0.1, 80.0, seed=2)
    zx = (res.dzdx[ok] - 0.2) / bound.sigma_dzdx[ok]
    zy = (res.dzdy[ok] - 0.1) / bound.sigma_dzdy[ok]
    assert 0.9 < zx.std() < 1.1 and 0.9 < zy.std() < 1.1, (zx.std(), zy.std())
    # and the bound is not flat over the field (else the normalisation proves little)
    assert np.ptp(bound.sigma_dzdx) > 0.05 * bound.sigma_dzdx.mean()


def test_the_unknown_scale_costs_precision():
    """Eliminating s (the nuisance) must cost something on the flat plate's q-row: the bound with
    s known (the (p, q) block of F inverted) is smaller."""
    g = ScanGeometry.nominal((1, 1), 80.0, 272.0, 127.0)
    from elo_mitsuba.analysis.precision import facet_signals

    pts, dirs = g.beam(None)
    sig = facet_signals(g.detectors, g.material, pts.reshape(-1, 3), dirs.reshape(-1, 3), 0.3, 0.0)
    full = bound_from_signals(sig, NOISE)["covariance"][0]
    m = sig["S"][:, 0] / sig["flat"][:, 0]
    J = np.stack([sig["dS_dp"][:, 0], sig["dS_dq"][:, 0]], axis=-1) / sig["flat"][:, :1]
    known = np.linalg.inv(J.T @ J / NOISE ** 2)
    assert full[0, 0] > 1.01 * known[0, 0]
    assert np.all(m > 0)


def test_shot_noise_bound_scales_as_one_over_root_n():
    g = ScanGeometry.nominal((2, 2), 80.0, 272.0, 127.0)
    a = gradient_bound(g, 0.1, 0.0, noise=SignalNoise(1e6)).sigma_dzdx
    b = gradient_bound(g, 0.1, 0.0, noise=SignalNoise(4e6)).sigma_dzdx
    assert np.allclose(a / b, 2.0, rtol=1e-6)


def test_two_hidden_detectors_leave_the_gradient_unfixed():
    # zeta = 75 deg: a slope of 0.5 away from two detectors hides both (masking slope 0.27)
    g = ScanGeometry.nominal((1, 1), 80.0, 77.6, 289.6)
    b = gradient_bound(g, 0.5 / np.sqrt(2), 0.5 / np.sqrt(2), noise=NOISE)
    assert int(b.visible[0, 0]) == 2 and np.isinf(b.sigma_worst[0, 0])
    m = design_metrics(g.detectors, grid=2, s_max=0.5)
    assert m["sigma_worst"] == 1e3 and np.isfinite(m["sigma_median"])


def test_bad_noise_is_refused():
    g = ScanGeometry.nominal((1, 1), 80.0, 272.0, 127.0)
    with pytest.raises(EloInputError, match="noise"):
        gradient_bound(g, noise=0.0)
    with pytest.raises(EloInputError, match="primary electrons"):
        SignalNoise(-1.0)
