"""Issue 13, item 6: a table of bad inputs, CLI and API. Each gives one line (CLI: on stderr,
``elo-mitsuba: error: ...``, exit status 2), no traceback, writes nothing and leaves what was
there untouched. The CLI runs in-process (``elo_mitsuba.cli.main``) to stay fast; a few cases
run as real processes (subprocess) at the end."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys

import numpy as np
import pytest

import elo_mitsuba as em
from conftest import one_line_error
from elo_mitsuba.cli import main
from elo_mitsuba.exr import write_exr
from elo_mitsuba.scene_files import scenes_dir

SENTINEL = b"written by the user"


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    """A folder with valid inputs of every command, a file 'afile', a folder 'adir' and an
    existing output 'exists.*' of every kind."""
    d = tmp_path_factory.mktemp("bad")
    assert main(["render", "flat_plate", "-o", str(d / "flat.exr"), "--resolution", "8", "--quiet"]) == 0
    assert main(["render", "corrugated_sheet", "-o", str(d / "corr.exr"), "--resolution", "8", "--quiet"]) == 0
    assert main(["gradient", "--flat", str(d / "flat.exr"), str(d / "corr.exr"), "-o", str(d / "grad.exr")]) == 0
    (d / "afile").write_bytes(SENTINEL)
    (d / "adir").mkdir()
    (d / "adir.exr").mkdir()
    (d / "folder" ".md").mkdir()  # a folder named like the report
    for suffix in ("exr", "png", "npy", "ply", "xml", "json", "md", "npz", "tif"):
        (d / f"exists.{suffix}").write_bytes(SENTINEL)
    rng = np.random.default_rng(0)
    np.save(d / "hm.npy", rng.random((6, 7)))
    np.save(d / "hm_nan.npy", np.full((6, 7), np.nan))
    np.save(d / "cube.npy", np.zeros((3, 3, 3)))
    (d / "garbage.npy").write_bytes(b"\x00not an array")
    (d / "garbage.exr").write_bytes(b"\x00not an exr")
    (d / "img.png").write_bytes(b"\x89PNG")
    for n in ("right", "left", "back", "front"):
        np.save(d / f"ok_{n}.npy", np.ones((8, 8)))
        np.save(d / f"zero_{n}.npy", np.zeros((8, 8)))
        np.save(d / f"neg_{n}.npy", -np.ones((8, 8)))
        np.save(d / f"nan_{n}.npy", np.full((8, 8), np.nan))
        np.save(d / f"mixed_{n}.npy", np.array([[1.0, -1.0], [1.0, 1.0]]))
        spike = np.ones((8, 8))
        spike[2, 5] = 1e30  # a saturated or glitched pixel
        np.save(d / f"spike_{n}.npy", spike)
        np.save(d / f"bright_{n}.npy", np.where(np.arange(64).reshape(8, 8) == 21, 900.0, 1.0))  # kept
    np.save(d / "small_right.npy", np.ones((4, 4)))
    write_exr(d / "nofield.exr", {"dzdx": np.zeros((4, 4)), "dzdy": np.zeros((4, 4))})
    # scenes a user might write
    src = scenes_dir()
    shutil.copy(src / "flat_plate.xml", d / "copied.xml")
    text = (src / "flat_plate.xml").read_text()
    absolute = text.replace('"layouts/', f'"{src.as_posix()}/layouts/').replace('"parts/', f'"{src.as_posix()}/parts/')
    (d / "parts").mkdir()
    for f in (src / "parts").glob("*.xml"):
        (d / "parts" / f.name).write_text(f.read_text().replace('<scale value="25"/>', '<scale value="0"/>'))
    (d / "zero_radius.xml").write_text(absolute.replace(f'"{src.as_posix()}/parts/', '"parts/'))
    corr = (src / "corrugated_sheet.xml").read_text().replace('"layouts/', f'"{src.as_posix()}/layouts/')
    corr = corr.replace('"parts/', f'"{src.as_posix()}/parts/').replace("meshes/corrugated_sheet.ply", "garbage.ply")
    (d / "garbage_ply.xml").write_text(corr)
    (d / "garbage.ply").write_bytes(bytes(range(256)) * 8)
    (d / "malformed.xml").write_text("<scene version='3.0.0'><shape")
    (d / "notscene.xml").write_text("<material/>")
    (d / "path.xml").write_text(absolute.replace('type="elo"', 'type="path"', 1))
    return d


def _snapshot(d):
    return {p.name: p.read_bytes() for p in d.rglob("*") if p.is_file()}


R = ["render", "flat_plate", "--resolution", "4"]
OUT = ["-o", "{d}/new.exr"]
G_FLAT = ["--flat", "{d}/flat.exr"]
FOUR = "--right {d}/{p}_right.npy --left {d}/{p}_left.npy --back {d}/{p}_back.npy --front {d}/{p}_front.npy".split()
GEO = ["--field", "80", "--dh", "272", "--dw", "127"]


def four(prefix):
    return [a.replace("{p}", prefix) for a in FOUR]


#: (id, argv, a fragment of the one line)
CLI_CASES = [
    # -- render: the scene
    ("render no such scene", ["render", "no_such_scene", *OUT], "neither an XML file nor a shipped scene"),
    ("render no such xml", ["render", "{d}/nothere.xml", *OUT], "does not exist"),
    ("render a folder", ["render", "{d}", *OUT], "is a folder; give an XML file in it"),
    ("render copied scene", ["render", "{d}/copied.xml", *OUT, "-D", "dh=250"], "included file 'layouts/zeta25.xml' not found"),
    ("render zero radius", ["render", "{d}/zero_radius.xml", *OUT], "has area 0 mm^2"),
    ("render garbage ply", ["render", "{d}/garbage_ply.xml", *OUT], "is not a PLY file"),
    ("render malformed xml", ["render", "{d}/malformed.xml", *OUT], "malformed XML"),
    ("render not a scene", ["render", "{d}/notscene.xml", *OUT], "expected <scene>"),
    ("render path integrator", ["render", "{d}/path.xml", *OUT], 'unreferenced property in integrator plugin of type "path"'),
    # -- render: outputs
    ("render -o suffix", [*R, "-o", "{d}/new.png"], "must end in .exr"),
    ("render -o no folder", [*R, "-o", "{d}/nodir/new.exr"], "does not exist"),
    ("render -o parent is a file", [*R, "-o", "{d}/afile/new.exr"], "is a file, not a directory"),
    ("render -o is a folder", [*R, "-o", "{d}/adir.exr"], "is a folder"),
    ("render -o exists", [*R, "-o", "{d}/exists.exr"], "exists; pass --overwrite"),
    ("render --preview suffix", [*R, *OUT, "--preview", "{d}/p.jpg"], "must end in .png"),
    ("render --preview exists", [*R, *OUT, "--preview", "{d}/exists.png"], "exists; pass --overwrite"),
    ("render --preview parent is a file", [*R, *OUT, "--preview", "{d}/afile/p.png"], "is a file, not a directory"),
    ("render --preview no folder", [*R, *OUT, "--preview", "{d}/nodir/p.png"], "does not exist"),
    # -- render: numbers
    ("render --spp 0", [*R, *OUT, "--spp", "0"], "0 must be >= 1"),
    ("render --spp -1", [*R, *OUT, "--spp", "-1"], "-1 must be >= 1"),
    ("render --spp abc", [*R, *OUT, "--spp", "abc"], "'abc' is not an integer"),
    ("render --spp 2.5", [*R, *OUT, "--spp", "2.5"], "'2.5' is not an integer"),
    ("render --events 0", [*R, *OUT, "--events", "0"], "0 must be >= 1"),
    ("render --events 100", [*R, *OUT, "--events", "100"], r"events=100; must be in [1, 10]"),
    ("render --resolution 0", [*R, *OUT, "--resolution", "0"], "0 must be >= 1"),
    ("render --resolution 100000", ["render", "flat_plate", *OUT, "--resolution", "100000"], "of memory"),
    ("render --seed -1", [*R, *OUT, "--seed", "-1"], "-1 must be >= 0"),
    ("render --seed 2^32", [*R, *OUT, "--seed", "4294967296"], "is above 4294967295"),
    ("render --seed x", [*R, *OUT, "--seed", "x"], "'x' is not an integer"),
    ("render --variant", [*R, *OUT, "--variant", "scalar_rgb"], "is not supported"),
    ("render --units", [*R, *OUT, "--units", "volts"], "invalid choice: 'volts'"),
    ("render --quality", [*R, *OUT, "--quality", "best"], "invalid choice: 'best'"),
    ("render --beam-current without volts", [*R, *OUT, "--beam-current", "1e-3"], "add --units voltage"),
    ("render --transimpedance without volts", [*R, *OUT, "--transimpedance", "1e6"], "add --units voltage"),
    ("render --beam-current -1", [*R, *OUT, "--units", "voltage", "--beam-current", "-1"], "beam_current=-1.0"),
    ("render --transimpedance x", [*R, *OUT, "--units", "voltage", "--transimpedance", "x"], "'x' is not a number"),
    ("render --detector-samples 0", [*R, *OUT, "--detector-samples", "0"], "0 must be >= 1"),
    ("render --detector-samples no effect", [*R, *OUT, "--detector-samples", "4"], "would change nothing"),
    ("render --layout zeta99", [*R, *OUT, "--layout", "zeta99"], "unknown detector layout 'zeta99'"),
    ("render --layout abc", [*R, *OUT, "--layout", "abc"], "unknown detector layout 'abc'"),
    ("render unknown flag", [*R, *OUT, "--colour", "red"],
     "render: error: unrecognized arguments: --colour red (see 'elo-mitsuba render --help')"),
    ("render no -o", [*R], "the following arguments are required: -o/--output"),
    # -- render: -D
    ("render -D no =", [*R, *OUT, "-D", "dh"], "is not NAME=VALUE"),
    ("render -D =5", [*R, *OUT, "-D", "=5"], "is not NAME=VALUE"),
    ("render -D dh=", [*R, *OUT, "-D", "dh="], "'dh=' gives dh no value"),
    ("render -D dh=1e40", [*R, *OUT, "-D", "dh=1e40"], "parameter dh='1e40' is not a finite number"),
    ("render -D unknown", [*R, *OUT, "-D", "colour=red"], "parameter 'colour' is not declared"),
    ("render -D dh=abc", [*R, *OUT, "-D", "dh=abc"], "parameter dh='abc' is not a valid"),
    ("render -D dh=inf", [*R, *OUT, "-D", "dh=inf"], "parameter dh='inf' is not a finite number"),
    ("render -D fwhm=nan", [*R, *OUT, "-D", "fwhm=nan"], "parameter fwhm='nan' is not a finite number"),
    ("render -D wd=abc", [*R, *OUT, "-D", "wd=abc"], "parameter wd='abc' is not a valid"),
    ("render -D res=x", ["render", "flat_plate", *OUT, "-D", "res=x"], "parameter res='x' is not a valid"),
    ("render -D dh=1 cuts the plate", [*R, *OUT, "-D", "dh=1"], "reaches down to z=-24 mm, through the build plane"),
    ("render -D dh=-10", [*R, *OUT, "-D", "dh=-10"], "at or below the build plane"),
    ("render -D dw=0 stacks the detectors", [*R, *OUT, "-D", "dw=0"], "detectors 'right' and 'left' intersect"),
    ("render -D layout", [*R, *OUT, "-D", "layout=zeta99"], "layout='zeta99' is not available"),
    ("render -D plates", [*R, *OUT, "-D", "plates=gold"], "plates='gold' is not available"),
    ("render -D spp", [*R, *OUT, "-D", "spp=64"], "-D spp=64 sets the scene file's sampler"),
    ("render -D material", [*R, *OUT, "-D", "material=Unobtainium"], "Unobtainium"),
    ("render -D composition", [*R, *OUT, "-D", "material=Ti:0.5,Al:0.2"], "sum"),
    ("render -D field=0", [*R, *OUT, "-D", "field=0"], "field"),
    ("render -D field=-5", [*R, *OUT, "-D", "field=-5"], "field"),
    ("render -D fwhm=-1", [*R, *OUT, "-D", "fwhm=-1"], "fwhm"),
    # a beam as wide as the field lights all of it at every scan point (fwhm=1e30 rendered zeros)
    ("render -D fwhm=100", [*R, *OUT, "-D", "fwhm=100"], "fwhm=100 mm; must be below the scan field's 80 mm"),
    ("render -D fwhm=1e30", [*R, *OUT, "-D", "fwhm=1e30"], "fwhm=1e+30 mm; must be 0 (a single ray) or 1e-06 to 1e+06 mm"),
    ("render -D projection", [*R, *OUT, "-D", "projection=fisheye"], "fisheye"),
    # -- calibrate
    ("calibrate --event 0", ["calibrate", "{d}/flat.exr", "--event", "0", "-o", "{d}/c.json"],
     "argument --event: 0 must be >= 1"),  # was "missing channel(s) right.e0"
    # -- gradient
    ("gradient no object", ["gradient", *G_FLAT, "-o", "{d}/g.exr"], "no object images"),
    ("gradient object missing", ["gradient", *G_FLAT, "{d}/nothere.exr", "-o", "{d}/g.exr"], "no such file"),
    ("gradient object garbage", ["gradient", *G_FLAT, "{d}/garbage.exr", "-o", "{d}/g.exr"], "not a readable EXR"),
    ("gradient object lacks channels", ["gradient", *G_FLAT, "{d}/grad.exr", "-o", "{d}/g.exr"], "missing channel(s) right"),
    ("gradient no flat", ["gradient", "{d}/corr.exr", "-o", "{d}/g.exr"], "no flat-plate images"),
    ("gradient --no-flat with flat", ["gradient", *G_FLAT, "{d}/corr.exr", "--no-flat", "-o", "{d}/g.exr"],
     "--no-flat contradicts"),
    ("gradient exr and files", ["gradient", "{d}/corr.exr", *four("ok"), *G_FLAT, "-o", "{d}/g.exr"], "not both"),
    ("gradient three files", ["gradient", *four("ok")[:6], "--no-flat", *GEO, "-o", "{d}/g.exr"], "missing front image"),
    ("gradient files without geometry", ["gradient", *four("ok"), "--no-flat", "-o", "{d}/g.exr"],
     "single-channel inputs carry no geometry"),
    ("gradient zero images", ["gradient", *four("zero"), "--no-flat", *GEO, "-o", "{d}/g.exr"], "recorded nothing"),
    ("gradient negative images", ["gradient", *four("neg"), "--no-flat", *GEO, "-o", "{d}/g.exr"], "ratios >= 0"),
    ("gradient nan images", ["gradient", *four("nan"), "--no-flat", *GEO, "-o", "{d}/g.exr"], "NaN or Inf"),
    ("gradient mixed sign", ["gradient", *four("mixed"), "--no-flat", *GEO, "-o", "{d}/g.exr"], "others positive"),
    ("gradient spike", ["gradient", *four("spike"), "--no-flat", *GEO, "-o", "{d}/g.exr"],
     "1 pixel(s) above 1000 x the image's median 1 (the largest 1e+30 at row 2, column 5)"),
    ("gradient png input", ["gradient", *four("ok")[:-1], "{d}/img.png", "--no-flat", *GEO, "-o", "{d}/g.exr"],
     "unsupported image type .png"),
    ("gradient garbage npy", ["gradient", *four("ok")[:-1], "{d}/garbage.npy", "--no-flat", *GEO, "-o", "{d}/g.exr"],
     "not a readable .npy"),
    ("gradient 3-D npy", ["gradient", *four("ok")[:-1], "{d}/cube.npy", "--no-flat", *GEO, "-o", "{d}/g.exr"],
     "expected one 2-D numeric image"),
    ("gradient shapes differ", ["gradient", "--right", "{d}/small_right.npy", *four("ok")[2:], "--no-flat", *GEO,
                                "-o", "{d}/g.exr"], "differ in shape"),
    ("gradient -o suffix", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.tif"], "must end in .exr"),
    ("gradient -o exists", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/exists.exr"], "exists; pass --overwrite"),
    ("gradient -o parent is a file", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/afile/g.exr"], "is a file"),
    ("gradient --preview exists", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--preview",
                                   "{d}/exists.png"], "exists; pass --overwrite"),
    ("gradient --field abc", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--field", "abc"],
     "give FX or FX,FY"),
    ("gradient --field 0", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--field", "0"],
     "one or two lengths of 1e-06 to 1e+06 mm"),
    ("gradient --dh -1", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--dh", "-1"], "must be a length of 1e-06 to 1e+06 mm"),
    # lengths beyond any chamber: the calibration's fit raised scipy's "initial guess outside bounds"
    ("calibrate --field 1e300", ["calibrate", "{d}/flat.exr", "-o", "{d}/c.json", "--field", "1e300"],
     "'1e300': give one or two lengths of 1e-06 to 1e+06 mm"),
    ("gradient --dh 1e300", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--dh", "1e300", "--dw", "127"],
     "'1e300': must be a length of 1e-06 to 1e+06 mm"),
    ("gradient --dw nan", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--dw", "nan"], "must be a length of"),
    # a noise of 1e-300 overflowed the misfit's chi^2 (numpy warnings, then uncertainties of 0); an
    # empty material fell back to the header's without a word; a FWHM of 1e-300 was a profile here and
    # refused by renders and headers; an alpha of 1e300 overflowed the float32 preconditioner
    ("gradient --noise 1e-300", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--noise", "1e-300"],
     "'1e-300': must be a number from 1e-09 to 1"),
    ("invert --noise 1e300", ["invert", *G_FLAT, "{d}/corr.exr", "-o", "{d}/h.exr", "--noise", "1e300"],
     "'1e300': must be a number from 1e-09 to 1"),
    ("gradient --noise 2", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--noise", "2"],
     "'2': must be a number from 1e-09 to 1"),
    ("gradient --material empty", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--material", ""],
     "argument --material: '' is empty; give a preset"),
    ("calibrate --material empty", ["calibrate", "{d}/flat.exr", "-o", "{d}/c.json", "--material", ""],
     "argument --material: '' is empty; give a preset"),
    ("invert --fwhm 1e-300", ["invert", *G_FLAT, "{d}/corr.exr", "-o", "{d}/h.exr", "--fwhm", "1e-300"],
     "'1e-300': must be 0 (a single ray) or 1e-06 to 1e+06 mm"),
    ("invert --alpha 1e300", ["invert", *G_FLAT, "{d}/corr.exr", "-o", "{d}/h.exr", "--alpha", "1e300"],
     "--alpha 1e+300: must be at most 1e+06"),
    ("reflectance-map --range 1e300", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.png", "--range", "1e300"],
     "--range 1e+300: must be at most 1000"),
    ("gradient --event 3", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--event", "3"], "right.e3"),
    ("gradient --event x", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--event", "x"], "invalid int value"),
    # -- reconstruct
    ("reconstruct missing", ["reconstruct", "{d}/nothere.exr", "-o", "{d}/h.npy"], "no such file"),
    ("reconstruct garbage", ["reconstruct", "{d}/garbage.exr", "-o", "{d}/h.npy"], "not a readable EXR"),
    ("reconstruct not a gradient", ["reconstruct", "{d}/flat.exr", "-o", "{d}/h.npy"], "missing channel(s) dzdx"),
    ("reconstruct no field", ["reconstruct", "{d}/nofield.exr", "-o", "{d}/h.npy"], "no 'field_mm' in the header"),
    ("reconstruct -o suffix", ["reconstruct", "{d}/grad.exr", "-o", "{d}/h.png"], "must end in"),
    ("reconstruct -o exists", ["reconstruct", "{d}/grad.exr", "-o", "{d}/exists.npy"], "exists; pass --overwrite"),
    ("reconstruct -o parent is a file", ["reconstruct", "{d}/grad.exr", "-o", "{d}/afile/h.npy"], "is a file"),
    ("reconstruct -o no folder", ["reconstruct", "{d}/grad.exr", "-o", "{d}/nodir/h.npy"], "does not exist"),
    ("reconstruct --preview exists", ["reconstruct", "{d}/grad.exr", "-o", "{d}/h.npy", "--preview", "{d}/exists.png"],
     "exists; pass --overwrite"),
    ("reconstruct --preview parent is a file", ["reconstruct", "{d}/grad.exr", "-o", "{d}/h.npy", "--preview",
                                                "{d}/afile/h.png"], "is a file"),
    ("reconstruct --method", ["reconstruct", "{d}/grad.exr", "-o", "{d}/h.npy", "--method", "poisson"],
     "invalid choice: 'poisson'"),
    ("reconstruct --min-component 0", ["reconstruct", "{d}/grad.exr", "-o", "{d}/h.npy", "--min-component", "0"],
     "must be >= 1"),
    ("reconstruct --field 0", ["reconstruct", "{d}/grad.exr", "-o", "{d}/h.npy", "--field", "0"], "lengths of 1e-06 to 1e+06 mm"),
    # -- mesh
    ("mesh missing", ["mesh", "{d}/nothere.npy", "-o", "{d}/m.ply", "--pixel-size", "0.05"], "nothere.npy"),
    ("mesh -o suffix", ["mesh", "{d}/hm.npy", "-o", "{d}/m.obj", "--pixel-size", "0.05"], "must end in .ply"),
    ("mesh -o exists", ["mesh", "{d}/hm.npy", "-o", "{d}/exists.ply", "--pixel-size", "0.05"], "exists"),
    ("mesh --pixel-size 0", ["mesh", "{d}/hm.npy", "-o", "{d}/m.ply", "--pixel-size", "0"], "pixel"),
    ("mesh --pixel-size abc", ["mesh", "{d}/hm.npy", "-o", "{d}/m.ply", "--pixel-size", "abc"], "is not a number"),
    ("mesh nan heights", ["mesh", "{d}/hm_nan.npy", "-o", "{d}/m.ply", "--pixel-size", "0.05"], "42 non-finite height(s)"),
    ("mesh --scene suffix", ["mesh", "{d}/hm.npy", "-o", "{d}/m.ply", "--pixel-size", "0.05", "--scene", "{d}/s.txt"],
     "must end in .xml"),
    ("mesh --scene exists", ["mesh", "{d}/hm.npy", "-o", "{d}/m.ply", "--pixel-size", "0.05", "--scene",
                             "{d}/exists.xml"], "exists"),
    ("mesh --material", ["mesh", "{d}/hm.npy", "-o", "{d}/m.ply", "--pixel-size", "0.05", "--scene", "{d}/s.xml",
                         "--material", "Unobtainium"], "Unobtainium"),
    ("mesh garbage", ["mesh", "{d}/garbage.npy", "-o", "{d}/m.ply", "--pixel-size", "0.05"], "garbage.npy"),
    # -- reflectance-map
    ("reflectance-map -o suffix", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.jpg"], "must end in .png"),
    ("reflectance-map -o exists", ["reflectance-map", "--zeta", "50", "-o", "{d}/exists.png"], "exists"),
    ("reflectance-map --data no folder", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.png", "--data",
                                          "{d}/nodir/m.npz"], "does not exist"),
    ("reflectance-map --data exists", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.png", "--data",
                                       "{d}/exists.npz"], "exists"),
    ("reflectance-map --zeta 33", ["reflectance-map", "--zeta", "33", "-o", "{d}/m.png"], "invalid choice"),
    ("reflectance-map --material", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.png", "--material", "Xx"], "Xx"),
    ("reflectance-map --samples 0", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.png", "--samples", "0"], "samples"),
    # -- validate / benchmark (their outputs are checked before any study runs)
    ("validate --json no folder", ["validate", "--quick", "--json", "{d}/nodir/x.json"], "does not exist"),
    ("validate --json exists", ["validate", "--quick", "--json", "{d}/exists.json"], "exists"),
    ("validate --output-dir is a file", ["validate", "--quick", "--output-dir", "{d}/afile"], "is a file, not a folder"),
    ("validate --output-dir under a file", ["validate", "--quick", "--output-dir", "{d}/afile/sub"], "is a file"),
    ("validate --update-report --quick", ["validate", "--quick", "--update-report"], "--update-report rewrites"),
    ("benchmark --out no folder", ["benchmark", "--out", "{d}/nodir/r.md"], "does not exist"),
    ("benchmark --out suffix", ["benchmark", "--out", "{d}/r.txt"], "must end in .md"),
    ("benchmark --out is a folder", ["benchmark", "--out", "{d}/folder.md"], "is a folder"),
    # -- the command itself
    ("unknown command", ["paint", "x"], "invalid choice: 'paint'"),
    # an empty value (an unset shell variable) was taken as the option not given: no preview, rc 0
    ("render --preview empty", ["render", "flat_plate", *OUT, "--preview", ""], "--preview '': empty; give a value"),
    ("gradient --preview empty", ["gradient", *G_FLAT, "{d}/corr.exr", "-o", "{d}/g.exr", "--preview", ""],
     "--preview '': empty; give a value"),
    ("invert --preview empty", ["invert", *G_FLAT, "{d}/corr.exr", "-o", "{d}/h.exr", "--preview", ""],
     "--preview '': empty; give a value"),
    ("reconstruct --preview empty", ["reconstruct", "{d}/flat.exr", "-o", "{d}/h.npy", "--preview", ""],
     "--preview '': empty; give a value"),
    ("gradient --flat empty", ["gradient", "--flat", "", "{d}/corr.exr", "-o", "{d}/g.exr"],
     "--flat '': empty; give a value"),
]


@pytest.mark.parametrize("argv,fragment", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_cli_bad_input(d, capsys, argv, fragment):
    before = _snapshot(d)
    rc = _main([a.format(d=d) for a in argv])
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith(("elo-mitsuba: error: ", "elo-mitsuba ", "python -m ")), err
    assert "Traceback" not in err and fragment in lines[0], lines[0]
    assert _snapshot(d) == before  # nothing written, nothing touched


def _main(argv):
    """``main`` with argparse's own exits (usage errors) as exit statuses."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


