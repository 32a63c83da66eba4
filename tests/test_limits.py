"""Issue 23, classes 1, 2 and 6: unbounded work is refused up front with its estimate (unless asked
for with --yes / force=True; memory never), outputs that cannot be written are refused before the
work, and nothing is overwritten without --overwrite. Each refusal: exit status 2, one line on
stderr naming what is wrong, nothing written. All cases stop before any real work (fast)."""

from __future__ import annotations

import resource
import subprocess
import sys

import numpy as np
import pytest

import elo_mitsuba as em
from elo_mitsuba import budget
from elo_mitsuba.cli import main

SENTINEL = b"written by the user"
CHATTR = {"ok": False}  # whether the fixture could set the immutable flag


def _main(argv):
    try:
        return main(argv)
    except SystemExit as exc:  # argparse's own exits
        return exc.code


def _snapshot(d):
    return {p.relative_to(d): p.read_bytes() for p in d.rglob("*") if p.is_file()}


def _refused(capsys, d, argv, fragment):
    before = _snapshot(d)
    rc = _main([a.format(d=d) for a in argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("elo-mitsuba: error: ") and "Traceback" not in err, err
    assert fragment in lines[0], lines[0]
    assert _snapshot(d) == before  # nothing written, nothing replaced
    return lines[0]


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    """Valid inputs of every command (tiny), existing outputs, and where chattr works an immutable
    folder 'imm' and immutable files 'imm.*' (the flags are removed afterwards)."""
    d = tmp_path_factory.mktemp("limits")
    assert main(["render", "flat_plate", "-o", str(d / "flat.exr"), "--resolution", "8", "--quiet"]) == 0
    assert main(["render", "corrugated_sheet", "-o", str(d / "corr.exr"), "--resolution", "8", "--quiet"]) == 0
    assert main(["gradient", "--flat", str(d / "flat.exr"), str(d / "corr.exr"), "-o", str(d / "grad.exr")]) == 0
    np.save(d / "hm.npy", np.random.default_rng(0).random((6, 7)))
    for suffix in ("exr", "png", "npy", "ply", "xml", "json", "md", "npz"):
        (d / f"exists.{suffix}").write_bytes(SENTINEL)
        (d / f"imm.{suffix}").write_bytes(SENTINEL)
    (d / "imm").mkdir()
    flagged = [d / "imm", *(d / f"imm.{s}" for s in ("exr", "png", "npy", "ply", "xml", "json", "md", "npz"))]
    try:
        CHATTR["ok"] = subprocess.run(["chattr", "+i", *map(str, flagged)], capture_output=True).returncode == 0
    except OSError:  # no chattr
        CHATTR["ok"] = False
    try:
        yield d
    finally:
        if CHATTR["ok"]:
            subprocess.run(["chattr", "-i", *map(str, flagged)], capture_output=True)


FLAT = ["--flat", "{d}/flat.exr", "{d}/corr.exr"]

# -- class 1: unbounded work, refused with its estimate ------------------------------------------
WORK_CASES = [
    ("render --spp 1e9", ["render", "flat_plate", "-o", "{d}/new.exr", "--spp", "1000000000"],
     "would take about"),
    ("render --spp 1e9 says --yes", ["render", "flat_plate", "-o", "{d}/new.exr", "--spp", "1000000000"],
     "pass --yes (Python: force=True)"),
    ("render --detector-samples 2^31 --events 2", ["render", "athene_flat", "-o", "{d}/new.exr", "--resolution", "8",
                                                   "--detector-samples", "2147483648", "--events", "2"],
     "detector points in the kernel"),
    ("render --detector-samples 2^31 memory even with --yes",
     ["render", "athene_flat", "-o", "{d}/new.exr", "--resolution", "8", "--detector-samples", "2147483648",
      "--events", "2", "--yes"], "of memory"),
    ("invert --uncertainty-probes 1e9", ["invert", *FLAT, "-o", "{d}/h.exr", "--uncertainty-probes", "1000000000"],
     "1000000000 uncertainty probes) would take about"),
    ("invert --iterations 1e8", ["invert", *FLAT, "-o", "{d}/h.exr", "--iterations", "100000000"],
     "would take about"),
]


@pytest.mark.parametrize("argv,fragment", [c[1:] for c in WORK_CASES], ids=[c[0] for c in WORK_CASES])
def test_unbounded_work_is_refused_with_its_estimate(d, capsys, argv, fragment):
    line = _refused(capsys, d, argv, fragment)
    assert "about" in line and ("h " in line or "days" in line or "B of memory" in line)


def test_an_inversion_that_cannot_fit_is_refused_before_it_starts(d, capsys, monkeypatch):
    # a 4000^2 input needs ~29 GB: here the machine is made small instead of the input large
    monkeypatch.setattr(budget, "memory_limit", lambda: (10 ** 6, "left under this process's 'ulimit -v'"))
    line = _refused(capsys, d, ["invert", *FLAT, "-o", "{d}/h.exr", "--yes"], "needs about")
    assert "1 MB is left under this process's 'ulimit -v'" in line and "crop or bin" in line
    with pytest.raises(em.EloInputError, match=r"inverting 4000x4000 px .* needs about 29 GB of memory"):
        budget.check_inversion((4000, 4000), 10, 4, 4, available=16 * 10 ** 9)
    budget.check_inversion((1500, 1500), 10, 4, 4, available=5 * 10 ** 9)  # issue 23: 4.2 GB measured


def test_the_api_refuses_unbounded_renders_and_inversions_unless_forced():
    scene = em.load_scene("flat_plate", res=16)
    with pytest.raises(em.EloInputError, match=r"would take about .* days .*force=True") as err:
        scene.render(spp=2 ** 32 - 1)  # the most a sampler counts (constants.MAX_SPP)
    assert "\n" not in str(err.value)
    from elo_mitsuba.analysis.inversion import invert_heights
    from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    from elo_mitsuba.constants import DETECTOR_NAMES

    ones = {n: np.ones((8, 8)) for n in DETECTOR_NAMES}
    with pytest.raises(em.EloInputError, match=r"inverting 8x8 px .*1000000000 uncertainty probes\) would take about"):
        invert_heights(ones, ones, ScanGeometry(field_mm=(80.0, 80.0), shape=(8, 8)), uncertainty_probes=10 ** 9)
    # force lets the time pass (never the memory)
    budget.check_inversion((64, 64), 10, 4, 10 ** 9, force=True, available=10 ** 10)
    assert budget.check_render((64, 64), 5, 10 ** 9, 1, 10, available=10 ** 10, force=True)  # notes only
    with pytest.raises(em.EloInputError, match="of memory"):
        budget.check_render((64, 64), 5, 1, 2, 1, available=10 ** 10, detector_points=(2 ** 33, 2 ** 31), force=True)


def test_check_work_is_the_one_rule():
    budget.check_work(budget.REFUSE_SECONDS, 10, available=100)  # at the limit: allowed
    with pytest.raises(em.EloInputError, match=r"sweep of 3 points would take about 4.2 h .*; lower --spp, or pass --yes"):
        budget.check_work(budget.REFUSE_SECONDS * 1.05, 10, what="a sweep of 3 points", hint="lower --spp",
                          available=100)
    budget.check_work(1e9, 10, force=True, available=100)
    with pytest.raises(em.EloInputError, match="needs about 1 kB of memory, 100 B|needs about 1 kB of memory"):
        budget.check_work(1, 1000, force=True, available=100)


def test_the_memory_limit_respects_ulimit_v():
    """RLIMIT_AS (ulimit -v) counts, not only MemAvailable: a render that cannot fit under it is
    refused in one line (it segfaulted before)."""
    code = ("from elo_mitsuba import budget; v, what = budget.memory_limit(); "
            "print(what); assert v < 2 * 2 ** 30, v")
    limit = 2 * 2 ** 30
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (limit, limit)))
    assert r.returncode == 0 and "ulimit -v" in r.stdout, r.stdout + r.stderr


