"""The software environment: LLVM check, variant choice and plugin registration.

Each test runs a fresh interpreter (fixture ``run_python``), so no Dr.Jit/Mitsuba state leaks.
Debian 12's LLVM 15/16 makes Mitsuba's llvm variants abort with SIGABRT; we must stop earlier with
an actionable one-line message and a normal non-zero exit status, never by a signal.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from elo_mitsuba.constants import SUPPORTED_VARIANTS

LLVM15 = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"
BAD_LLVM = [
    pytest.param("/nonexistent/libLLVM.so", id="missing-file"),
    pytest.param(LLVM15, id="llvm15", marks=pytest.mark.skipif(
        not os.path.exists(LLVM15), reason=f"{LLVM15} not installed")),
]
PLUGIN_FILE = Path(__file__).resolve().parents[1] / "plugins" / "bsdf_elo_bse.py"
needs_bsdf = pytest.mark.skipif(not PLUGIN_FILE.exists(), reason="plugins/bsdf_elo_bse.py missing")


def _assert_clean_failure(proc):
    """Non-zero exit by sys.exit/exception, not by a signal (negative code, or 134 = 128+SIGABRT)."""
    assert proc.returncode > 0, f"returncode {proc.returncode}; stderr:\n{proc.stderr}"
    assert proc.returncode not in (134, 139), f"killed by a signal; stderr:\n{proc.stderr}"
    assert "LLVM ERROR" not in proc.stderr


def _assert_actionable(text):
    assert "libllvm19" in text, text
    assert "DRJIT_LIBLLVM_PATH" in text, text


@pytest.mark.parametrize("libpath", BAD_LLVM)
def test_ensure_variant_refuses_unusable_llvm(run_python, libpath):
    proc = run_python(code="import elo_mitsuba; elo_mitsuba.ensure_variant()",
                      env={"DRJIT_LIBLLVM_PATH": libpath})
    _assert_clean_failure(proc)
    _assert_actionable(proc.stderr)
    assert "EloEnvironmentError" in proc.stderr


def _has_render(run_python) -> bool:
    proc = run_python("-m", "elo_mitsuba", "--help")
    return proc.returncode == 0 and "render" in proc.stdout


@pytest.mark.parametrize("libpath", BAD_LLVM)
def test_cli_render_refuses_unusable_llvm_in_one_line(run_python, libpath, tmp_path):
    if not _has_render(run_python):
        pytest.skip("the render sub-command does not exist yet")
    scene = tmp_path / "scene.xml"
    scene.write_text('<scene version="3.0.0"/>\n')
    proc = run_python("-m", "elo_mitsuba", "render", str(scene), "-o", str(tmp_path / "x.exr"),
                      env={"DRJIT_LIBLLVM_PATH": libpath})
    _assert_clean_failure(proc)
    lines = proc.stderr.splitlines()
    print(f"\nstderr with DRJIT_LIBLLVM_PATH={libpath}:\n{proc.stderr}")
    assert len(lines) == 1, f"expected exactly one line on stderr, got {len(lines)}:\n{proc.stderr}"
    assert lines[0].startswith("elo-mitsuba: error:")
    _assert_actionable(lines[0])
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "x.exr").exists()


def test_unsupported_variant_env_var(run_python):
    proc = run_python(code="import elo_mitsuba; elo_mitsuba.ensure_variant()",
                      env={"ELO_MITSUBA_VARIANT": "scalar_rgb"})
    _assert_clean_failure(proc)
    assert "scalar_rgb" in proc.stderr and "ELO_MITSUBA_VARIANT" in proc.stderr
    for name in SUPPORTED_VARIANTS:
        assert name in proc.stderr


def test_unsupported_variant_in_process():
    from elo_mitsuba.errors import EloInputError
    from elo_mitsuba.runtime import resolve_variant

    with pytest.raises(EloInputError, match="'llvm_ad_rgb' is not supported"):
        resolve_variant("llvm_ad_rgb")
    assert resolve_variant("cuda_ad_mono") == "cuda_ad_mono"


def test_cli_unsupported_variant_one_line(run_python, tmp_path):
    if not _has_render(run_python):
        pytest.skip("the render sub-command does not exist yet")
    scene = tmp_path / "scene.xml"
    scene.write_text('<scene version="3.0.0"/>\n')
    proc = run_python("-m", "elo_mitsuba", "render", str(scene), "-o", str(tmp_path / "x.exr"),
                      env={"ELO_MITSUBA_VARIANT": "scalar_rgb"})
    _assert_clean_failure(proc)
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and "scalar_rgb" in lines[0], proc.stderr


# --- plugin registration, whatever the import order ----------------------------------------------

_CHECK_BSDF = """
b = mi.load_dict({'type': 'elo_bse'})
assert isinstance(b, mi.BSDF), type(b)
si = mi.SurfaceInteraction3f(); si.wi = mi.Vector3f(0, 0, 1)
import numpy as np
v = np.array(b.eval(mi.BSDFContext(), si, mi.Vector3f(0, 0, 1))).ravel()
assert v.size == 1 and v[0] > 0, v
print('OK', mi.variant())
"""


@needs_bsdf
def test_register_import_package_then_set_variant(run_python):
    """(a) import elo_mitsuba, then the user sets the variant with Mitsuba's own API."""
    proc = run_python(code="import elo_mitsuba\nimport mitsuba as mi\nmi.set_variant('llvm_ad_mono')\n"
                      + _CHECK_BSDF)
    assert proc.returncode == 0 and "OK llvm_ad_mono" in proc.stdout, proc.stderr[-2000:]


@needs_bsdf
def test_register_set_variant_then_import_package(run_python):
    """(b) mi.set_variant first, then import elo_mitsuba."""
    proc = run_python(code="import mitsuba as mi\nmi.set_variant('llvm_ad_mono')\nimport elo_mitsuba\n"
                      + _CHECK_BSDF)
    assert proc.returncode == 0 and "OK llvm_ad_mono" in proc.stdout, proc.stderr[-2000:]


@needs_bsdf
def test_register_after_variant_switch(run_python):
    """(c) scalar_rgb -> llvm_ad_mono re-registers; and llvm -> scalar -> llvm gives classes of the
    active variant (not stale ones from the first registration)."""
    code = ("import mitsuba as mi\nimport elo_mitsuba\nmi.set_variant('scalar_rgb')\n"
            "mi.set_variant('llvm_ad_mono')\n" + _CHECK_BSDF)
    proc = run_python(code=code)
    assert proc.returncode == 0 and "OK llvm_ad_mono" in proc.stdout, proc.stderr[-2000:]
    code = ("import elo_mitsuba\nmi = elo_mitsuba.ensure_variant()\n" + _CHECK_BSDF
            + "mi.set_variant('scalar_rgb')\nmi.set_variant('llvm_ad_mono')\n" + _CHECK_BSDF)
    proc = run_python(code=code)
    assert proc.returncode == 0 and proc.stdout.count("OK llvm_ad_mono") == 2, proc.stderr[-2000:]


@needs_bsdf
def test_ensure_variant_registers(run_python):
    proc = run_python(code="import elo_mitsuba\nmi = elo_mitsuba.ensure_variant()\n" + _CHECK_BSDF)
    assert proc.returncode == 0 and "OK llvm_ad_mono" in proc.stdout, proc.stderr[-2000:]
