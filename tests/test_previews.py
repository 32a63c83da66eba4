"""Previews that do not mislead (issue 24): gradient panels symmetric about 0 with a noise floor
that a flat panel names, a diverging map with distinguishable ends, a mask grey outside every
colour map, height previews that say method and unit, sweep plots that name a tiny span."""

from __future__ import annotations

import numpy as np
import pytest

from elo_mitsuba.analysis import plots


def _rgb(name, n=256):
    import cmasher  # noqa: F401
    import matplotlib as mpl

    return mpl.colormaps[name](np.linspace(0, 1, n))[:, :3]


def test_gradient_scale_is_symmetric_per_panel_and_names_noise():
    rng = np.random.default_rng(0)
    ramp = np.linspace(-0.8, 1.0, 400).reshape(20, 20)
    lo, hi, note = plots.colour_limits(ramp, symmetric=True, min_scale=plots.GRADIENT_MIN_SCALE)
    assert lo == -hi and hi == pytest.approx(np.percentile(ramp, 99.5)) and note == ""
    noise = 5e-4 * rng.standard_normal((20, 20))  # a flat plate's dZ/dy
    lo, hi, note = plots.colour_limits(noise, symmetric=True, min_scale=plots.GRADIENT_MIN_SCALE)
    assert (lo, hi) == (-plots.GRADIENT_MIN_SCALE, plots.GRADIENT_MIN_SCALE) and "noise level" in note


def test_gradient_preview_titles_and_limits(tmp_path):
    rng = np.random.default_rng(1)
    gx = np.sign(np.sin(np.arange(32) / 2))[None, :] * np.ones((32, 1))  # corrugated: +-1
    gy = 5e-4 * rng.standard_normal((32, 32))
    mask = np.zeros((32, 32), bool)
    mask[:4] = True
    fig_axes = {}
    original = plots.save_figure

    def keep(fig, path, overwrite):
        fig_axes["axes"] = [a for a in fig.axes if a.images]
        return original(fig, path, overwrite)

    plots.save_figure = keep
    try:
        plots.preview_gradient(gx, gy, 16.0, tmp_path / "g.png", mask=mask)
    finally:
        plots.save_figure = original
    ax_x, ax_y = fig_axes["axes"]
    assert ax_x.images[0].get_clim() == (-1.0, 1.0)
    assert ax_y.images[0].get_clim() == (-plots.GRADIENT_MIN_SCALE, plots.GRADIENT_MIN_SCALE)
    assert "noise level" in ax_y.get_title() and "noise level" not in ax_x.get_title()
    assert ax_x.get_legend().get_texts()[0].get_text().startswith("masked")
    assert ax_x.images[0].get_cmap().name == plots.CMAP_DIVERGING


def test_diverging_ends_differ_and_mask_grey_is_in_no_map():
    rgb = _rgb(plots.CMAP_DIVERGING)
    assert np.linalg.norm(rgb[0] - rgb[-1]) > 0.4  # the two ends (fusion_r's: 0.13)
    import matplotlib as mpl

    grey = np.asarray(mpl.colors.to_rgb(plots.MASK_COLOUR))
    for name in (plots.CMAP_DIVERGING, plots.CMAP_HEIGHT, plots.CMAP_INTENSITY):
        assert np.min(np.linalg.norm(_rgb(name) - grey, axis=1)) > 0.3, name


def test_height_preview_title_says_method_and_unit(tmp_path, monkeypatch):
    titles = []
    original = plots.save_figure
    monkeypatch.setattr(plots, "save_figure", lambda fig, path, ow: (titles.extend(a.get_title() for a in fig.axes),
                                                                original(fig, path, ow))[1])
    h = np.outer(np.linspace(-1, 1, 16), np.ones(16)) * 0.05
    plots.preview_height(h, 16.0, tmp_path / "h.png", title="Height map by normal integration ('dct' solver)")
    assert "'dct' solver" in titles[0] and "Z in mm, relative" in titles[0] and "range 0.1 mm" in titles[0]


def test_sweep_plot_names_a_tiny_span(tmp_path):
    import xarray as xr

    from elo_mitsuba.sweeps.plot import plot_metric, span_note

    assert span_note([0.3001, 0.3008]).startswith("span only 0.23 %")
    assert span_note([0.2, 0.3]) == "" and span_note([0.0, 0.0]) == ""
    z = 0.3001 + 0.0007 * np.random.default_rng(0).random((3, 4))
    ds = xr.Dataset({"signal_mean": (("a", "b"), z), "status": (("a", "b"), np.ones((3, 4), np.int8))},
                    coords={"a": [10.0, 20.0, 30.0], "b": [1.0, 2.0, 3.0, 4.0]})
    ds.to_zarr(tmp_path / "s.zarr", zarr_format=2)
    titles = []
    original = plots.save_figure
    try:
        plots.save_figure = lambda fig, path, ow: (titles.extend(a.get_title() for a in fig.axes), original(fig, path, ow))[1]
        plot_metric(tmp_path / "s.zarr", "signal_mean", tmp_path / "p.png")
    finally:
        plots.save_figure = original
    assert any("span only 0.2" in t for t in titles)
