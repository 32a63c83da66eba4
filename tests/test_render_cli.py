"""`elo-mitsuba render` end to end, and its answers to bad input (one line, exit 2, no EXR)."""

import subprocess
import sys

import numpy as np
import pytest

from elo_mitsuba.exr import read_exr


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "elo_mitsuba", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, timeout=600)


def test_render_shipped_flat_plate(tmp_path):
    out = tmp_path / "flat.exr"
    r = run("render", "flat_plate", "-o", out, "--resolution", 32, "--spp", 4)
    assert r.returncode == 0, r.stderr
    channels, meta = read_exr(out)
    assert {"right", "left", "back", "front"} <= set(channels)
    assert channels["right"].shape == (32, 32)
    assert meta["resolution"] == [32, 32] and meta["spp"] == 4
    # right detector brighter towards +x (last column)
    assert channels["right"][:, -4:].mean() > channels["right"][:, :4].mean()


def test_define_moves_detectors(tmp_path):
    out = tmp_path / "moved.exr"
    r = run("render", "flat_plate", "-o", out, "--resolution", 8, "--spp", 2, "-D", "dh=200", "-D", "dw=150")
    assert r.returncode == 0, r.stderr
    _, meta = read_exr(out)
    np.testing.assert_allclose(meta["detectors"]["right"]["center"], [150, 0, 200], atol=1e-3)
    np.testing.assert_allclose(meta["detectors"]["front"]["center"], [0, -150, 200], atol=1e-3)


def _bad_scene(tmp_path, body):
    path = tmp_path / "bad.xml"
    path.write_text(f'<scene version="3.0.0">{body}</scene>')
    return path


SENSOR = ('<sensor type="elo_beam"><film type="hdrfilm"><integer name="width" value="4"/>'
          '<integer name="height" value="4"/><rfilter type="box"/></film></sensor>')
PLATE = '<shape type="rectangle"><bsdf type="elo_bse"/></shape>'
DETECTOR = ('<shape type="disk" id="right"><transform name="to_world"><scale value="25"/>'
            '<lookat origin="127,0,{z}" target="0,0,0" up="0,0,1"/></transform><emitter type="area"/></shape>')


@pytest.mark.parametrize("case, args_or_xml, expected", [
    ("missing scene", ["render", "no_such_scene.xml"], "does not exist"),
    ("unknown shipped", ["render", "no_such_scene"], "neither an XML file nor a shipped scene"),
    ("malformed", "<scene><shape", "malformed XML"),
    ("unknown parameter", f'<integrator type="elo"/>{SENSOR}<shape type="rectangle"><bsdf type="elo_bse"><float name="colour" value="1"/></bsdf></shape>', "colour"),
    ("missing mesh", f'<integrator type="elo"/>{SENSOR}<shape type="ply"><string name="filename" value="nope.ply"/></shape>', "nope.ply"),
    ("no detectors", f'<integrator type="elo"/>{SENSOR}{PLATE}', "no detector"),
    ("detector below plate", f'<integrator type="elo"/>{SENSOR}{PLATE}{DETECTOR.format(z=-50)}', "below"),
    ("negative field", f'<integrator type="elo"/><sensor type="elo_beam"><float name="field" value="-5"/><film type="hdrfilm"><rfilter type="box"/></film></sensor>{PLATE}', "field=-5"),
    ("bad material", f'<integrator type="elo"/>{SENSOR}<shape type="rectangle"><bsdf type="elo_bse"><string name="material" value="Unobtainium"/></bsdf></shape>', "Unobtainium"),
    ("events 0", ["render", "flat_plate", "--events", "0"], "must be >= 1"),
    ("spp 0", ["render", "flat_plate", "--spp", "0"], "must be >= 1"),
    ("resolution 0", ["render", "flat_plate", "--resolution", "0"], "must be >= 1"),
    ("undeclared -D", ["render", "flat_plate", "-D", "colour=3"], "colour"),
    ("bad layout", ["render", "flat_plate", "--layout", "zeta33"], "zeta33"),
])
def test_bad_input_gives_one_clear_line(tmp_path, case, args_or_xml, expected):
    out = tmp_path / "out.exr"
    if isinstance(args_or_xml, str):
        args = ["render", _bad_scene(tmp_path, args_or_xml) if not args_or_xml.startswith("<scene") else _write(tmp_path, args_or_xml)]
    else:
        args = list(args_or_xml)
    r = run(*args, "-o", out)
    assert r.returncode == 2, (case, r.returncode, r.stderr[-1500:])
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and "WARN" not in ln and not ln.startswith("\x1b")]
    assert len(lines) == 1, (case, r.stderr)
    assert expected in lines[0], (case, lines[0])
    assert "Traceback" not in r.stderr
    assert not out.exists()


