"""Bad input to the analysis commands (gradient, calibrate, reconstruct, invert) found by the
bad-input sweep: each is refused with exit status 2 and one line naming the file or option, the
value and what is allowed, before any work, with nothing written; or, where the input is good
(an upper-case .NPY), it is written as asked.

The inputs are 16^2 renders (flat plate, corrugated sheet) and files derived from them."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from conftest import one_line_error, raw_exr
from elo_mitsuba.cli import main
from elo_mitsuba.exr import read_exr, write_exr


def _main(argv):
    """``main`` with argparse's own exits (usage errors) as exit statuses."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


def _second_event(path, channels, meta, **changes):
    """A 'render with --events 2' of the flat plate (totals and 1st-event channels), its header changed."""
    later = {**channels, **{f"{n}.e1": 0.95 * v for n, v in channels.items()}}
    write_exr(path, later, {**meta, "events": 2, **changes})


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad_analysis")
    assert main(["render", "flat_plate", "-o", str(d / "flat.exr"), "--resolution", "16", "--quiet"]) == 0
    assert main(["render", "corrugated_sheet", "-o", str(d / "corr.exr"), "--resolution", "16", "--quiet"]) == 0
    assert main(["gradient", "--method", "eq26", "--flat", str(d / "flat.exr"), str(d / "corr.exr"),
                 "-o", str(d / "grad.exr")]) == 0
    flat, fmeta = read_exr(d / "flat.exr")
    obj, ometa = read_exr(d / "corr.exr")
    grad, gmeta = read_exr(d / "grad.exr")
    write_exr(d / "huge.exr", {k: np.full_like(v, 3e38) for k, v in obj.items()}, ometa)
    write_exr(d / "uniform.exr", {k: np.full_like(v, float(v.mean())) for k, v in flat.items()}, fmeta)
    # gradients: every pixel masked; NaN at a trusted pixel; NaN at a masked one (another tool's unknown)
    write_exr(d / "allmask.exr", {**grad, "mask": np.ones_like(grad["mask"])}, gmeta)
    nan = {**grad, "dzdx": grad["dzdx"].copy(), "mask": np.zeros_like(grad["mask"])}
    nan["dzdx"][3, 3] = np.nan
    raw_exr(d / "nan_trusted.exr", nan, json.dumps(gmeta))
    nan["mask"][3, 3] = 1
    raw_exr(d / "nan_masked.exr", nan, json.dumps(gmeta))
    # second-event renders of another field, another detector height; heights of another field
    _second_event(d / "se_f40.exr", flat, fmeta, field_mm=[40.0, 40.0])
    dets = json.loads(json.dumps(fmeta["detectors"]))
    for det in dets.values():
        det["center"][2] = 150.0
    _second_event(d / "se_dh.exr", flat, fmeta, detectors=dets)
    _second_event(d / "se_ok.exr", flat, fmeta)
    write_exr(d / "h40.exr", {"height": np.zeros((16, 16))}, {"field_mm": [40.0, 40.0]})
    # starts of another size, with a NaN; an object whose header lacks one detector
    np.save(d / "h_small.npy", np.zeros((8, 8)))
    h_nan = np.zeros((16, 16))
    h_nan[2, 2] = np.nan
    np.save(d / "h_nan.npy", h_nan)
    no_front = json.loads(json.dumps(ometa))
    del no_front["detectors"]["front"]
    write_exr(d / "corr_nofront.exr", obj, no_front)
    write_exr(d / "corr_unob.exr", obj, {**ometa, "materials": {k: "Unob" for k in ometa["materials"]}})
    raw_exr(d / "rect_nometa.exr", {k: v[:, :8] for k, v in obj.items()}, json.dumps({}))
    # calibrations: a fifth detector, a misspelt key, another format
    good = {"format": "elo-mitsuba calibration 1",
            "detectors": {n: {k: g[k] for k in ("center", "normal", "radius")} for n, g in fmeta["detectors"].items()}}
    for name, edit in (("cal_extra", lambda c: c["detectors"].__setitem__("top", c["detectors"]["right"])),
                       ("cal_key", lambda c: c["detectors"]["right"].__setitem__("gian", 2.0)),
                       ("cal_format", lambda c: c.__setitem__("format", "something else")),
                       ("cal_topkey", lambda c: c.__setitem__("sorce", {})),
                       ("cal_ok", lambda c: None)):
        doc = json.loads(json.dumps(good))
        edit(doc)
        (d / f"{name}.json").write_text(json.dumps(doc))
    for n, img in obj.items():
        np.save(d / f"obj_{n}.npy", img.astype(float))
        np.save(d / f"flat_{n}.npy", flat[n].astype(float))
    (d / "trunc.tif").write_bytes(_tiff_bytes()[:200])
    (d / "adir").mkdir()
    (d / "d.npy").mkdir()
    return d


