"""CLI round trip: EXR -> gradient -> height reproduces the library calls; recorded-image inputs;
user errors exit with status 2 and one line."""

import re

import numpy as np
import pytest

from elo_mitsuba.analysis import (
    flat_plate_images,
    integrate_gradient,
    pixel_coordinates,
    point_detector_images,
    surface_gradient,
)
from elo_mitsuba.cli import main
from elo_mitsuba.constants import DETECTOR_DIRECTIONS, DETECTOR_NAMES
from elo_mitsuba.exr import read_exr, write_exr

FIELD = (24.0, 20.0)
SHAPE = (40, 48)            # H, W: non-square to catch transposes
DH, DW = 250.0, 150.0


def detector_block(dh=DH, dw=DW, jitter=None):
    out = {}
    for n, (ex, ey) in DETECTOR_DIRECTIONS.items():
        c = [dw * ex, dw * ey, dh + (jitter or {}).get(n, 0.0)]
        out[n] = {"center": c, "normal": list(-np.array(c) / np.linalg.norm(c)), "radius": 25.0}
    return out


def surface():
    x, y = pixel_coordinates(SHAPE, FIELD)
    r2 = (x - 3) ** 2 + (y + 2) ** 2
    z = 1.5 * np.exp(-r2 / 20.0)
    gx = -2 * (x - 3) / 20.0 * z
    gy = -2 * (y + 2) / 20.0 * z
    gx = np.where((x < -8) & (y > 5), 4.0, gx)   # a steep patch: right detector masked there
    return gx, gy


def meta(**kw):
    m = {"field_mm": list(FIELD), "resolution": [SHAPE[1], SHAPE[0]], "units": "N_d/N_0",
         "detectors": detector_block(), "events": 1, "spp": 1, "material": "Ti-6Al-4V",
         "work_distance_mm": 400.0, "projection": "orthographic"}
    m.update(kw)
    return m


def channels(images):
    out = dict(images)
    out.update({f"{n}.e1": v for n, v in images.items()})
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    gx, gy = surface()
    kw = dict(model="lambert", detector_radius_mm=25.0)
    obj = point_detector_images(gx, gy, FIELD, DH, DW, **kw)
    flat = flat_plate_images(SHAPE, FIELD, DH, DW, **kw)
    write_exr(d / "obj.exr", channels(obj), meta())
    write_exr(d / "flat.exr", channels(flat), meta())
    return d, gx, gy


def test_round_trip_matches_library(scene, tmp_path):
    d, gx, gy = scene
    grad, height = tmp_path / "grad.exr", tmp_path / "h.exr"
    assert main(["gradient", "--method", "eq26", "--flat", str(d / "flat.exr"), str(d / "obj.exr"), "-o", str(grad),
                 "--preview", str(tmp_path / "g.png")]) == 0
    assert main(["reconstruct", str(grad), "-o", str(height), "--preview", str(tmp_path / "h.png")]) == 0
    ch, m = read_exr(grad)
    assert {"dzdx", "dzdy", "Mx", "My", "mask"} <= set(ch)
    assert m["d_h_mm"] == pytest.approx(DH) and m["d_w_mm"] == pytest.approx(DW)
    assert m["field_mm"] == list(FIELD) and m["resolution"] == [SHAPE[1], SHAPE[0]]
    # library on the same (float32) inputs
    obj, _ = read_exr(d / "obj.exr")
    flat, _ = read_exr(d / "flat.exr")
    res = surface_gradient({n: obj[n] for n in DETECTOR_NAMES}, {n: flat[n] for n in DETECTOR_NAMES}, FIELD, DH, DW)
    assert np.array_equal(ch["mask"] > 0.5, res.mask)
    assert np.allclose(ch["dzdx"], res.dzdx, atol=1e-6) and np.allclose(ch["dzdy"], res.dzdy, atol=1e-6)
    assert np.allclose(ch["Mx"], res.mx, atol=1e-6)
    assert res.mask.any() and np.all(ch["dzdx"][res.mask] == 0)
    # the masked patch is where the right detector cannot see; elsewhere the gradient is right
    assert np.array_equal(res.mask, gx == 4.0)
    assert np.max(np.abs(res.dzdx - gx)[~res.mask]) < 1e-5
    hc, hm = read_exr(height)
    h_lib, m_lib = integrate_gradient(ch["dzdx"], ch["dzdy"], FIELD, mask=ch["mask"] > 0.5, min_component_size=16)
    assert np.allclose(hc["height"], h_lib, atol=1e-6)
    assert np.array_equal(hc["mask"] > 0.5, m_lib)
    assert hm["method"] == "masked" and hm["units"] == "mm"
    for png in ("g.png", "h.png"):
        assert (tmp_path / png).read_bytes()[:4] == b"\x89PNG"


