"""Eqs. 15-26 on point-detector-model images; STSA correction; masks; orientation conventions."""

import numpy as np
import pytest

from elo_mitsuba.analysis import (
    MASK_BITS,
    detector_masking,
    eq24_differences,
    flat_plate_images,
    gradient_from_differences,
    normalised_differences,
    pixel_coordinates,
    point_detector_images,
    raw_gradient,
    stsa_correct,
    sum_images,
    surface_gradient,
)
from elo_mitsuba.constants import (
    DETECTOR_DISTANCE_MM,
    DETECTOR_HEIGHT_MM,
    DETECTOR_NAMES,
    FIELD_MM,
    TABLE1_LAYOUTS,
)
from elo_mitsuba.errors import EloInputError

DH, DW = DETECTOR_HEIGHT_MM, DETECTOR_DISTANCE_MM


def random_gradient(n, lim=1.0, seed=3):
    rng = np.random.default_rng(seed)
    return rng.uniform(-lim, lim, (n, n)), rng.uniform(-lim, lim, (n, n))


def test_pixel_coordinates_convention():
    x, y = pixel_coordinates((4, 8), (80.0, 40.0))
    assert x[0, 0] == pytest.approx(-40 + 5) and x[0, -1] == pytest.approx(40 - 5)
    assert y[0, 0] == pytest.approx(20 - 5) and y[-1, 0] == pytest.approx(-20 + 5)  # row 0 = +y edge
    assert np.all(np.diff(x, axis=1) > 0) and np.all(np.diff(y, axis=0) < 0)
    with pytest.raises(EloInputError):
        pixel_coordinates((4, 4), -1.0)


@pytest.mark.parametrize("zeta", sorted(TABLE1_LAYOUTS))
@pytest.mark.parametrize("beam", ["vertical", "pivot"])
def test_eq26_exact_for_lambert_point_detector(zeta, beam):
    """Eq. 26 recovers the gradient at every pixel of the 80 mm field to 1e-6 (Lambert, Eq. 19).

    The paper derives it for a vertical beam; the pivot case checks that eta(theta)/eta_C cancels.
    Slopes up to 0.3 so that no detector of the steepest layout (zeta 75, d_h/d_w = 0.27) is masked.
    """
    dh, dw = TABLE1_LAYOUTS[zeta]
    n = 161  # odd: includes the pixel at the origin; corners at +-39.75 mm
    lim = 0.9 * dh / (dw + FIELD_MM / 2) if zeta > 25 else 1.0
    gx, gy = random_gradient(n, lim)
    kw = dict(model="lambert", beam=beam, detector_radius_mm=25.0)
    res = surface_gradient(point_detector_images(gx, gy, FIELD_MM, dh, dw, **kw),
                           flat_plate_images(gx.shape, FIELD_MM, dh, dw, **kw), FIELD_MM, dh, dw)
    assert not res.mask.any()
    assert np.max(np.abs(res.dzdx - gx)) <= 1e-6
    assert np.max(np.abs(res.dzdy - gy)) <= 1e-6


