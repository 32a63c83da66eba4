"""Reflectance maps, normal histograms, masking lines, image statistics and PNG previews."""

import numpy as np
import pytest

from elo_mitsuba.analysis import (
    detector_pq,
    detector_vectors,
    image_statistics,
    layout_geometry,
    masked_normal_fraction,
    masking_lines,
    normal_histogram,
    pixel_coordinates,
    point_detector_images,
    reflectance_map,
)
from elo_mitsuba.analysis import plots
from elo_mitsuba.constants import DETECTOR_NAMES, TABLE1_LAYOUTS
from elo_mitsuba.errors import EloInputError


@pytest.mark.parametrize("zeta", sorted(TABLE1_LAYOUTS))
@pytest.mark.parametrize("at", [(0.0, 0.0), (30.0, -25.0)])
@pytest.mark.parametrize("lobe", [True, False])
def test_reflectance_map_masking_equals_geometric_test(zeta, at, lobe):
    """The hatched region equals the independent test angle(n_S, d) >= 90 deg, and g_BSE = 0 there."""
    dh, dw = TABLE1_LAYOUTS[zeta]
    d = detector_vectors(at[0], at[1], dh, dw, ("right",))["right"]
    p, q, g, masked = reflectance_map((d[0], d[1]), lobe=lobe, n=121)
    n = np.stack([p, q, np.ones_like(p)], axis=-1)
    cos_alpha = n @ d / (np.linalg.norm(n, axis=-1) * np.linalg.norm(d))
    geometric = cos_alpha <= 0
    assert np.array_equal(masked, geometric)
    assert np.all(g[masked] == 0) and np.all(g[~masked] > 0)
    # Sec. 4.3: at the field centre the border is the vertical line p = -d_h/d_w
    if at == (0.0, 0.0):
        assert np.array_equal(masked, p <= -dh / dw)


def test_reflectance_map_orientation_and_peak():
    d = detector_pq(272.0, 127.0)
    assert d == pytest.approx((127 / 272, 0.0))
    p, q, g, _ = reflectance_map(d, lobe=False, n=(241, 121))
    assert p.shape == (121, 241) and q[0, 0] == 3.0 and q[-1, 0] == -3.0 and p[0, 0] == -3.0
    i = np.unravel_index(np.argmax(g), g.shape)
    assert p[i] == pytest.approx(d[0], abs=0.03) and q[i] == pytest.approx(0, abs=0.06)  # n_S parallel d


def test_masking_lines_table1():
    lines = masking_lines()
    assert set(lines) == set(TABLE1_LAYOUTS)
    for zeta, (dh, dw) in TABLE1_LAYOUTS.items():
        assert lines[zeta]["right"] == pytest.approx((dw / dh, 0.0))
        assert lines[zeta]["front"] == pytest.approx((0.0, -dw / dh))
    assert layout_geometry(50) == TABLE1_LAYOUTS[50]
    with pytest.raises(EloInputError):
        layout_geometry(30)


def test_normal_histogram_of_a_plane():
    n = 64
    x, y = pixel_coordinates((n, n), 20.0)
    z = 0.5 * x - 0.25 * y     # n_S = [-0.5, 0.25, 1]
    hist, pe, qe = normal_histogram(z, 20.0, bins=80, p_range=(-2, 2), q_range=(-2, 2))
    assert hist.sum() == n * n
    r, c = np.unravel_index(np.argmax(hist), hist.shape)
    assert pe[c] <= -0.5 < pe[c + 1]
    qe_desc = qe[::-1]          # row 0 = largest q
    assert qe_desc[r + 1] <= 0.25 < qe_desc[r]


def test_masked_fraction_and_image_statistics():
    n = 40
    x, _ = pixel_coordinates((n, n), 40.0)
    gx = np.where(x < 0, 3.0, 0.0)    # left half: n_Sx = -3 masks the right detector for every layout
    gy = np.zeros_like(gx)
    frac = masked_normal_fraction(gx, gy, 40.0, 272.0, 127.0)
    assert frac["right"] == pytest.approx(0.5) and frac["left"] == 0 and frac["any"] == pytest.approx(0.5)
    img = point_detector_images(gx, gy, 40.0, 272.0, 127.0, model="g_bse", detector_radius_mm=25.0)["right"]
    s = image_statistics(img)
    assert s["masked_fraction"] == pytest.approx(0.5)
    assert np.array_equal(s["masked"], x < 0)
    assert s["mean"] == pytest.approx(img.mean()) and s["std"] == pytest.approx(img.std())
    assert s["hist"].sum() == n * n
    # more inclined detector (Table 1, zeta 75) sees less on average (Fig. 15)
    img75 = point_detector_images(0 * gx, gy, 40.0, *TABLE1_LAYOUTS[75], detector_radius_mm=25.0)["right"]
    img25 = point_detector_images(0 * gx, gy, 40.0, *TABLE1_LAYOUTS[25], detector_radius_mm=25.0)["right"]
    assert image_statistics(img75)["mean"] < image_statistics(img25)["mean"]


def test_previews_written_and_not_overwritten(tmp_path):
    n = 32
    x, y = pixel_coordinates((n, n), 16.0)
    mask = (x**2 + y**2) < 4
    plots.preview_gradient(x / 8, y / 8, 16.0, tmp_path / "g.png", mask=mask)
    plots.preview_height(x * y, 16.0, tmp_path / "h.png")
    hist, pe, qe = normal_histogram(np.sin(x) * np.cos(y), 16.0, bins=40)
    plots.plot_normal_histogram(hist, pe, qe, tmp_path / "n.png", lines=masking_lines())
    stats = {f"zeta {z}": image_statistics(point_detector_images(
        np.sin(x), np.cos(y), 16.0, *TABLE1_LAYOUTS[z], detector_radius_mm=25.0)["right"], bins=30)
        for z in (25, 75)}
    plots.plot_image_histograms(stats, tmp_path / "s.png")
    for name in ("g", "h", "n", "s"):
        data = (tmp_path / f"{name}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    with pytest.raises(EloInputError, match="exists"):
        plots.preview_height(x, 16.0, tmp_path / "h.png")
    assert set(DETECTOR_NAMES) == {"right", "left", "back", "front"}