def test_a_render_beyond_ulimit_v_is_refused_in_one_line(tmp_path):
    limit = 4 * 10 ** 9
    r = subprocess.run([sys.executable, "-m", "elo_mitsuba", "render", "flat_plate", "-o", str(tmp_path / "u.exr"),
                        "--resolution", "6000", "--quiet"], capture_output=True, text=True, timeout=120,
                       preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (limit, limit)))
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "left under this process's 'ulimit -v'" in r.stderr and "Traceback" not in r.stderr
    assert list(tmp_path.iterdir()) == []


# -- class 2: outputs that cannot be written -----------------------------------------------------
PROC_CASES = [
    ("render -o /proc", ["render", "flat_plate", "-o", "/proc/self/x.exr"], "cannot write in folder /proc/self"),
    ("render --preview /proc", ["render", "flat_plate", "-o", "{d}/new.exr", "--preview", "/proc/x.png"],
     "cannot write in folder /proc"),
    ("gradient -o /proc", ["gradient", *FLAT, "-o", "/proc/self/g.exr"], "cannot write in folder"),
    ("reconstruct -o /proc", ["reconstruct", "{d}/grad.exr", "-o", "/proc/h.npy"], "cannot write in folder"),
    ("invert -o /sys", ["invert", *FLAT, "-o", "/sys/h.exr"], "cannot write in folder /sys"),
    ("calibrate -o /proc", ["calibrate", "{d}/flat.exr", "--dh", "272", "--dw", "127", "-o", "/proc/c.json"],
     "cannot write in folder"),
    ("mesh -o /proc", ["mesh", "{d}/hm.npy", "-o", "/proc/m.ply", "--pixel-size", "0.05"], "cannot write in folder"),
    ("new-scene /proc", ["new-scene", "/proc/s.xml"], "cannot write in folder"),
    ("reflectance-map -o /proc", ["reflectance-map", "--zeta", "50", "-o", "/proc/m.png"], "cannot write in folder"),
    ("reflectance-map --data /proc", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.png", "--data", "/proc/m.npz"],
     "cannot write in folder"),
    ("benchmark --out /proc", ["benchmark", "--out", "/proc/r.md"], "cannot write in folder"),
    ("validate --json /proc", ["validate", "--quick", "--output-dir", "{d}/v", "--json", "/proc/r.json"],
     "cannot write in folder"),
    ("validate --output-dir /proc", ["validate", "--quick", "--output-dir", "/proc/self/report"],
     "cannot write in folder /proc/self"),
]