def _tiff_bytes() -> bytes:
    import io

    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, np.ones((32, 32), np.float32), resolution=(10.0, 10.0))
    return buf.getvalue()


G = ["gradient", "--flat", "{d}/flat.exr", "{d}/corr.exr", "-o", "{d}/new.exr"]
INV = ["invert", "--flat", "{d}/flat.exr", "{d}/corr.exr", "-o", "{d}/new.exr", "--quiet", "--no-local",
       "--uncertainty-probes", "0"]
CAL = ["calibrate", "{d}/flat.exr", "-o", "{d}/new.json"]
REC = ["reconstruct", "{d}/grad.exr", "-o", "{d}/new.npy"]
SINGLE = ["--field", "80", "--dh", "272", "--dw", "127", "-o", "{d}/new.exr"]


def four(prefix, left=None):
    """--right {d}/<prefix>right.npy ... (the left detector's file named ``left`` if given)."""
    return sum(([f"--{n}", f"{{d}}/{prefix}{left if (left and n == 'left') else n}.npy"]
                for n in ("right", "left", "back", "front")), [])


FLATS = sum(([f"--flat-{n}", f"{{d}}/flat_{n}.npy"] for n in ("right", "left", "back", "front")), [])

CASES = [
    # A1: a calibration with a fifth detector (KeyError after the images were read)
    ("A1 gradient --calibration extra detector", [*G, "--calibration", "{d}/cal_extra.json"],
     "detector 'top' is not one of the scan's detectors right, left, back, front"),
    ("A1 invert --calibration extra detector", [*INV, "--calibration", "{d}/cal_extra.json"], "detector 'top'"),
    # B4/C6: object or flat of absurd level against the other
    ("B4 object 3e38", ["gradient", "--flat", "{d}/flat.exr", "{d}/huge.exr", "-o", "{d}/new.exr"],
     "x its flat-plate image's"),
    ("B4 object 3e38 eq26", ["gradient", "--method", "eq26", "--flat", "{d}/flat.exr", "{d}/huge.exr", "-o",
                             "{d}/new.exr"], "allowed 1/1000 to 1000 x"),
    ("C6 flat 3e38", ["gradient", "--flat", "{d}/huge.exr", "{d}/corr.exr", "-o", "{d}/new.exr"],
     "x its flat-plate image's 3e+38"),
    ("C6 calibrate a uniform flat", ["calibrate", "{d}/uniform.exr", "-o", "{d}/new.json"], "holds one value"),
    ("C6 calibrate 3e38", ["calibrate", "{d}/huge.exr", "-o", "{d}/new.json"], "(3e+38) at every pixel"),
    # B5: a truncated TIFF (tifffile's log lines: test_a_truncated_tiff_is_one_line)
    ("B5 truncated tiff", ["gradient", *four("obj_")[:-2], "--front", "{d}/trunc.tif", *FLATS, *SINGLE],
     "trunc.tif: not a readable TIFF"),
    # C7: nothing to integrate; NaN where the mask says trusted
    ("C7 all masked", [*REC[:1], "{d}/allmask.exr", *REC[2:]], "all 256 pixels are masked"),
    ("C7 all masked dct", [*REC[:1], "{d}/allmask.exr", *REC[2:], "--method", "dct"], "all 256 pixels are masked"),
    ("C7 NaN at a trusted pixel", [*REC[:1], "{d}/nan_trusted.exr", *REC[2:]],
     "hold NaN in dzdx or dzdy where the mask says trusted (first at row 3, column 3)"),
    # D8: --second-event of another set-up; I22: of another size (its line)
    ("D8 gradient --second-event field", [*G, "--second-event", "{d}/se_f40.exr"],
     "se_f40.exr: the images' (", ),
    ("D8 gradient --second-event dh", [*G, "--second-event", "{d}/se_dh.exr"],
     "right detector at [127.0, 0.0, 150.0] mm is 122 mm from"),
    ("D8 calibrate --second-event", [*CAL, "--second-event", "{d}/se_f40.exr"], "contradicts the header's field_mm 40x40"),
    ("D8 invert --second-event", [*INV, "--second-event", "{d}/se_dh.exr"], "(allowed: within its radius"),
    # D9: --init of another scan field
    ("D9 invert --init heights of 40 mm", [*INV, "--init", "{d}/h40.exr"],
     "--init {d}/h40.exr: the images' field 80x80 mm contradicts the header's field_mm 40x40 mm"),
    # D10: one file for two detectors; one flat recording twice
    ("D10 one file, two detectors", ["gradient", *four("obj_", left="right"), *FLATS, *SINGLE],
     "obj_right.npy: given for both the right and the left detector (object images)"),
    ("D10 --flat twice", ["gradient", "--flat", "{d}/flat.exr", "--flat", "{d}/flat.exr", "{d}/corr.exr", "-o",
                          "{d}/new.exr"], "--flat {d}/flat.exr: the same file as --flat {d}/flat.exr"),
    ("D10 calibrate the same flat twice", ["calibrate", "{d}/flat.exr", "{d}/flat.exr", "-o", "{d}/new.json"],
     "the same file as"),
    # D11: --field against a rendered header
    ("D11 gradient --field", [*G, "--field", "40"], "corr.exr: --field 40x40 mm contradicts the header's field_mm 80x80"),
    ("D11 calibrate --field", [*CAL, "--field", "40"], "--field 40x40 mm contradicts"),
    ("D11 invert --field", [*INV, "--field", "40"], "--field 40x40 mm contradicts"),
    # F13: --min-component that would not be applied, or drops everything
    ("F13 --min-component with dct", [*REC, "--method", "dct", "--min-component", "5"],
     "--min-component applies to --method masked, robust or auto"),
    ("F13 --min-component beyond the image", [*REC, "--min-component", "100000"],
     "--min-component 100000: the largest trusted region of"),
    # G17: a calibration's unknown key, another format
    ("G17 calibration key", [*G, "--calibration", "{d}/cal_key.json"], "detector 'right': unknown key 'gian'"),
    ("G17 calibration top key", [*G, "--calibration", "{d}/cal_topkey.json"],
     "unknown key 'sorce'; a calibration file has: format, units, detectors, source"),
    ("G17 calibration format", [*G, "--calibration", "{d}/cal_format.json"], "format 'something else'"),
    # I20: a folder where a file belongs
    ("I20 gradient --flat folder", ["gradient", "--flat", "{d}/adir", "{d}/corr.exr", "-o", "{d}/new.exr"],
     "{d}/adir is a folder; give a file"),
    ("I20 calibrate folder", ["calibrate", "{d}/adir", "-o", "{d}/new.json"], "is a folder"),
    ("I20 reconstruct folder", ["reconstruct", "{d}/adir", "-o", "{d}/new.npy"], "is a folder"),
    ("I20 --calibration folder", [*G, "--calibration", "{d}/adir"], "calibration file {d}/adir is a folder"),
    ("I20 mesh folder .npy", ["mesh", "{d}/d.npy", "-o", "{d}/new.ply"], "height map {d}/d.npy is a folder"),
    ("I20 mesh folder", ["mesh", "{d}/adir", "-o", "{d}/new.ply"], "is a folder"),
    # I23: --event 0
    ("I23 gradient --event 0", [*G, "--event", "0"], "--event 0: must be >= 1"),
    # J25: --scales beyond the image, --tol beyond a fraction
    ("J25 invert --scales 100", [*INV, "--scales", "100"], "--scales 100: a 16x16 image allows at most 1"),
    ("J25 invert --tol 2", [*INV, "--tol", "2"], "--tol=2.0; must be a number in [0, 1)"),
    # I24: which rule failed, and what is missing
    ("I24 invert --init of another size", [*INV, "--init", "{d}/h_small.npy"],
     "--init {d}/h_small.npy: heights of 8x8 px, the images 16x16 px"),
    ("I24 invert --init with NaN", [*INV, "--init", "{d}/h_nan.npy"], "--init {d}/h_nan.npy: 1 height(s) NaN or Inf"),
    ("I24 gradient header lacks one detector", ["gradient", "--flat", "{d}/flat.exr", "{d}/corr_nofront.exr", "-o",
                                                "{d}/new.exr"], "header lacks the detector front;"),
    ("I24 gradient header of an unknown material", ["gradient", "--flat", "{d}/flat.exr", "{d}/corr_unob.exr", "-o",
                                                    "{d}/new.exr"], "{d}/corr_unob.exr: header unknown material 'Unob'"),
    ("I24 gradient object without header, of another size",
     ["gradient", "--flat", "{d}/flat.exr", "{d}/rect_nometa.exr", "-o", "{d}/new.exr"], "{d}/flat.exr"),
]