def test_raw_m_shows_dw_over_dh_and_position_dependence():
    """Eq. 24: M_x = n_Sx d_w / (d_h - n_Sx x - n_Sy y); raw -M_x is not the gradient."""
    n = 161
    x, y = pixel_coordinates((n, n), FIELD_MM)
    gx = np.full((n, n), -1.0)            # n_S = [1, 0, 1], the rising flank of Sec. 4.2
    gy = np.zeros((n, n))
    imgs = point_detector_images(gx, gy, FIELD_MM, DH, DW)
    flats = flat_plate_images(gx.shape, FIELD_MM, DH, DW)
    corrected, _ = stsa_correct(imgs, flats)
    mx, my, mask = normalised_differences(corrected)
    assert not mask.any()
    # the model images follow Eq. 24 exactly
    ex, ey = eq24_differences(1.0, 0.0, x, y, DH, DW)
    assert np.max(np.abs(mx - ex)) < 1e-12 and np.max(np.abs(my - ey)) < 1e-12
    c = n // 2
    assert mx[c, c] == pytest.approx(DW / DH, abs=1e-12)                 # d_w/d_h at x = 0
    assert mx[c, 0] == pytest.approx(DW / (DH - x[c, 0]), abs=1e-12)     # d_w/(d_h - x) at x < 0
    assert mx[c, -1] == pytest.approx(DW / (DH - x[c, -1]), abs=1e-12)
    assert mx[c, 0] < mx[c, c] < mx[c, -1]
    rx, _ = raw_gradient(mx, my)
    assert np.max(np.abs(rx - gx)) > 0.45                                 # raw M_x is ~0.47 x the slope
    sx, _ = raw_gradient(mx, my, DH, DW)
    assert np.max(np.abs(sx - gx)) > 0.1                                  # rescaling leaves the x-dependence
    assert sx[c, c] == pytest.approx(-1.0, abs=1e-12)
    dzdx, dzdy, m = gradient_from_differences(mx, my, FIELD_MM, DH, DW)
    assert not m.any() and np.max(np.abs(dzdx - gx)) < 1e-12 and np.max(np.abs(dzdy)) < 1e-12


def test_sign_convention_rising_towards_right_darkens_right():
    gx = np.full((5, 5), 0.5)   # Z rises towards +x: n_S tilts towards -x (Eq. 16)
    imgs = point_detector_images(gx, 0 * gx, 10.0, DH, DW)
    assert np.all(imgs["right"] < imgs["left"])
    res = surface_gradient(imgs, flat_plate_images(gx.shape, 10.0, DH, DW), 10.0, DH, DW)
    assert np.all(res.mx < 0) and np.allclose(res.dzdx, 0.5)


def test_sum_images_eq23():
    n = 41
    x, y = pixel_coordinates((n, n), FIELD_MM)
    gx, gy = random_gradient(n, 0.8)
    corrected, _ = stsa_correct(point_detector_images(gx, gy, FIELD_MM, DH, DW, model="diffuse"),
                                flat_plate_images((n, n), FIELD_MM, DH, DW, model="diffuse"))
    s_x, s_y = sum_images(corrected)
    nrm = np.sqrt(gx**2 + gy**2 + 1)
    expect = 2 / nrm * (1 - (-gx * x - gy * y) / DH)    # eta/eta_C = 1 for the diffuse part
    assert np.allclose(s_x, expect, atol=1e-12) and np.allclose(s_y, expect, atol=1e-12)


def test_full_gbse_departure_is_measured():
    """With the specular lobe of Eq. 13, Eq. 26 is only approximate. Measured (61 x 61, 80 mm,
    slopes uniform in [-1, 1], zeta 25, vertical beam): median |error| 0.082, max 0.33 mm/mm
    (length of the gradient error vector).
    We assert it is clearly non-zero and bounded, not that it vanishes."""
    n = 61
    gx, gy = random_gradient(n, 1.0)
    kw = dict(model="g_bse", beam="vertical")
    res = surface_gradient(point_detector_images(gx, gy, FIELD_MM, DH, DW, **kw),
                           flat_plate_images((n, n), FIELD_MM, DH, DW, **kw), FIELD_MM, DH, DW)
    err = np.hypot(res.dzdx - gx, res.dzdy - gy)[~res.mask]
    med, mx = float(np.median(err)), float(err.max())
    print(f"\nfull g_BSE: Eq. 26 error median {med:.3f}, max {mx:.3f} mm/mm")
    assert 1e-3 < med < 0.2 and mx < 0.6