@pytest.mark.parametrize("argv,fragment", [c[1:] for c in PROC_CASES], ids=[c[0] for c in PROC_CASES])
def test_outputs_in_virtual_folders_are_refused_before_the_work(d, capsys, argv, fragment):
    _refused(capsys, d, argv, fragment)


IMMUTABLE_CASES = [
    ("render -o in immutable folder", ["render", "flat_plate", "-o", "{d}/imm/x.exr"], "immutable (chattr +i)"),
    ("render -o immutable file", ["render", "flat_plate", "-o", "{d}/imm.exr", "--overwrite"],
     "is immutable (chattr +i) and cannot be replaced"),
    ("gradient -o in immutable folder", ["gradient", *FLAT, "-o", "{d}/imm/g.exr"], "cannot write in folder"),
    ("gradient --preview immutable file", ["gradient", *FLAT, "-o", "{d}/g.exr", "--preview", "{d}/imm.png",
                                           "--overwrite"], "cannot be replaced"),
    ("reconstruct -o immutable file", ["reconstruct", "{d}/grad.exr", "-o", "{d}/imm.npy", "--overwrite"],
     "cannot be replaced"),
    ("invert -o in immutable folder", ["invert", *FLAT, "-o", "{d}/imm/h.exr"], "cannot write in folder"),
    ("calibrate -o immutable file", ["calibrate", "{d}/flat.exr", "--dh", "272", "--dw", "127", "-o",
                                     "{d}/imm.json", "--overwrite"], "cannot be replaced"),
    ("mesh -o immutable file", ["mesh", "{d}/hm.npy", "-o", "{d}/imm.ply", "--pixel-size", "0.05", "--overwrite"],
     "cannot be replaced"),
    ("new-scene immutable file", ["new-scene", "{d}/imm.xml", "--overwrite"], "cannot be replaced"),
    ("reflectance-map --data immutable", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.png", "--data",
                                          "{d}/imm.npz", "--overwrite"], "cannot be replaced"),
    ("benchmark --out immutable file", ["benchmark", "--out", "{d}/imm.md", "--overwrite"], "cannot be replaced"),
    ("validate --output-dir immutable", ["validate", "--quick", "--output-dir", "{d}/imm/report"],
     "cannot write in folder"),
]


@pytest.mark.parametrize("argv,fragment", [c[1:] for c in IMMUTABLE_CASES], ids=[c[0] for c in IMMUTABLE_CASES])
def test_immutable_folders_and_files_are_refused_before_the_work(d, capsys, argv, fragment):
    if not CHATTR["ok"]:
        pytest.skip("chattr +i is not available here (file system or privileges)")
    _refused(capsys, d, argv, fragment)


# -- class 6: nothing overwritten without asking -------------------------------------------------
OVERWRITE_CASES = [
    ("benchmark --out exists", ["benchmark", "--out", "{d}/exists.md"], "--out {d}/exists.md exists; pass --overwrite"),
    ("benchmark --out exists quick", ["benchmark", "--quick", "--only", "presets", "--out", "{d}/exists.md"],
     "exists; pass --overwrite"),
    ("validate --json exists", ["validate", "--quick", "--output-dir", "{d}/v", "--json", "{d}/exists.json"],
     "exists; pass --overwrite"),
    ("reflectance-map --data exists", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.png", "--data",
                                       "{d}/exists.npz"], "exists; pass --overwrite"),
    ("new-scene exists", ["new-scene", "{d}/exists.xml"], "exists; pass --overwrite"),
]


@pytest.mark.parametrize("argv,fragment", [c[1:] for c in OVERWRITE_CASES], ids=[c[0] for c in OVERWRITE_CASES])
def test_nothing_is_overwritten_without_asking(d, capsys, argv, fragment):
    _refused(capsys, d, argv, fragment.format(d=d))


def test_benchmark_default_out_is_not_replaced_either(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "RESULTS-quick.md").write_bytes(SENTINEL)
    _refused(capsys, tmp_path, ["benchmark", "--quick"], "--out RESULTS-quick.md exists; pass --overwrite")