def test_recorded_single_files_and_formats(scene, tmp_path):
    import tifffile

    d, _, _ = scene
    obj, _ = read_exr(d / "obj.exr")
    flat, _ = read_exr(d / "flat.exr")
    args = []
    for n in DETECTOR_NAMES:
        np.save(tmp_path / f"{n}.npy", -1e5 * obj[n])          # volts, negative: units cancel
        tifffile.imwrite(tmp_path / f"flat_{n}.tif", (-1e5 * flat[n]).astype(np.float32))
        args += [f"--{n}", str(tmp_path / f"{n}.npy"), f"--flat-{n}", str(tmp_path / f"flat_{n}.tif")]
    out = tmp_path / "grad.exr"
    assert main(["gradient", "--method", "eq26", *args, "--field", "24,20", "--dh", str(DH), "--dw", str(DW), "-o", str(out)]) == 0
    ref = tmp_path / "ref.exr"
    assert main(["gradient", "--method", "eq26", "--flat", str(d / "flat.exr"), str(d / "obj.exr"), "-o", str(ref)]) == 0
    a, _ = read_exr(out)
    b, _ = read_exr(ref)
    assert np.allclose(a["dzdx"], b["dzdx"], atol=1e-5) and np.array_equal(a["mask"], b["mask"])
    for suffix in ("npy", "tif"):
        h = tmp_path / f"h.{suffix}"
        assert main(["reconstruct", str(out), "-o", str(h), "--method", "dct"]) == 0
        arr = np.load(h) if suffix == "npy" else tifffile.imread(h)
        # no height (NaN, not 0) exactly where the gradient is masked (heightmap.write_height)
        assert arr.shape == SHAPE and np.array_equal(np.isnan(arr), a["mask"] > 0.5) and (a["mask"] > 0.5).any()


def test_event_channels(scene, tmp_path):
    d, _, _ = scene
    assert main(["gradient", "--method", "eq26", "--flat", str(d / "flat.exr"), str(d / "obj.exr"), "--event", "1",
                 "-o", str(tmp_path / "g1.exr")]) == 0