def _scene():
    return em.load_scene("flat_plate", res=2)


#: (id, call, a fragment of the one-line EloInputError)
API_CASES = [
    ("load_scene int", lambda: em.load_scene(123), "scene 123 (int)"),
    ("load_scene None", lambda: em.load_scene(None), "scene None"),
    ("load_scene unknown", lambda: em.load_scene("nope"), "neither an XML file nor a shipped scene"),
    ("load_scene empty", lambda: em.load_scene(""), "scene '' is empty; give an XML path"),  # was "a folder"
    ("load_scene bad value", lambda: em.load_scene("flat_plate", dh="abc"), "parameter dh='abc'"),
    ("load_scene unknown parameter", lambda: em.load_scene("flat_plate", colour=1), "'colour' is not declared"),
    ("load_scene bad layout", lambda: em.load_scene("flat_plate", detector_layout="zeta99"), "zeta99"),
    ("render spp nan", lambda: _scene().render(spp=math.nan), "spp=nan"),
    ("render spp text", lambda: _scene().render(spp="x"), "spp='x'"),
    ("render spp 0", lambda: _scene().render(spp=0), "spp=0"),
    ("render seed -1", lambda: _scene().render(seed=-1), "seed=-1"),
    ("render quality", lambda: _scene().render(quality="best"), "quality 'best'"),
    ("render events 0", lambda: _scene().render(events=0), "events=0"),
    ("render events 100", lambda: _scene().render(events=100), "events=100"),
    ("set_detector unknown", lambda: _scene().set_detector("top", center=(0, 0, 100)), "no detector 'top'"),
    ("set_detector text", lambda: _scene().set_detector("right", center="abc"), "centre 'abc'"),
    ("set_detector origin", lambda: _scene().set_detector("right", center=(0, 0, 0)), "is the origin"),
    ("set_detector two values", lambda: _scene().set_detector("right", center=(1, 2)), "need 3 finite numbers"),
    ("set_detector nan", lambda: _scene().set_detector("right", center=(math.nan, 0, 200)), "need 3 finite"),
    ("set_detector radius", lambda: _scene().set_detector("right", radius=-1), "mm > 0"),
    ("set_detector radius text", lambda: _scene().set_detector("right", radius="big"), "radius 'big'"),
    ("set_detector below", lambda: _scene().set_detector("right", center=(127, 0, -5)), "below the build plane"),
    ("set_detector cuts the plate", lambda: _scene().set_detector("right", center=(127, 0, 5)), "reaches down"),
    ("render with a detector moved onto another", lambda: _moved_onto_back().render(quality="draft", progress=False),
     "detectors 'right' and 'back' intersect (centres 0 mm apart"),
    ("set_material unknown material", lambda: _scene().set_material("plate", "Unobtainium"), "Unobtainium"),
    ("set_material unknown shape", lambda: _scene().set_material("lid", "Cu"), "no shape with id 'lid'"),
    ("configure unknown", lambda: _scene().configure(colour=1), "no option 'colour'"),
    ("configure events", lambda: _scene().configure(events=100), "events=100"),
    ("configure units", lambda: _scene().configure(units="amps"), "amps"),
    ("integrate shapes", lambda: _integrate(np.zeros((3, 4)), np.zeros((4, 3))), "expected two 2-D arrays of one shape"),
    ("integrate 1-D", lambda: _integrate(np.zeros(4), np.zeros(4)), "expected two 2-D arrays"),
    ("integrate method", lambda: _integrate(np.zeros((3, 3)), np.zeros((3, 3)), method="poisson"), "'poisson'"),
    ("integrate mask", lambda: _integrate(np.zeros((3, 3)), np.zeros((3, 3)), mask=np.zeros((2, 2), bool)),
     "mask shape (2, 2)"),
    ("write_exr nan", lambda: write_exr("/tmp/never-written.exr", {"a": np.full((2, 2), np.nan)}), "NaN or Inf"),
    ("write_exr no channels", lambda: write_exr("/tmp/never-written.exr", {}), "no channels"),
    ("material composition", lambda: _material("Ti:0.5,Al:0.2"), "sum"),
    ("material unknown", lambda: _material("Unobtainium"), "Unobtainium"),
]


