"""The one image orientation (elo_mitsuba.grid): numpy axes, film coordinates and the beam agree."""

import numpy as np
import pytest

from elo_mitsuba.errors import EloInputError
from elo_mitsuba.grid import field_xy, film_to_plane, pixel_axes, pixel_coordinates, pixel_size


def test_pixel_axes_orientation_by_hand():
    xs, ys = pixel_axes((2, 4), (80.0, 40.0))  # 4 columns over 80 mm, 2 rows over 40 mm
    np.testing.assert_allclose(xs, [-30.0, -10.0, 10.0, 30.0])  # columns towards +x
    np.testing.assert_allclose(ys, [10.0, -10.0])  # row 0 is the +y edge
    x, y = pixel_coordinates((2, 4), (80.0, 40.0))
    assert x.shape == y.shape == (2, 4) and x[0, 3] == 30.0 and y[0, 3] == 10.0
    assert pixel_size((2, 4), (80.0, 40.0)) == (20.0, 20.0)
    with pytest.raises(EloInputError, match="field_mm"):
        field_xy((80.0, -1.0))


@pytest.mark.parametrize("shape,field", [((7, 5), (80.0, 112.0)), ((1500, 1500), 80.0), ((3, 64), (10.0, 0.47))])
def test_film_coordinates_map_onto_the_pixel_axes(shape, field):
    h, w = shape
    fx, fy = field_xy(field)
    xs, ys = pixel_axes(shape, field)
    u, v = (np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h
    x, _ = film_to_plane(u, 0.5, fx, fy)
    _, y = film_to_plane(0.5, v, fx, fy)
    np.testing.assert_allclose(x, xs, rtol=0, atol=1e-12 * fx)
    np.testing.assert_allclose(y, ys, rtol=0, atol=1e-12 * fy)


def test_beam_aims_at_the_pixel_axes(mi):
    """The sensor's beam targets (float32, Dr.Jit) are the numpy pixel centres, up to the aim
    nudge (< 1 % of a pixel, at most 3 um)."""
    w, h, field = 6, 4, 60.0
    sensor = mi.load_dict({"type": "elo_beam", "field": field,
                           "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}}})
    j, i = np.mgrid[0:h, 0:w]
    u, v = (i.ravel() + 0.5) / w, (j.ravel() + 0.5) / h
    x, y = sensor.beam_target(mi.Point2f(mi.Float(u.astype(np.float32)), mi.Float(v.astype(np.float32))))
    xs, ys = pixel_axes((h, w), field)  # a scalar field: the width, as the sensor reads it
    dx, dy = sensor.aim_offset_mm  # recorded in every header as beam_aim_offset_mm
    assert 0 < dx < 3e-3 and 0 < dy < 3e-3
    np.testing.assert_allclose(np.array(x).reshape(h, w), np.broadcast_to(xs + dx, (h, w)), atol=1e-5)
    np.testing.assert_allclose(np.array(y).reshape(h, w), np.broadcast_to(ys[:, None] + dy, (h, w)), atol=1e-5)


@pytest.mark.parametrize("spp", [1, 3])
def test_every_sample_aims_at_its_own_pixel_at_the_edges_of_the_pixel(mi, spp):
    """Mitsuba's render passes pixel + u, u uniform in [0, 1), scaled to [0, 1] in float32, and puts
    the sample into the pixel itself (box filter). With u within half a float32 step of 1 (2^-13
    of a pixel from column 1024 on) the sum rounds to the next pixel, and the scalings round too
    (at 1500² a render aimed 148 pixels at their neighbour's scan point). The beam aims at the lane's own pixel: the render's lanes are pixels row by row, spp each
    (Mitsuba's wavefront), as here; a sample off by more than one pixel is taken as given."""
    w, h, field = 1500, 3, 80.0
    sensor = mi.load_dict({"type": "elo_beam", "field": field,
                           "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}}})
    xs, ys = pixel_axes((h, w), (field, field * h / w))
    dx, dy = sensor.aim_offset_mm
    lane = np.arange(w * h * spp) // spp
    col, row = (lane % w).astype(np.float32), (lane // w).astype(np.float32)
    scale = np.float32(1.0) / np.array([w, h], np.float32)
    for u in (np.nextafter(np.float32(1), np.float32(0)), np.float32(0)):
        pos_x, pos_y = col + u, row + u  # float32, as Mitsuba adds them
        assert u == 0 or np.count_nonzero(pos_x == col + 1) > 0.5 * w * spp  # the sum rounds up
        x, y = sensor.beam_target(mi.Point2f(mi.Float(pos_x * scale[0]), mi.Float(pos_y * scale[1])))
        np.testing.assert_allclose(np.array(x), xs[lane % w] + dx, rtol=0, atol=1e-4, err_msg=str(u))
        np.testing.assert_allclose(np.array(y), ys[lane // w] + dy, rtol=0, atol=1e-4, err_msg=str(u))
    # positions of its own (not a wavefront): the pixel they fall in
    x, _ = sensor.beam_target(mi.Point2f(mi.Float(np.float32([0.25, 0.75])), mi.Float(np.float32([0.5, 0.5]))))
    np.testing.assert_allclose(np.array(x), xs[[375, 1125]] + dx, rtol=0, atol=1e-4)


@pytest.mark.parametrize("quality", ["default", "reference"])
def test_four_detectors_see_a_flat_plate_as_rotations_at_the_pixel_centres(mi, quality):
    """Row E3's symmetry at the renderer's own precision: the presets' 1st event is a deterministic
    quadrature, so the images of the Eq. 17 layout must be rotations of each other to float32
    roundoff once taken at the pixel centres (measured 3.6e-7 to 6.9e-7 at 32²); at the nudged
    landing points they differ by 1.2e-5 to 3.2e-5, which a rotation cannot map."""
    import elo_mitsuba as em
    from elo_mitsuba.grid import at_pixel_centres

    r = em.load_scene("flat_plate", res=32).render(quality=quality, events=1, progress=False)
    field, offset = r.metadata["field_mm"], r.metadata["beam_aim_offset_mm"]
    raw = {n: r.channels[n].astype(float) for n in ("right", "back", "left", "front")}
    centred = {n: at_pixel_centres(v, field, offset) for n, v in raw.items()}
    for name, k in (("back", 1), ("left", 2), ("front", 3)):
        assert np.max(np.abs(centred[name] / np.rot90(centred["right"], k) - 1)) < 2e-6, name
        assert np.max(np.abs(raw[name] / np.rot90(raw["right"], k) - 1)) > 1e-5, name


def test_header_records_the_true_scan_positions(mi):
    import elo_mitsuba as em

    scene = em.load_scene("flat_plate", res=5, field=40.0)
    meta = scene.render(quality="default").metadata
    assert meta["beam_aim_offset_mm"] == list(scene.sensor.aim_offset_mm)


def test_a_scalar_field_is_the_width_of_a_non_square_image():
    """As the beam scans (field_y = field H/W, square pixels), so do the images."""
    xs, ys = pixel_axes((20, 40), 80.0)  # 20 rows, 40 columns, 80 mm wide
    assert pixel_size((20, 40), 80.0) == (2.0, 2.0)
    np.testing.assert_allclose([xs[0], xs[-1], ys[0], ys[-1]], [-39.0, 39.0, 19.0, -19.0])
    assert field_xy(80.0) == (80.0, 80.0) and field_xy(80.0, (20, 40)) == (80.0, 40.0)


def test_eq26_on_a_non_square_image_with_a_scalar_field():
    """Eq. 26 recovers a tilt exactly from the Lambert point-detector images (independent model)
    only where it places every row at the y the scan had: field 80 mm wide, 20 x 40 pixels."""
    from elo_mitsuba.analysis import point_detector_images, surface_gradient

    shape, d_h, d_w = (20, 40), 272.0, 127.0
    dzdx, dzdy = np.full(shape, 0.1), np.full(shape, -0.2)
    truth = (80.0, 40.0)  # the scan: 80 mm wide, square pixels
    images = point_detector_images(dzdx, dzdy, truth, d_h, d_w, model="lambert")
    flats = point_detector_images(0 * dzdx, 0 * dzdy, truth, d_h, d_w, model="lambert")
    g = surface_gradient(images, flats, 80.0, d_h, d_w)  # the field as a scalar width
    np.testing.assert_allclose(g.dzdx, dzdx, atol=1e-9)
    np.testing.assert_allclose(g.dzdy, dzdy, atol=1e-9)


def test_beam_profile_is_the_gaussian_of_its_fwhm(mi):
    """fwhm = 0.27 mm: the aim points of one pixel's samples scatter with sigma = FWHM/2.3548."""
    sensor = mi.load_dict({"type": "elo_beam", "field": 20.0, "fwhm": 0.27,
                           "film": {"type": "hdrfilm", "width": 480, "height": 480, "rfilter": {"type": "box"},
                                    "pixel_format": "luminance"}})
    rng = np.random.default_rng(1)
    u, v = ((240 + rng.random(200_000)) / 480 for _ in range(2))
    x, y = sensor.beam_target(mi.Point2f(mi.Float(u.astype(np.float32)), mi.Float(v.astype(np.float32))))
    sigma = 0.27 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    xs, ys = pixel_axes((480, 480), 20.0)
    for aim, centre, offset in ((np.array(x), xs[240], sensor.aim_offset_mm[0]),
                                (np.array(y), ys[240], sensor.aim_offset_mm[1])):
        assert aim.std() == pytest.approx(sigma, rel=0.01)  # 200k samples: 0.16 % standard error
        assert aim.mean() == pytest.approx(centre + offset, abs=4 * sigma / np.sqrt(aim.size))
