"""The step of a part that a cliff cuts off, searched in its shadows (analysis/step_offsets.py).

Model images (the inversion's own forward model on a surface four times as fine as the scan, so
that the cliff is a wall one sub-pixel (0.05 mm) wide, as the search's refinement models it) of a raised square of 0.6 mm beside
flat powder; the start has the square integrated short (a third of its height) and smeared, as
the model gradient leaves a cliff. Gradient steps cannot use the shadow that the square casts (it
has no derivative); the search must. A cliff whose wall is one sub-pixel wide with its top edge on
the part's boundary (``cliff_corners``) must be searched with that wall.
"""

import numpy as np
import pytest

from elo_mitsuba.analysis.height_model import HeightModel, SuperResolvedModel, corners_from_pixels
from elo_mitsuba.analysis.inversion import invert_heights
from elo_mitsuba.analysis.scan_geometry import ScanGeometry

N = 64
FWHM = 0.25


def _step(height, part, powder):
    return float(np.median(height[part]) - np.median(height[powder]))


@pytest.fixture(scope="module", params=[0.6, 0.2], ids=["0.6mm", "0.2mm"])
def square_case(request):
    from scipy.ndimage import binary_dilation, binary_erosion, gaussian_filter

    step = request.param
    geo = ScanGeometry.nominal((N, N), 0.2 * N, 100.0, 150.0)
    yy, xx = np.mgrid[0:4 * N, 0:4 * N].astype(float)
    fine = step * ((np.abs(yy - 127.5) < 40) & (np.abs(xx - 127.5) < 40))   # cliffs on pixel edges
    rng = np.random.default_rng(5)
    lin = SuperResolvedModel(geo, 4, fwhm_mm=FWHM).evaluate(corners_from_pixels(fine))
    img = {k: lin.images[i] * (1 + 0.003 * rng.standard_normal((N, N))) for i, k in enumerate(geo.detectors)}
    flat = {k: v * (1 + 0.003 * rng.standard_normal(v.shape))
            for k, v in HeightModel(geo, fwhm_mm=FWHM, shadows=False).images(np.zeros((N, N))).items()}
    part = fine[::4, ::4] > 0
    start = gaussian_filter(step / 3.0 * part.astype(float), 1.5)
    inside = binary_erosion(part, iterations=4)
    powder = ~binary_dilation(part, iterations=12)
    kw = dict(start=start, fwhm_mm=FWHM, noise=0.003 * np.sqrt(2), uncertainty_probes=0, scales=1, iterations=3)
    return step, img, flat, geo, kw, inside, powder


def test_the_shadow_gives_the_step_that_the_slopes_miss(square_case):
    step, img, flat, geo, kw, inside, powder = square_case
    res = invert_heights(img, flat, geo, **kw)
    assert [p.status for p in res.steps] == ["lifted"], res.stopped
    assert res.steps[0].wall == "interpolated"  # the images' own wall: the sharp one fits no better
    found = _step(res.height, inside, powder)
    assert abs(found - step) < 0.1 * step, found
    assert res.steps[0].objective_after < res.steps[0].objective_before
    assert abs(res.steps[0].step_after - step) <= 2 * res.steps[0].error  # the stated uncertainty holds
    # without the search (no local refinement) the gradient steps keep most of the start's shortfall
    plain = invert_heights(img, flat, geo, local=False, **kw)
    assert _step(plain.height, inside, powder) < 0.7 * step
    assert plain.steps == []