@pytest.mark.parametrize("argv,fragment", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_cli_bad_input(d, capfd, argv, fragment):
    before = {p.name for p in d.rglob("*")}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = _main([a.format(d=d) for a in argv])
    out, err = capfd.readouterr()  # file descriptors: a library's log lines count too
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("elo-mitsuba"), err
    assert fragment.format(d=d) in lines[0], lines[0]
    assert not [str(w.message) for w in caught if not issubclass(w.category, ResourceWarning)]  # no numpy warning
    assert {p.name for p in d.rglob("*")} == before  # nothing written


def test_the_good_neighbours_still_run(d, capfd):
    """What the refusals leave alone: NaN at a masked pixel (another tool's unknown), a
    second-event render of the images' own set-up, the good calibration, --min-component on the
    masked solver."""
    assert main([*(a.format(d=d) for a in REC[:1]), str(d / "nan_masked.exr"), "-o", str(d / "ok1.npy")]) == 0
    assert main([a.format(d=d) for a in G[:-1]] + [str(d / "ok2.exr"), "--second-event", str(d / "se_ok.exr"),
                                                   "--calibration", str(d / "cal_ok.json")]) == 0
    assert main([a.format(d=d) for a in REC[:-1]] + [str(d / "ok3.npy"), "--method", "masked",
                                                     "--min-component", "5"]) == 0
    capfd.readouterr()


@pytest.mark.parametrize("argv,fragment", [
    (["gradient", *four("obj_")[:-2], "--front", "{d}/trunc.tif", *FLATS, *SINGLE], "trunc.tif: not a readable TIFF"),
    (["mesh", "{d}/trunc.tif", "-o", "{d}/new.ply"], "trunc.tif' could not be read"),
], ids=["gradient", "mesh"])
def test_a_truncated_tiff_is_one_line(d, argv, fragment):
    """B5: tifffile logged each tag it could not read ('<TiffTag.fromfile> raised ...') before the
    refusal; in a process of its own, where no test harness takes the log records."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "elo_mitsuba", *(a.format(d=d) for a in argv)], capture_output=True,
                         text=True, timeout=120)
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and len(lines) == 1 and fragment.format(d=d) in lines[0], run.stderr


def test_an_upper_case_npy_is_written_as_named(d, tmp_path, capfd):
    """A2: np.save appended '.npy' to '.r.NPY.partial-<pid>.NPY' and the rename failed after the work,
    leaving the hidden file behind."""
    from elo_mitsuba.heightmap import write_height

    assert main(["reconstruct", str(d / "grad.exr"), "-o", str(tmp_path / "r.NPY")]) == 0
    write_height(tmp_path / "w.Npy", np.ones((2, 3)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.NPY", "w.Npy"]  # nothing stray
    assert np.load(tmp_path / "r.NPY").shape == (16, 16) and np.load(tmp_path / "w.Npy").shape == (2, 3)
    capfd.readouterr()


def test_the_inversion_estimate_notes_long_runs():
    """E12: 100000 uncertainty probes at 32^2 take about 17 min on 2 cores (4000 measured: 48 s) and
    were started without a word; the estimate of any inversion counts its fixed cost (32^2 with
    no probes: 8.9 s measured, 0.3 s estimated before)."""
    from elo_mitsuba import budget

    notes = budget.check_inversion((32, 32), 10, 4, 100000, available=10 ** 10)
    assert len(notes) == 1 and "100000 uncertainty probes" in notes[0] and "min" in notes[0], notes
    assert budget.check_inversion((32, 32), 10, 4, 8, available=10 ** 10) == []
    assert budget.estimate_inversion((32, 32), 10, 4, 0)["seconds"] >= budget.INVERSION_FIXED_SECONDS


def test_a_second_event_render_of_another_size_says_what_to_do(d):
    """I22: the line said '(16, 16) px, the images (32, 32)'."""
    from elo_mitsuba.analysis.io import read_later_events

    message = one_line_error(lambda: read_later_events(d / "se_ok.exr", (32, 32)))
    assert "16x16 px, the images 32x32 px; render the flat plate's later events at the images' resolution" in message


def test_the_calibration_keys_are_the_ones_written(d):
    """G17: the keys read_calibration accepts are those write_calibration writes."""
    from elo_mitsuba.analysis.calibration import DETECTOR_KEYS, FILE_KEYS, Calibration, DetectorFit
    from elo_mitsuba.analysis.scan_geometry import Disc

    fit = DetectorFit(disc=Disc([127.0, 0.0, 272.0], [-0.4, 0.0, -0.9], 25.0), gain=1.0, offset=0.0, sigma={},
                      correlation={}, degenerate=[], rms_residual=0.0)
    doc = Calibration(detectors={"right": fit}, source={}).as_dict()
    assert tuple(doc) == FILE_KEYS and tuple(doc["detectors"]["right"]) == DETECTOR_KEYS