def _integrate(*args, **kw):
    from elo_mitsuba.analysis import integrate_gradient

    return integrate_gradient(*args, 10.0, **kw)


def _material(text):
    from elo_mitsuba.physics import get_material

    return get_material(text)


@pytest.mark.parametrize("call,fragment", [c[1:] for c in API_CASES], ids=[c[0] for c in API_CASES])
def test_api_bad_input(call, fragment):
    message = one_line_error(call)
    assert fragment in message, message


@pytest.mark.parametrize("argv,fragment", [
    (["render", "flat_plate", "-o", "{d}/afile/x.exr"], "is a file, not a directory"),
    (["render", "flat_plate", "-o", "{d}/new.exr", "--resolution", "4", "-D", "dh=abc"], "parameter dh='abc'"),
    (["gradient", "--flat", "{d}/flat.exr", "{d}/nothere.exr", "-o", "{d}/g.exr"], "no such file"),
])
def test_real_processes(d, argv, fragment):
    before = _snapshot(d)
    r = subprocess.run([sys.executable, "-m", "elo_mitsuba", *[a.format(d=d) for a in argv]], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and fragment in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and _snapshot(d) == before


def test_the_table_is_large_enough():
    assert len(CLI_CASES) + len(API_CASES) >= 100
    assert len({c[0] for c in CLI_CASES}) == len(CLI_CASES) and len({c[0] for c in API_CASES}) == len(API_CASES)
    json.dumps([c[1] for c in CLI_CASES])  # plain argv lists


def test_a_measured_composition_is_normalised_with_a_note():
    from elo_mitsuba.physics import get_material

    m = get_material("Ti:0.9,Al:0.06,V:0.0395")  # sums to 0.9995: rounded analysis values
    assert abs(sum(m.composition.values()) - 1) < 1e-12 and "normalised" in m.note and "normalised" in m.describe()
    assert get_material("Ti:0.9,Al:0.06,V:0.04").note == ""
    scene = em.load_scene("flat_plate", res=2, material="Ti:0.9,Al:0.06,V:0.0395")
    assert any("normalised to 1" in n for n in scene.metadata(1, 0)["notes"])


def _moved_onto_back():
    scene = _scene()
    scene.set_detector("right", center=(0, 127, 272))
    return scene


def test_a_bright_pixel_below_the_spike_bound_is_a_signal(d, tmp_path):
    """A pixel 900x its image's median is no surface's either (the validation surfaces stay
    within 9x), but the bound (1000x) leaves room: such images are still read and solved."""
    out = tmp_path / "g.exr"
    assert _main(["gradient", *[a.format(d=d) for a in four("bright")], "--no-flat", *GEO, "-o", str(out)]) == 0
    assert out.exists()


#: Header values elo-mitsuba never writes (a header edited by hand or by another tool), each with
#: what the one-line refusal names; every one ended in a traceback or a ZeroDivisionError before.
BAD_HEADERS = [
    ({"resolution": "abc"}, "header resolution='abc'; need two whole numbers >= 1 [W, H]"),
    ({"resolution": [8, 8, 1]}, "header resolution=[8, 8, 1]"),
    ({"beam_aim_offset_mm": -1}, "header beam_aim_offset_mm=-1; need two lengths"),
    ({"work_distance_mm": []}, "header work_distance_mm=[]"),
    ({"work_distance_mm": 1e-300}, "header work_distance_mm=1e-300; need a length of 1e-06 to 1e+06 mm"),
    ({"field_mm": 1e300}, "header field_mm=1e+300"),
    ({"beam_fwhm_mm": "abc"}, "header beam_fwhm_mm='abc'"),
    ({"events": "abc"}, "header events='abc'; need a whole number >= 1"),
    ({"projection": "fisheye"}, "header projection='fisheye'; need perspective or orthographic"),
    ({"materials": "abc"}, "header materials='abc'"),
    ({"scattering": "abc"}, "header scattering='abc'"),
    ({"detectors": "abc"}, "header detectors='abc'"),
    ({"detectors": {"right": {"center": [1, 2, 3], "normal": [0, 0, -1], "radius": "abc"}}}, "header detectors="),
    ({"detectors": {"right": {"center": [1, 2, 3], "normal": [0, 0, 0], "radius": 25}}}, "header detectors="),
]


@pytest.mark.parametrize("change,fragment", BAD_HEADERS, ids=[next(iter(c)) + "=" + repr(next(iter(c.values())))[:20]
                                                             for c, _ in BAD_HEADERS])
def test_a_bad_header_is_one_line_before_any_work(d, tmp_path, change, fragment):
    from elo_mitsuba.exr import read_exr

    channels, meta = read_exr(d / "flat.exr")
    bad = tmp_path / "bad.exr"
    write_exr(bad, channels, {**meta, **change})
    for argv in (["gradient", "--flat", str(d / "flat.exr"), str(bad), "-o", str(tmp_path / "g.exr")],
                 ["calibrate", str(bad), "-o", str(tmp_path / "c.json")]):
        rc, message = _one_line(argv)
        assert rc == 2 and message.startswith(f"elo-mitsuba: error: {bad}: ") and fragment in message, message
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.exr"]


def _one_line(argv):
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = _main(argv)
    lines = err.getvalue().strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err.getvalue(), err.getvalue()
    return rc, lines[0]


def test_cropped_images_with_the_scans_header_are_refused_by_calibrate_too(d, tmp_path):
    from elo_mitsuba.exr import read_exr

    channels, meta = read_exr(d / "flat.exr")
    bad = tmp_path / "crop.exr"
    write_exr(bad, {k: v[:, :4] for k, v in channels.items()}, meta)
    write_exr(tmp_path / "crop_flat.exr", {k: v[:, :4] for k, v in channels.items()}, meta)
    for argv in (["calibrate", str(bad), "-o", str(tmp_path / "c.json")],
                 ["gradient", "--flat", str(tmp_path / "crop_flat.exr"), str(bad), "-o", str(tmp_path / "g.exr")]):
        rc, message = _one_line(argv)
        assert rc == 2 and "header resolution [8, 8] (W, H) does not match the image shape 4x8" in message, message