def test_a_sharp_cliff_is_searched_with_a_sharp_wall():
    # the images of a cliff whose top edge lies on the part's boundary and whose wall is one facet
    # wide (cliff_corners): the search must choose that wall, and find the step with it
    from scipy.ndimage import binary_dilation, binary_erosion, gaussian_filter

    from elo_mitsuba.analysis.step_offsets import cliff_corners

    step = 0.6
    geo = ScanGeometry.nominal((N, N), 0.2 * N, 100.0, 150.0)
    yy, xx = np.mgrid[0:4 * N, 0:4 * N].astype(float)
    mask = ((np.abs(yy - 127.5) < 40) & (np.abs(xx - 127.5) < 40)).astype(float)
    rng = np.random.default_rng(5)
    lin = SuperResolvedModel(geo, 4, fwhm_mm=FWHM).evaluate(step * cliff_corners(mask, raised=True))
    img = {k: lin.images[i] * (1 + 0.003 * rng.standard_normal((N, N))) for i, k in enumerate(geo.detectors)}
    flat = {k: v * (1 + 0.003 * rng.standard_normal(v.shape))
            for k, v in HeightModel(geo, fwhm_mm=FWHM, shadows=False).images(np.zeros((N, N))).items()}
    part = mask[::4, ::4] > 0
    start = gaussian_filter(step / 3.0 * part.astype(float), 1.5)
    res = invert_heights(img, flat, geo, start=start, fwhm_mm=FWHM, noise=0.003 * np.sqrt(2), uncertainty_probes=0,
                         scales=1, iterations=3)
    assert [(p.status, p.wall) for p in res.steps] == [("lifted", "sharp")], res.stopped
    found = _step(res.height, binary_erosion(part, iterations=4), ~binary_dilation(part, iterations=12))
    assert abs(found - step) < 0.05 * step, found
    assert abs(res.steps[0].step_after - step) <= res.steps[0].error


def test_a_part_whose_images_hold_its_step_is_kept(square_case):
    # started at the true heights the search finds nothing better: kept
    step, img, flat, geo, kw, inside, powder = square_case
    yy, xx = np.mgrid[0:N, 0:N]
    truth = step * ((np.abs(yy - 31.5) < 10) & (np.abs(xx - 31.5) < 10))
    res = invert_heights(img, flat, geo, **dict(kw, start=truth, iterations=1))
    assert all(p.status != "lifted" or abs(p.step_after - step) < 0.1 * step for p in res.steps)
    assert abs(_step(res.height, inside, powder) - step) < 0.1 * step


@pytest.mark.parametrize("square_case", [0.6], indirect=True, ids=["0.6mm"])
def test_a_lift_that_would_shrink_the_solves_step_is_refused(square_case):
    # a start twice the true step: the images' best step is the true one, half the solve's. At a
    # cliff the slopes only lose height, so a smaller best step is taken for the model's misfit (on
    # the smooth hills such lifts put parts 0.46-0.77 mm off): kept, with the reason
    from scipy.ndimage import gaussian_filter

    step, img, flat, geo, kw, inside, powder = square_case
    yy, xx = np.mgrid[0:N, 0:N]
    start = gaussian_filter(2 * step * ((np.abs(yy - 31.5) < 10) & (np.abs(xx - 31.5) < 10)).astype(float), 1.5)
    res = invert_heights(img, flat, geo, **dict(kw, start=start))
    statuses = [p.status for p in res.steps]
    assert statuses and all(s.startswith("kept (its best step") and "MAX_SHRINK" in s for s in statuses), statuses
    assert _step(res.height, inside, powder) > 1.5 * step