def _write(tmp_path, text):
    path = tmp_path / "malformed.xml"
    path.write_text(text)
    return path


def test_existing_output_is_not_overwritten(tmp_path):
    out = tmp_path / "keep.exr"
    out.write_bytes(b"user data")
    r = run("render", "flat_plate", "-o", out, "--resolution", 4, "--spp", 1)
    assert r.returncode == 2 and "exists" in r.stderr
    assert out.read_bytes() == b"user data"
    r = run("render", "flat_plate", "-o", out, "--resolution", 4, "--spp", 1, "--overwrite")
    assert r.returncode == 0, r.stderr
    assert read_exr(out)[0]["right"].shape == (4, 4)


def test_help_teaches():
    r = run("render", "--help")
    assert r.returncode == 0
    for word in ("N_d/N_0", "row 0", "--events", "-D", "examples"):
        assert word in r.stdout


def test_render_reports_what_each_event_adds(tmp_path):
    """A flat plate without chamber cannot scatter twice: the render says so, reports the event
    shares (e1 = 100 %) and that --events 1 would do."""
    out = tmp_path / "flat3.exr"
    r = run("render", "flat_plate", "-o", out, "--resolution", 16, "--spp", 2, "--events", 3)
    assert r.returncode == 0, r.stderr
    assert "e1 100.00% (100.00%), e2 0.00% (0.00%), e3 0.00% (0.00%)" in r.stderr
    assert "--events 1 gives the same images" in r.stderr
    assert "exactly zero" in r.stderr


def test_render_prints_and_stores_the_error_estimate(tmp_path):
    """Issue 10: every channel's estimated error is printed, stored in the header and, with
    --error-channels, written as <channel>.err; the 1st event by the quadrature is deterministic."""
    out = tmp_path / "corr.exr"
    r = run("render", "corrugated_chamber", "-o", out, "--resolution", 16, "-D", "field=10", "--error-channels")
    assert r.returncode == 0, r.stderr
    assert "estimated error per pixel" in r.stderr and "e1 deterministic (no sampling error)" in r.stderr
    assert "e2 " in r.stderr and "% RMS" in r.stderr
    channels, meta = read_exr(out)
    summary = meta["error_estimate"]["channels"]
    assert summary["right.e1"]["status"] == "deterministic" and np.all(channels["right.e1.err"] == 0)
    assert summary["right.e2"]["status"] == "estimated" and channels["right.e2.err"].max() > 0
    plain = tmp_path / "plain.exr"
    assert run("render", "flat_plate", "-o", plain, "--resolution", 8, "--quiet").returncode == 0
    assert not any(name.endswith(".err") for name in read_exr(plain)[0])


def test_halves_equal_to_rounding_read_deterministic():
    """Issue 24: a channel whose halves differ by float32 summation order only is reported as
    deterministic, not as '0.000244 %'."""
    from types import SimpleNamespace

    from elo_mitsuba.cli.render import error_lines

    rounding = {"status": "estimated", "rms_rel": 2.44e-6, "p99_rel": 4e-6, "rms_abs": 1e-9}
    noisy = {"status": "estimated", "rms_rel": 2e-3, "p99_rel": 6e-3, "rms_abs": 1e-4}
    result = SimpleNamespace(detectors=["right"], error_summary=lambda: {"right": rounding, "right.e2": noisy})
    lines = error_lines(result, "scene")
    assert "right: deterministic (the halves agree to float32 rounding)" in lines[1]
    assert "%" not in lines[1].split(";")[0] and "e2 0.2 % RMS" in lines[1]
