"""Sweep dimension names that ``ds.sel(name=value)`` accepts (issue 24): a swept spec key is
stored under :func:`elo_mitsuba.sweeps.dimension_name` (``right.radius`` -> ``right_radius``), a
``[zip.NAME]`` group as ``NAME``; ``sweep-plot --select`` and ``--x`` take either spelling and
name the dimension as the store does; a store written with the earlier dotted names resumes and
plots; names that could not be such keywords are refused when the spec is parsed.

Stores here are 4 points at 8 x 8 pixels, rendered in process (``--workers 0``)."""

from __future__ import annotations

import json
import keyword

import warnings

import numpy as np
import pytest

from elo_mitsuba.cli import main

xr = pytest.importorskip("xarray")
pytest.importorskip("zarr")

SPEC = """\
scene = "flat_plate"
[vary]
right.radius = [20, 30]
dw = [127]
[zip.geometry]
dh = [272, 250]
left.center = [[-127, 0, 272], [-150, 0, 250]]
detectors.normal = [[0, 0, -1], [0.1, 0, -1]]
[render]
resolution = 8
spp = 1
[keep]
channels = ["right"]
metrics = ["signal_mean"]
"""


def _cli(*args) -> int:
    return main([str(a) for a in args])


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("elo-mitsuba: error: "), err
    return err


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """(spec path, store path) of SPEC: detector moves, a scene parameter, a zipped group."""
    tmp = tmp_path_factory.mktemp("names")
    spec = tmp / "n.toml"
    spec.write_text(SPEC)
    out = tmp / "n.zarr"
    assert _cli("sweep", spec, "-o", out, "--workers", "0", "--no-progress") == 0
    return spec, out


@pytest.mark.parametrize("key, name", [("right.radius", "right_radius"), ("detectors.radius", "detectors_radius"),
                                       ("right.center", "right_center"), ("dh", "dh"), ("beam-fwhm", "beam_fwhm")])
def test_dimension_name(key, name):
    from elo_mitsuba.sweeps import dimension_name

    assert dimension_name(key) == name


def test_every_name_of_the_store_is_a_keyword_argument(store):
    _, out = store
    ds = xr.open_zarr(out)
    names = set(ds.dims) | set(ds.coords)
    assert {"right_radius", "dw", "geometry", "dh", "left_center", "left_center_xyz", "detectors_normal",
            "detectors_normal_xyz"} <= names
    for name in names:
        assert name.isidentifier() and not keyword.iskeyword(name), name
    assert ds["signal_mean"].dims == ("right_radius", "dw", "geometry", "detector")
    # every swept dimension, selected by keyword with each of its values
    for dim in ("right_radius", "dw", "geometry"):
        for value in ds[dim].values:
            assert ds.sel(**{dim: value})["status"].size == ds["status"].size // ds.sizes[dim]
    # plain keyword syntax, as a user writes it
    point = ds.sel(right_radius=20.0, geometry=1, dw=127)
    assert int(point["status"]) == 1
    assert float(point["dh"]) == 250 and point["left_center_xyz"].values.tolist() == [-150, 0, 250]
    np.testing.assert_array_equal(point["image_right"].values, ds["image_right"].values[0, 0, 1])
    assert ds.sel(right_radius=30.0)["signal_mean"].dims == ("dw", "geometry", "detector")


def test_the_store_keeps_the_spec_as_written(store):
    spec, out = store
    ds = xr.open_zarr(out)
    assert ds["right_radius"].attrs["long_name"] == "right.radius" and ds["right_radius"].attrs["units"] == "mm"
    assert ds["left_center"].attrs["long_name"] == "left.center"
    assert ds["geometry"].attrs["description"] == "zipped group: dh, left_center, detectors_normal"
    assert ds.attrs["spec_toml"] == spec.read_text()
    axes = json.loads(ds.attrs["spec"])["axes"]
    assert [a[0] for a in axes] == ["right.radius", "dw", "geometry"]


def test_sweep_plot_select_takes_both_spellings(store, capsys):
    _, out = store
    png = out.parent / "p.png"
    for select in ("right.radius=30", "right_radius=30"):
        assert _cli("sweep-plot", out, "signal_mean", "-o", png, "--select", select, "--overwrite") == 0
        assert png.stat().st_size > 5000
    assert _cli("sweep-plot", out, "signal_mean", "-o", png, "--x", "right.radius", "--detector", "right",
                "--overwrite") == 0
    capsys.readouterr()
    for args, expected in (
            (("--select", "right.radius=25"), "--select right_radius=25: not a value of the sweep; right_radius takes 20, 30"),
            (("--select", "left.radius=25"), "left_radius is not swept in"),
            (("--select", "right.radius=20", "--select", "right_radius=30"),
             "--select names right_radius twice (right.radius, right_radius)"),
            (("--x", "left.center"), "--x left.center: left_center is not among the plotted dimensions")):
        assert _cli("sweep-plot", out, "signal_mean", "-o", out.parent / "q.png", *args) == 2
        err = _one_line_error(capsys)
        assert expected in err, err
        assert "right.radius is" not in err and "right.radius takes" not in err