def _small_cliff_case():
    """A 0.1 mm square the solve left as a smeared ramp of two thirds of it, its misfit above the
    noise on two of its four walls only (as on the stepped layer's 0.1 mm cliffs, 56-65 % of the
    wall): no band of misfit closes round it, the ramp does."""
    from scipy.ndimage import binary_dilation, binary_erosion, gaussian_filter

    from elo_mitsuba.analysis.height_solver import ALPHA_PER_NOISE2

    step, noise = 0.1, 0.003
    geo = ScanGeometry.nominal((N, N), 0.2 * N, 100.0, 150.0)
    yy, xx = np.mgrid[0:4 * N, 0:4 * N].astype(float)
    fine = step * ((np.abs(yy - 127.5) < 40) & (np.abs(xx - 127.5) < 40))
    rng = np.random.default_rng(5)
    lin = SuperResolvedModel(geo, 4, fwhm_mm=FWHM).evaluate(corners_from_pixels(fine))
    img = {k: lin.images[i] * (1 + noise * rng.standard_normal((N, N))) for i, k in enumerate(geo.detectors)}
    flat = {k: v * (1 + noise * rng.standard_normal(v.shape))
            for k, v in HeightModel(geo, fwhm_mm=FWHM, shadows=False).images(np.zeros((N, N))).items()}
    part = fine[::4, ::4] > 0
    height = gaussian_filter(step * 2.0 / 3.0 * part.astype(float), 0.7)
    expected = noise * np.sqrt(2)
    misfit = np.full((N, N), expected)
    gy, gx = np.gradient(height, 0.2)
    wall = np.hypot(gx, gy) > 0.06
    half = np.zeros((N, N), bool)
    half[:, :N // 2] = half[:N // 2, :] = True
    misfit[wall & half] = 3.0 * expected
    kw = dict(fwhm_mm=FWHM, noise=expected, alpha=ALPHA_PER_NOISE2 * expected ** 2)
    inside, powder = binary_erosion(part, iterations=3), ~binary_dilation(part, iterations=8)
    return step, height, misfit, expected, img, flat, geo, kw, inside, powder


def test_a_cliff_whose_misfit_does_not_close_round_it_is_found_by_its_ramp_and_lifted():
    from elo_mitsuba.analysis.local_inversion import threshold
    from elo_mitsuba.analysis.noise import local_chi2
    from elo_mitsuba.analysis.step_offsets import edge_parts, floating_parts, search_offsets

    step, height, misfit, expected, img, flat, geo, kw, inside, powder = _small_cliff_case()
    limit = threshold()
    chi2 = local_chi2(misfit, expected)
    assert floating_parts(chi2, limit) == []
    assert [int(c.sum()) for c, _, _ in edge_parts(height, chi2, limit, (0.2, 0.2))] == [324]
    out, parts, error = search_offsets(height, misfit, expected, limit, img, flat, geo, **kw)
    assert [p.status for p in parts] == ["lifted"]
    assert abs(_step(height, inside, powder) - step) > 0.3 * step  # the solve's two thirds
    assert abs(_step(out, inside, powder) - step) < 0.1 * step, _step(out, inside, powder)
    assert abs(parts[0].step_after - step) <= parts[0].error
    # the same ramp where the images agree with it (misfit at the noise): not a part
    assert edge_parts(height, local_chi2(np.full((N, N), expected), expected), limit, (0.2, 0.2)) == []


def test_a_steep_band_is_a_cliff_only_against_the_fields_own_slopes():
    # a 70 um step with misfit everywhere is a part; on a field whose slopes are steep everywhere
    # (ridges of slope up to 0.09, median 0.06, as on rough relief) its ramp does not stand out and
    # cuts nothing off; a part that a band of misfit already cuts off is floating_parts' alone
    from elo_mitsuba.analysis.step_offsets import edge_parts, floating_parts

    h = np.zeros((60, 60))
    h[20:40, 20:40] = 0.07
    chi2 = np.full((60, 60), 3.0)
    assert [int(c.sum()) for c, _, _ in edge_parts(h, chi2, 2.0, (0.2, 0.2))] == [324]
    ridged = h + 0.03 * np.sin(2 * np.pi * 0.2 * np.arange(60) / 2.0)[None, :]
    assert edge_parts(ridged, chi2, 2.0, (0.2, 0.2)) == []
    closed = np.ones((60, 60))
    closed[18:42, 18:42] = 3.0
    closed[21:39, 21:39] = 1.0
    assert len(floating_parts(closed, 2.0)) == 1
    assert edge_parts(h, closed, 2.0, (0.2, 0.2)) == []


def test_a_step_whose_shadow_leaves_the_window_is_not_searched():
    # a 5 mm plateau (the top of a hill cut off by masked slopes): its shadow at 40 degrees reaches
    # 6 mm, beyond the window's 3.2 mm margin, so the search would measure nothing; reported, kept
    from elo_mitsuba.analysis.step_offsets import search_offsets

    geo = ScanGeometry.nominal((N, N), 0.2 * N, 100.0, 150.0)
    h = np.zeros((N, N))
    h[20:44, 20:44] = 5.0
    misfit = np.full((N, N), 1e-3)
    misfit[16:48, 16:48] = 1.0
    misfit[22:42, 22:42] = 1e-3
    flat = HeightModel(geo, shadows=False).images(np.zeros((N, N)))
    out, parts, error = search_offsets(h, misfit, 1e-3, 2.0, flat, flat, geo, fwhm_mm=FWHM, noise=1e-3, alpha=1e-3)
    assert [p.status for p in parts] == ["not searched (step beyond its window)"]
    assert np.array_equal(out, h) and np.isnan(error).all()



def test_an_island_smaller_than_a_part_is_not_searched():
    # islands of trusted pixels that bands of misfit cut off, as on steep slopes, on 0.05 mm pixels:
    # the part the misfit leaves of a 1 x 1 mm island (its core, less the misfit window's reach) is
    # too small to be a part beside powder: reported, kept; that of a 1.5 x 1.5 mm one is searched
    from elo_mitsuba.analysis.step_offsets import MIN_PART_MM2, search_offsets

    geo = ScanGeometry.nominal((N, N), 0.05 * N, 100.0, 150.0)
    flat = HeightModel(geo, shadows=False).images(np.zeros((N, N)))
    statuses = []
    for side in (20, 30):
        a, b = 32 - side // 2, 32 + side // 2
        h = np.zeros((N, N))
        h[a:b, a:b] = 0.2
        misfit = np.full((N, N), 1e-3)
        misfit[a - 8:b + 8, a - 8:b + 8] = 1.0
        misfit[a:b, a:b] = 1e-3
        out, parts, error = search_offsets(h, misfit, 1e-3, 2.0, flat, flat, geo, fwhm_mm=FWHM, noise=1e-3,
                                           alpha=1e-3)
        assert len(parts) == 1
        statuses.append((parts[0].status, parts[0].pixels * 0.05 ** 2))
        if parts[0].status.startswith("not searched"):
            assert np.array_equal(out, h) and np.isnan(error).all()
    assert statuses[0][0] == "not searched (smaller than MIN_PART_MM2)" and statuses[0][1] < MIN_PART_MM2
    assert not statuses[1][0].startswith("not searched") and statuses[1][1] >= MIN_PART_MM2

def _floating_parts_whole_field(chi2, limit):
    """floating_parts as first written: every growth dilates the whole field (the reference that
    the bounding-box version must reproduce exactly)."""
    from scipy.ndimage import binary_dilation, label

    from elo_mitsuba.analysis.step_offsets import MIN_COMPONENT_PX, RING_PX

    bad = chi2 > limit
    labels, n = label(~bad)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    reference = int(np.argmax(sizes))
    out = []
    for k in range(1, n + 1):
        if k == reference or sizes[k] < MIN_COMPONENT_PX:
            continue
        comp = labels == k
        grown, band, ring = comp, np.zeros_like(comp), np.zeros_like(comp)
        for _ in range(4 * RING_PX):
            nxt = binary_dilation(grown)
            new = nxt & ~grown
            band |= new & bad
            ring |= new & ~bad & ~comp
            grown = nxt
            if ring.sum() >= min(sizes[k], 4 * RING_PX * RING_PX):
                break
        if ring.any():
            out.append((comp, band, ring))
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_floating_parts_grown_in_a_box_are_those_grown_over_the_whole_field(seed):
    """Rings of misfit of random size and width (some cut by the field's edge, some wider than the
    growth reaches) around random parts: the same parts, bands and rings as the whole-field growth."""
    from elo_mitsuba.analysis.step_offsets import floating_parts

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:300, 0:260].astype(float)
    chi2 = np.ones(yy.shape)
    for _ in range(9):
        cy, cx = rng.uniform(-10, 310), rng.uniform(-10, 270)
        r, w = rng.uniform(4, 40), rng.uniform(1, 60)
        d = np.hypot(yy - cy, xx - cx)
        chi2[(d > r) & (d < r + w)] = 9.0
    got, want = floating_parts(chi2, 2.0), _floating_parts_whole_field(chi2, 2.0)
    assert len(want) >= 3
    assert len(got) == len(want)
    for g, w in zip(got, want):
        for a, b in zip(g, w):
            assert np.array_equal(a, b)