def test_user_errors_exit_2(scene, tmp_path, capsys):
    d, _, _ = scene
    out = tmp_path / "g.exr"
    base = ["gradient", "--method", "eq26", "--flat", str(d / "flat.exr"), str(d / "obj.exr"), "-o", str(out)]
    assert main(base) == 0
    assert main(base) == 2 and "exists" in capsys.readouterr().err           # no silent overwrite
    assert main(base + ["--overwrite"]) == 0
    # detectors that disagree in height
    obj, _ = read_exr(d / "obj.exr")
    write_exr(tmp_path / "bad.exr", obj, meta(detectors=detector_block(jitter={"back": 5.0})))
    assert main(["gradient", "--method", "eq26", "--flat", str(d / "flat.exr"), str(tmp_path / "bad.exr"),
                 "-o", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err
    assert "differ in height" in err and err.count("\n") == 1
    # ... unless overridden
    assert main(["gradient", "--method", "eq26", "--flat", str(d / "flat.exr"), str(tmp_path / "bad.exr"), "--dh", str(DH),
                 "-o", str(tmp_path / "x.exr")]) == 0
    capsys.readouterr()
    # a flat recorded with another field
    flat, _ = read_exr(d / "flat.exr")
    write_exr(tmp_path / "flat80.exr", flat, meta(field_mm=[80.0, 80.0]))
    assert main(["gradient", "--method", "eq26", "--flat", str(tmp_path / "flat80.exr"), str(d / "obj.exr"),
                 "-o", str(tmp_path / "w.exr")]) == 2
    assert "field_mm" in capsys.readouterr().err
    # header resolution that does not match the pixels
    write_exr(tmp_path / "res.exr", obj, meta(resolution=[SHAPE[0], SHAPE[1]]))
    assert main(["gradient", "--method", "eq26", "--no-flat", str(tmp_path / "res.exr"), "-o", str(tmp_path / "v.exr")]) == 2
    assert "resolution" in capsys.readouterr().err
    # single files without geometry
    np.save(tmp_path / "r.npy", obj["right"])
    args = sum(([f"--{n}", str(tmp_path / "r.npy")] for n in DETECTOR_NAMES), [])
    assert main(["gradient", "--method", "eq26", *args, "--no-flat", "-o", str(tmp_path / "y.exr")]) == 2
    assert "--field" in capsys.readouterr().err
    # missing flat
    assert main(["gradient", "--method", "eq26", str(d / "obj.exr"), "-o", str(tmp_path / "z.exr")]) == 2
    assert "flat" in capsys.readouterr().err
    assert main(["reconstruct", str(d / "obj.exr"), "-o", str(tmp_path / "h.npy")]) == 2
    assert "dzdx" in capsys.readouterr().err
    assert main(["reconstruct", str(out), "-o", str(tmp_path / "h.png")]) == 2


def test_reflectance_map_cli(tmp_path, capsys):
    out = tmp_path / "m.png"
    assert main(["reflectance-map", "--dh", "272", "--dw", "127", "-o", str(out), "--samples", "61",
                 "--data", str(tmp_path / "m.npz")]) == 0
    data = np.load(tmp_path / "m.npz")
    assert np.array_equal(data["masked"], data["p"] <= -272 / 127)
    assert out.read_bytes()[:4] == b"\x89PNG"
    assert main(["reflectance-map", "--zeta", "50", "--dh", "1", "-o", str(tmp_path / "n.png")]) == 2
    assert main(["reflectance-map", "--zeta", "60", "--beam", "pivot", "--at", "30,-20", "--samples", "41",
                 "-o", str(tmp_path / "n.png")]) == 0


def test_help_texts_teach(capsys):
    for cmd, words in (("gradient", ["Eq. 26", "d_w + x M_x + y M_y", "examples:"]),
                       ("reconstruct", ["DCT", "Frankot-Chellappa", "examples:"]),
                       ("reflectance-map", ["Eq. 13", "p d_x + q d_y + 1 <= 0", "examples:"])):
        with pytest.raises(SystemExit) as exc:
            main([cmd, "--help"])
        assert exc.value.code == 0
        text = capsys.readouterr().out
        assert all(w in text for w in words), cmd


def test_several_flats_are_averaged(scene, tmp_path, capsys):
    """Repeated --flat: the mean of the recordings divides the object, so the flat's share of the
    noise falls as 1/N: with 1 % on the object and on each flat, the Eq. 26 gradient's noise
    with 4 flats is sqrt((1 + 1/4) / 2) = 0.79 of that with one."""
    from elo_mitsuba.analysis import mean_flat

    d, _, _ = scene
    obj, m = read_exr(d / "obj.exr")
    flat, _ = read_exr(d / "flat.exr")
    obj, flat = ({n: c[n] for n in DETECTOR_NAMES} for c in (obj, flat))
    rng = np.random.default_rng(5)
    noisy = {n: v * (1 + 0.01 * rng.standard_normal(v.shape)) for n, v in obj.items()}
    write_exr(tmp_path / "obj.exr", noisy, m)
    flats = []
    for i in range(4):
        f = {n: v * (1 + 0.01 * rng.standard_normal(v.shape)) for n, v in flat.items()}
        write_exr(tmp_path / f"flat{i}.exr", f, m)
        flats.append(f)
    clean = surface_gradient(obj, flat, FIELD, DH, DW)
    errors = {}
    for n_flats in (1, 4):
        out = tmp_path / f"g{n_flats}.exr"
        args = sum((["--flat", str(tmp_path / f"flat{i}.exr")] for i in range(n_flats)), [])
        assert main(["gradient", "--method", "eq26", *args, str(tmp_path / "obj.exr"), "-o", str(out)]) == 0
        said = capsys.readouterr().out
        # the flat's share of the noise variance: 1/2 with one flat, 1/5 with the mean of four
        got = re.search(r"object ([\d.]+) %, flat plate ([\d.]+) % \((.*)\): the flat holds (\d+) %", said)
        assert got, said
        assert float(got[1]) == pytest.approx(1.0, rel=0.06)
        assert float(got[2]) == pytest.approx(1.0 / np.sqrt(n_flats), rel=0.06)
        assert got[3] == ("1 recording" if n_flats == 1 else "the mean of 4 recordings")
        assert int(got[4]) == pytest.approx(100 / (1 + n_flats), abs=4)
        ch, hdr = read_exr(out)
        # what was applied is the mean of the recordings, and the header names every one
        lib = surface_gradient(noisy, mean_flat(flats[:n_flats]), FIELD, DH, DW)
        np.testing.assert_allclose(ch["dzdx"], lib.dzdx, rtol=1e-5, atol=1e-6)
        src = hdr["sources"]["flat"]
        assert (src if n_flats > 1 else [src]) == [str(tmp_path / f"flat{i}.exr") for i in range(n_flats)]
        good = ~(lib.mask | clean.mask)
        errors[n_flats] = np.sqrt(np.mean(np.r_[(lib.dzdx - clean.dzdx)[good], (lib.dzdy - clean.dzdy)[good]] ** 2))
    capsys.readouterr()
    assert errors[4] / errors[1] == pytest.approx(np.sqrt(1.25 / 2), rel=0.04)  # seeds 5-8: 0.780-0.801
    # recordings that do not describe the object's scan, or each other, are refused in one line
    write_exr(tmp_path / "flat80.exr", flat, {**m, "field_mm": [80.0, 80.0]})
    small = {n: v[:-2] for n, v in flat.items()}
    np.save(tmp_path / "r.npy", flat["right"])
    for extra, expected in ((["--flat", str(tmp_path / "flat80.exr")], "flat80.exr: flat-plate field_mm"),
                            (["--flat-right", str(tmp_path / "r.npy")], "missing left, back, front")):
        assert main(["gradient", "--method", "eq26", "--flat", str(tmp_path / "flat0.exr"), *extra,
                     str(tmp_path / "obj.exr"), "-o", str(tmp_path / "bad.exr")]) == 2
        err = capsys.readouterr().err
        assert expected in err and err.count("\n") == 1, err
    with pytest.raises(Exception, match=r"recordings differ in shape \(1: 48x40, 2: 48x38 px\)"):
        mean_flat([flat, small])


@pytest.mark.parametrize("dtype", ["complex64", "complex128", "bool", "timedelta64[s]", "datetime64[s]"])
def test_gradient_refuses_images_that_are_not_real_numbers(tmp_path, capsys, dtype):
    """Found by the bad-input sweep: a complex .npy was taken with a numpy ComplexWarning on stderr
    and its imaginary part dropped."""
    args = []
    for n in DETECTOR_NAMES:
        np.save(tmp_path / f"{n}.npy", np.ones((8, 8)))
        args += [f"--{n}", str(tmp_path / f"{n}.npy")]
    odd = np.ones((8, 8)).astype(dtype) if dtype.startswith(("complex", "bool")) else np.zeros((8, 8), dtype)
    np.save(tmp_path / "odd.npy", odd)
    args[1] = str(tmp_path / "odd.npy")
    out = tmp_path / "g.exr"
    assert main(["gradient", *args, "--no-flat", "--field", "80", "--dh", "272", "--dw", "127", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (f"elo-mitsuba: error: {tmp_path / 'odd.npy'}: expected one 2-D numeric image of real values "
                   f"(integer or floating point), got shape (8, 8) ({odd.dtype})\n")
    assert not out.exists()


def _quadric(shape, field):
    x, y = pixel_coordinates(shape, field)
    z = 0.01 * x**2 - 0.05 * y**2 + 0.02 * x * y + 0.1 * x
    return z - z.mean(), 0.02 * x + 0.02 * y + 0.1, -0.1 * y + 0.02 * x


def test_reconstruct_non_square_pixels(tmp_path, capsys, monkeypatch):
    """Found by the bad-input sweep: '--field 80,40' on a square image was refused only after the
    solve, as 'only square pixels can be meshed'. The solvers take dx and dy apart, so a .npy
    (no pixel size) is written; the formats that record one square pixel refuse before any work."""
    shape, field = (30, 50), (80.0, 20.0)                    # pixels 1.6 x 0.667 mm
    z, gx, gy = _quadric(shape, field)
    grad = tmp_path / "g.exr"
    write_exr(grad, {"dzdx": gx, "dzdy": gy})                # another tool's: no header
    for method in ("dct", "masked"):
        out = tmp_path / f"h_{method}.npy"
        assert main(["reconstruct", str(grad), "-o", str(out), "--field", "80,20", "--method", method]) == 0
        assert np.max(np.abs(np.load(out) - z)) < 1e-4   # exact for a quadric up to float32 input
    capsys.readouterr()
    from elo_mitsuba.analysis import chain

    monkeypatch.setattr(chain, "heights", None)              # a refusal comes before the solve
    for suffix in ("exr", "tif", "gsf"):
        out = tmp_path / f"h.{suffix}"
        assert main(["reconstruct", str(grad), "-o", str(out), "--field", "80,20", "--preview",
                     str(tmp_path / "h.png")]) == 2
        err = capsys.readouterr().err
        assert err == (f"elo-mitsuba: error: --field 80,20 over 50x30 px gives pixels of 1.6 x 0.666667 mm; a .{suffix} "
                       "height map records one square pixel size: write a .npy (no pixel size), or give a field "
                       "with square pixels (e.g. --field 80,48)\n")
        assert not out.exists() and not (tmp_path / "h.png").exists()
    write_exr(tmp_path / "gh.exr", {"dzdx": gx, "dzdy": gy}, {"field_mm": [80.0, 20.0]})
    assert main(["reconstruct", str(tmp_path / "gh.exr"), "-o", str(tmp_path / "h.tif")]) == 2
    assert f"{tmp_path / 'gh.exr'}: header field_mm 80 x 20 mm over 50x30 px" in capsys.readouterr().err