def test_masked_detector_gives_mask_not_nan():
    """A surface steep enough that the right detector is behind its tangent plane: R = 0."""
    n = 21
    gx = np.zeros((n, n))
    gx[5:10, 5:10] = 3.0     # n_Sx = -3 < -d_h/d_w: right detector masked (Sec. 4.3)
    imgs = point_detector_images(gx, 0 * gx, FIELD_MM, DH, DW)
    flats = flat_plate_images(gx.shape, FIELD_MM, DH, DW)
    assert np.all(imgs["right"][5:10, 5:10] == 0)
    geo = detector_masking(gx, 0 * gx, FIELD_MM, DH, DW)
    assert np.array_equal(geo["right"], imgs["right"] == 0)
    res = surface_gradient(imgs, flats, FIELD_MM, DH, DW)
    assert np.array_equal(res.mask, gx > 0)
    assert np.all(res.reasons[5:10, 5:10] & MASK_BITS["detector_dark"])
    assert np.all(res.dzdx[res.mask] == 0)
    for arr in (res.dzdx, res.dzdy, res.mx, res.my, res.sum_x, res.sum_y):
        assert np.all(np.isfinite(arr))
    assert np.max(np.abs(res.dzdx[~res.mask] - gx[~res.mask])) < 1e-9


def test_zero_nan_and_inf_inputs_are_masked():
    n = 16
    flats = flat_plate_images((n, n), FIELD_MM, DH, DW)
    imgs = {k: v.copy() for k, v in flats.items()}
    imgs["left"][1, 1] = np.nan
    imgs["back"][2, 2] = np.inf
    flats = {k: v.copy() for k, v in flats.items()}
    flats["front"][3, 3] = 0.0            # dead flat pixel: division impossible
    for k in DETECTOR_NAMES:
        imgs[k][4, 4] = 0.0               # all four dark: sums are 0
    imgs["right"][5, 5] = 0.0             # one detector dark
    with np.errstate(all="raise"):       # no division by zero or invalid operation on the way
        res = surface_gradient(imgs, flats, FIELD_MM, DH, DW)
    expected = np.zeros((n, n), dtype=bool)
    for ij in ((1, 1), (2, 2), (3, 3), (4, 4), (5, 5)):
        expected[ij] = True
    assert np.array_equal(res.mask, expected)
    assert res.reasons[1, 1] & MASK_BITS["invalid_input"] and res.reasons[3, 3] & MASK_BITS["invalid_input"]
    assert res.reasons[4, 4] & MASK_BITS["sum_small"] and res.reasons[5, 5] & MASK_BITS["detector_dark"]
    for arr in (res.dzdx, res.dzdy, res.mx, res.my, res.sum_x, res.sum_y, *res.corrected.values()):
        assert np.all(np.isfinite(arr))


def test_denominator_mask():
    mx = np.array([[0.5, -0.9]])
    my = np.zeros((1, 2))
    # x = -20 and +20 mm on a 80 x 40 mm field of 2 pixels; denominators 127 - 10, 127 - 18
    dzdx, _, m = gradient_from_differences(mx, my, (80.0, 40.0), DH, DW)
    assert not m.any()
    # M_x = 7 at x = -20 mm: d_w + x M_x = 127 - 140 < 0 (impossible for real data: masked)
    dzdx, _, m = gradient_from_differences(np.array([[7.0, 0.1]]), my, (80.0, 40.0), DH, DW)
    assert m.tolist() == [[True, False]] and dzdx[0, 0] == 0.0


def test_no_flat_and_input_errors():
    flats = flat_plate_images((8, 8), FIELD_MM, DH, DW)
    res = surface_gradient({k: np.ones((8, 8)) for k in DETECTOR_NAMES}, None, FIELD_MM, DH, DW)
    assert not res.mask.any() and np.all(res.dzdx == 0)
    with pytest.raises(EloInputError, match="missing detector"):
        stsa_correct({"right": flats["right"]}, flats)
    with pytest.raises(EloInputError, match="d_h"):
        gradient_from_differences(np.zeros((2, 2)), np.zeros((2, 2)), 10.0, -1.0, DW)
    with pytest.raises(EloInputError, match="model"):
        point_detector_images(np.zeros((2, 2)), np.zeros((2, 2)), 10.0, DH, DW, model="phong")