def _rimmed_plateau(band_misfit=1.0):
    # a plateau 0.1 mm high whose rim falls smoothly over 1.6 mm (a melt square's, not a cliff), its
    # images the model's own of it; a band of misfit (as the model's error at a rim leaves one) closes
    # round its top: what the solve holds is already the surface
    from elo_mitsuba.analysis.step_offsets import search_offsets

    geo = ScanGeometry.nominal((N, N), 0.2 * N, 100.0, 150.0)
    yy, xx = np.mgrid[0:N, 0:N].astype(float)
    d = np.maximum(np.abs(yy - 31.5), np.abs(xx - 31.5))
    h = 0.1 * np.clip((24.0 - d) / 8.0, 0.0, 1.0) ** 2 * (3 - 2 * np.clip((24.0 - d) / 8.0, 0.0, 1.0))
    img = HeightModel(geo, fwhm_mm=FWHM).images(h)
    flat = HeightModel(geo, fwhm_mm=FWHM, shadows=False).images(np.zeros((N, N)))
    misfit = np.where((d < 26) & (d >= 14), band_misfit, 1e-3)

    def search(**kw):
        return search_offsets(h, misfit, 1e-3, 2.0, img, flat, geo, fwhm_mm=FWHM, noise=2e-3, alpha=1e-3, **kw)
    return h, search, misfit