def test_sweep_plot_detector_on_a_per_point_metric_is_refused(store, capsys):
    """--detector on a metric with one value per point was ignored (a setting not applied)."""
    _, out = store
    capsys.readouterr()
    assert _cli("sweep-plot", out, "render_seconds", "-o", out.parent / "q.png", "--detector", "right") == 2
    assert "--detector right: render_seconds is one value per sweep point, not one per detector" in _one_line_error(capsys)
    assert not (out.parent / "q.png").exists()


def test_sweep_plot_reads_a_store_without_consolidated_metadata_quietly(store, tmp_path, capfd):
    """A store whose consolidated metadata is gone (copied by a tool that drops it) plots without
    xarray's and zarr's warnings before the figure."""
    import shutil

    _, out = store
    copy = tmp_path / "c.zarr"
    shutil.copytree(out, copy)
    (copy / ".zmetadata").unlink()
    (copy / ".claims").mkdir(exist_ok=True)
    capfd.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert _cli("sweep-plot", copy, "signal_mean", "-o", tmp_path / "c.png", "--select", "right.radius=30") == 0
    assert not [str(w.message) for w in caught], [str(w.message) for w in caught]
    assert capfd.readouterr().err == ""


def test_a_store_with_dotted_names_resumes_and_plots(store, tmp_path, capsys):
    """A store written before the names were identifiers: the same spec resumes it (its names
    stay), and sweep-plot reads it with either spelling."""
    import zarr

    spec, out = store
    old = tmp_path / "old.zarr"
    dotted = {"right_radius": "right.radius", "left_center": "left.center", "left_center_xyz": "left.center_xyz",
              "detectors_normal": "detectors.normal", "detectors_normal_xyz": "detectors.normal_xyz"}
    ds = xr.open_zarr(out).rename(dotted)
    ds.to_zarr(old, mode="w-", zarr_format=2, consolidated=True)
    stored = xr.open_zarr(old)
    assert "right.radius" in stored.dims and stored.attrs["elo_sweep_digest"] == xr.open_zarr(out).attrs["elo_sweep_digest"]
    mean = stored["signal_mean"].values.copy()
    g = zarr.open_group(str(old), mode="r+")
    g["status"][1, 0, 0] = 0
    g["signal_mean"][1, 0, 0] = np.nan
    capsys.readouterr()
    assert _cli("sweep", spec, "-o", old, "--workers", "0", "--no-progress") == 0
    assert "3 already stored (resumed)" in capsys.readouterr().out
    again = xr.open_zarr(old)
    assert "right.radius" in again.dims and (again["status"].values == 1).all()
    np.testing.assert_array_equal(again["signal_mean"].values, mean)
    png = tmp_path / "old.png"
    for select in ("right.radius=30", "right_radius=30"):
        assert _cli("sweep-plot", old, "signal_mean", "-o", png, "--select", select, "--overwrite") == 0
    capsys.readouterr()
    assert _cli("sweep-plot", old, "signal_mean", "-o", png, "--select", "right.radius=25", "--overwrite") == 2
    assert "right_radius takes 20, 30" in _one_line_error(capsys)


BAD_NAMES = {
    "not_identifier": ('[zip."2nd"]\ndh = [200, 272]\n', "zip.2nd: its store name '2nd' is not a Python identifier"),
    "keyword": ("[zip.lambda]\ndh = [200, 272]\n", "its store name 'lambda' is not a Python identifier"),
    "sel_keyword": ("[zip.method]\ndh = [200, 272]\n", "its store name 'method' is a keyword of Dataset.sel"),
    "store_dimension": ("[zip.detector]\ndh = [200, 272]\n", "its store name 'detector' is a name the store uses"),
    "store_variable": ("[zip.status]\ndh = [200, 272]\n", "its store name 'status' is a name the store uses"),
    "two_keys_one_name": ("[vary]\nright.radius = [20, 30]\n[zip.right_radius]\ndh = [200, 272]\n",
                          "vary.right.radius and zip.right_radius would both be the store's 'right_radius'"),
    "member_and_group": ("[zip.g]\ndh = [200, 272]\nright.center = [[127, 0, 272], [127, 0, 250]]\n"
                         "[zip.right_center]\ndw = [100, 127]\n",
                         "zip.g.right.center and zip.right_center would both be the store's 'right_center'"),
}


@pytest.mark.parametrize("case", sorted(BAD_NAMES))
def test_names_that_sel_cannot_take_are_refused(case):
    from conftest import one_line_error
    from elo_mitsuba.sweeps import load_spec

    body, expected = BAD_NAMES[case]
    message = one_line_error(lambda: load_spec('scene = "flat_plate"\n' + body))
    assert expected in message, message
