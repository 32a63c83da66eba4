"""Bad input to the forward and design commands (render, mesh, sweep, sweep-plot, optimize) and the
shared output helpers, from the bad-input sweep of issue s69: each case is refused before any work
with exit status 2 and one line naming what is wrong, or (a layout, a mesh's scan field) the
setting recorded is the one applied."""

from __future__ import annotations

import os
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

import elo_mitsuba as em
from conftest import one_line_error
from elo_mitsuba.cli import build_parser, main
from elo_mitsuba.files import atomic_write, check_output
from elo_mitsuba.exr import read_exr
from elo_mitsuba.scene_files import portable_scene_text, shipped_scenes, write_scene

SWEEP = 'scene = "flat_plate"\n[render]\nresolution = 4\n'


def _main(argv):
    try:
        return main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's usage errors
        return exc.code


def _refused(capfd, argv, fragment):
    """Run the CLI in this process: exit status 2, exactly one line on stderr holding ``fragment``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = _main(argv)
    out, err = capfd.readouterr()
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and "error: " in lines[0] and "Traceback" not in err, err
    assert fragment in lines[0], lines[0]
    assert not [str(w.message) for w in caught if not issubclass(w.category, ResourceWarning)]
    return lines[0]


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    d = tmp_path_factory.mktemp("forward")
    (d / "afile").write_text("x")
    (d / "adir.npy").mkdir()
    np.save(d / "h.npy", np.zeros((16, 12), np.float32))
    (d / "opt.toml").write_text("[parameters]\nradius = 25.0\n")
    (d / "sweep.toml").write_text(SWEEP + "[vary]\ndh = [200, 272]\n")
    return d


# --- A3, I21: an output store's folder: one line, as for single files ----------------------------------------------
@pytest.mark.parametrize("command", ["optimize", "sweep"])
def test_a_store_in_a_folder_that_takes_no_files_is_refused(d, capfd, command):
    spec = d / ("opt.toml" if command == "optimize" else "sweep.toml")
    if Path("/proc").is_dir():  # a virtual file system: it took the check and crashed at mkdir (A3)
        _refused(capfd, [command, spec, "-o", "/proc/o.zarr", "--workers", "0"], "cannot write in folder /proc")
    _refused(capfd, [command, spec, "-o", d / "afile" / "o.zarr", "--workers", "0"], "afile is a file, not a directory")
    assert not list(d.glob("*.zarr"))


def test_sweep_plot_of_a_missing_store_says_it_is_missing(d, capfd):
    _refused(capfd, ["sweep-plot", d / "nosuch.zarr", "signal_mean", "-o", d / "p.png"], "nosuch.zarr: no such store")


# --- G16: a single-valued option given twice ----------------------------------------------------------------------
@pytest.mark.parametrize("argv,fragment", [
    (["render", "flat_plate", "-o", "{d}/r.exr", "--resolution", "16", "--resolution", "32"],
     "--resolution 16 and --resolution 32: the option is given twice with different values"),
    (["gradient", "--flat", "{d}/f.exr", "{d}/o.exr", "-o", "{d}/g.exr", "--method", "eq26", "--method", "model"],
     "--method eq26 and --method model"),
    (["gradient", "{d}/o.exr", "-o", "{d}/g.exr", "--wd", "300", "--work-distance", "400"],
     "--wd 300 and --work-distance 400"),  # two spellings of one option
    (["sweep", "{d}/sweep.toml", "-o", "{d}/s.zarr", "--workers", "0", "--workers", "1"], "--workers 0 and --workers 1"),
])
def test_a_repeated_option_with_another_value_is_refused(d, capfd, argv, fragment):
    _refused(capfd, [a.format(d=d) for a in argv], fragment)


def test_options_meant_to_repeat_still_repeat():
    parser = build_parser()
    args = parser.parse_args(["render", "flat_plate", "-o", "x.exr", "-D", "dh=250", "-D", "dw=140",
                              "--resolution", "16", "--resolution", "16"])  # the same value twice: harmless
    assert args.defines == [("dh", "250"), ("dw", "140")] and args.resolution == 16
    assert not [k for k in vars(args) if k.startswith("_")]  # the bookkeeping does not leak into the options
    args = parser.parse_args(["gradient", "--flat", "a.exr", "--flat", "b.exr", "o.exr", "-o", "g.exr"])
    assert args.flat == ["a.exr", "b.exr"]


# --- F14: settings that would change nothing ------------------------------------------------------------------------
@pytest.mark.parametrize("text,fragment", [
    (SWEEP + "[vary]\ndh = [200, 272]\n[keep]\ndownsample = 2\n", "keep.downsample = 2 shrinks kept images"),
    (SWEEP + "[vary]\nright.radius = [10, 20]\ndetectors.radius = [15, 25]\n",
     "vary.right.radius and vary.detectors.radius both set the radius of 'right'"),
    # G15: a layout and the dh it sets
    (SWEEP + "[fixed]\nlayout = \"zeta50\"\n[vary]\ndh = [200, 272]\n",
     "fixed.layout=zeta50 sets dh and dw; vary.dh=200 contradicts it"),
])
def test_a_sweep_spec_setting_that_changes_nothing_is_refused(tmp_path, capfd, text, fragment):
    spec = tmp_path / "s.toml"
    spec.write_text(text)
    _refused(capfd, ["sweep", spec, "-o", tmp_path / "s.zarr", "--workers", "0"], fragment)
    assert not (tmp_path / "s.zarr").exists()


def test_worker_wait_without_workers_is_refused(d, capfd):
    _refused(capfd, ["sweep", d / "sweep.toml", "-o", d / "w.zarr", "--workers", "0", "--worker-wait", "5"],
             "--worker-wait) waits for Dask workers, and workers=0")
    message = one_line_error(lambda: em.sweep(d / "sweep.toml", d / "w.zarr", workers=0, worker_wait_s=5))
    assert "worker_wait_s=5" in message and not (d / "w.zarr").exists()


# --- G15: a layout and the dh/dw it sets; the layout recorded ---------------------------------------------------------
def test_a_layout_parameter_with_dh_is_refused(d, capfd):
    _refused(capfd, ["render", "flat_plate", "-o", d / "l.exr", "-D", "layout=zeta50", "-D", "dh=100"],
             "-D layout=zeta50 sets dh and dw; -D dh=100 contradicts it")
    assert "dw=140 contradicts" in one_line_error(lambda: em.load_scene("flat_plate", layout="zeta50", dw=140))


def test_render_records_the_layout_it_used(tmp_path):
    out = tmp_path / "l.exr"
    assert _main(["render", "flat_plate", "--layout", "zeta50", "--resolution", "4", "--quality", "draft", "-o", out,
                  "--quiet"]) == 0
    params = read_exr(out)[1]["parameters"]
    assert params["layout"] == "zeta50" and float(params["dh"]) == pytest.approx(192.7)


# --- G18: a scene declaring a parameter twice -----------------------------------------------------------------------
def test_a_parameter_declared_twice_in_a_scene_is_refused(tmp_path, capfd):
    text = portable_scene_text(shipped_scenes()["flat_plate"])
    scene = tmp_path / "dup.xml"
    scene.write_text(text.replace('<default name="wd" value="400"/>',
                                  '<default name="wd" value="400"/><default name="wd" value="300"/>'))
    _refused(capfd, ["render", scene, "-o", tmp_path / "o.exr"], "<default name='wd'> is declared twice")


# --- H19: a dangling symbolic link at the output path -----------------------------------------------------------------
def test_a_dangling_link_is_not_replaced_without_overwrite(tmp_path, capfd):
    link = tmp_path / "dangling.exr"
    os.symlink("nowhere.exr", link)
    _refused(capfd, ["render", "flat_plate", "-o", link], "a symbolic link to 'nowhere.exr'")
    assert link.is_symlink()
    assert check_output(link, (".exr",), overwrite=True) == link


def test_an_upper_case_suffix_leaves_no_stray_file(tmp_path):
    """np.save appended ".npy" to a temporary ".NPY" file, so the rename failed (A2)."""
    out = atomic_write(tmp_path / "h.NPY", lambda tmp: np.save(tmp, np.ones(3)))
    assert [p.name for p in tmp_path.iterdir()] == ["h.NPY"] and np.load(out).tolist() == [1, 1, 1]


# --- I20: a folder given as the height map ------------------------------------------------------------------------------
def test_mesh_of_a_folder_says_it_is_a_folder(d, capfd):
    _refused(capfd, ["mesh", d / "adir.npy", "-o", d / "m.ply", "--pixel-size", "0.1"], "adir.npy is a folder")


# --- J25: detector parameters beyond sense ------------------------------------------------------------------------------
@pytest.mark.parametrize("define,fragment", [
    ("dh=1e12", "each coordinate must be within 1e+06 mm of the origin"),
    ("dw=1e12", "each coordinate must be within 1e+06 mm of the origin"),
    ("dw=-127", "parameter dw=-127 is negative"),
])
def test_detectors_beyond_sense_are_refused(d, capfd, define, fragment):
    _refused(capfd, ["render", "flat_plate", "--resolution", "4", "-o", d / "j.exr", "-D", define], fragment)
    assert not (d / "j.exr").exists()


# --- J26: mesh --scene scans the field the mesh covers ------------------------------------------------------------------
def test_mesh_scene_scans_the_field_the_mesh_covers(d, capfd):
    assert _main(["mesh", d / "h.npy", "-o", d / "m.ply", "--pixel-size", "0.1", "--scene", d / "m.xml"]) == 0
    capfd.readouterr()
    fields = [e.get("value") for e in ET.parse(d / "m.xml").getroot().iter("default") if e.get("name") == "field"]
    assert fields == ["1.1"]  # 12 columns of 0.1 mm: centres 1.1 mm apart (the shorter side)
    assert "field_mm=-1.0" in one_line_error(lambda: write_scene(d / "x.xml", d / "m.ply", field_mm=-1.0))