def test_a_rim_that_a_clean_step_cannot_describe_is_not_searched():
    h, search, _ = _rimmed_plateau()
    out, parts, error = search()
    assert len(parts) == 1 and parts[0].status.startswith("not searched (no cliff"), parts
    assert np.array_equal(out, h) and np.isnan(error).all()


def test_a_part_whose_band_is_no_cliff_takes_the_bands_error_not_its_step():
    """Its offset is what the band's heights carry: the noise part scaled by the band's misfit
    (3 noise levels here, chi-square 9 inside the band), RMS over the band (the band round the
    part, floating_parts), with the 7x7 chi-square computed here by hand; not the whole 0.1 mm
    step, which is what the floating part's rule (offset_errors) would state."""
    from scipy.ndimage import uniform_filter

    from elo_mitsuba.analysis.step_offsets import floating_parts

    h, search, misfit = _rimmed_plateau(band_misfit=3e-3)
    noise = np.full(h.shape, 2e-3)
    out, parts, error = search(noise_error=noise)
    assert len(parts) == 1 and parts[0].status.startswith("not searched (no cliff"), parts
    chi2 = uniform_filter((misfit / 1e-3) ** 2, 7, mode="nearest")
    (_, band, _), = floating_parts(chi2, 2.0)
    want = 2e-3 * np.sqrt(np.mean(np.maximum(chi2[band], 1.0)))
    assert parts[0].error == pytest.approx(want, rel=1e-9) and 4e-3 < want < 6e-3
    assert error[31, 31] == pytest.approx(want, rel=1e-9) and np.isnan(error[2, 2])
    assert np.array_equal(out, h)

