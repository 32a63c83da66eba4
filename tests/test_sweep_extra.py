"""Dask, distributed, xarray and Zarr are the optional extra ``sweep``: without them the package
imports and renders, and a sweep or a plot of its store stops in one line saying what to install.

Their absence is simulated in a fresh interpreter, by ``sys.modules[name] = None`` (the import is
refused) or by a meta path finder that finds no such module."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "examples" / "sweep_minimal.toml"

BLOCKED = """
import sys
for name in {names!r}:
    sys.modules[name] = None
"""

NOT_FOUND = """
import importlib.abc, sys
class _Absent(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {names!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None
sys.meta_path.insert(0, _Absent())
"""


def _python(code, cwd):
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd, timeout=120)


@pytest.mark.parametrize("how", [BLOCKED, NOT_FOUND], ids=["refused", "not-found"])
def test_the_package_imports_without_the_sweep_extra(how, tmp_path):
    code = how.format(names=("dask", "distributed", "xarray", "zarr")) + """
import elo_mitsuba, elo_mitsuba.sweeps
import elo_mitsuba.cli.sweep, elo_mitsuba.cli.sweep_plot
print(elo_mitsuba.sweep.__name__, elo_mitsuba.load_scene("flat_plate", res=2).render(spp=1).channels["right"].shape)
"""
    r = _python(code, tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "sweep (2, 2)"


@pytest.mark.parametrize("how", [BLOCKED, NOT_FOUND], ids=["refused", "not-found"])
def test_sweep_without_the_extra_says_what_to_install(how, tmp_path):
    code = how.format(names=("dask",)) + f"""
from elo_mitsuba.cli import main
sys.exit(main(["sweep", {str(SPEC)!r}, "-o", "out.zarr", "--workers", "0"]))
"""
    r = _python(code, tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and r.stdout == "", r.stderr
    assert "a sweep needs the optional packages dask, distributed, xarray, zarr (dask missing)" in r.stderr
    assert "pip install 'elo-mitsuba[sweep]'" in r.stderr
    assert not (tmp_path / "out.zarr").exists()


def test_sweep_plot_without_the_extra_says_what_to_install(tmp_path):
    code = BLOCKED.format(names=("xarray", "zarr")) + """
from elo_mitsuba.cli import main
sys.exit(main(["sweep-plot", "out.zarr", "signal_mean", "-o", "mean.png"]))
"""
    r = _python(code, tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "elo-mitsuba sweep-plot needs the optional packages dask, xarray, zarr (xarray, zarr missing)" in r.stderr
    assert "elo-mitsuba[sweep]" in r.stderr and not (tmp_path / "mean.png").exists()


def test_the_sweep_function_without_the_extra_raises_one_line(tmp_path):
    code = NOT_FOUND.format(names=("distributed",)) + f"""
import elo_mitsuba as em
try:
    em.sweep({str(SPEC)!r}, "out.zarr", workers=0)
except em.EloEnvironmentError as exc:
    print(exc)
"""
    r = _python(code, tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("\n") == 1 and "(distributed missing)" in r.stdout and "elo-mitsuba[sweep]" in r.stdout
