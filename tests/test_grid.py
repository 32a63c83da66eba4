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
    xs, ys = pixel_axes((h, w), (field, field * h / w))
    np.testing.assert_allclose(np.array(x).reshape(h, w), np.broadcast_to(xs, (h, w)), atol=3e-3)
    np.testing.assert_allclose(np.array(y).reshape(h, w), np.broadcast_to(ys[:, None], (h, w)), atol=2e-3)
