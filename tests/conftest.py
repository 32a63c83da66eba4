"""Shared fixtures of the test suite.

* ``mi``: Mitsuba with our variant set and our plugins registered (``elo_mitsuba.ensure_variant``),
  once per session;
* ``run_python``: run a Python snippet (or ``-m module ...``) in a fresh interpreter, so that
  environment and variant state do not leak between tests; returns ``CompletedProcess``;
* ``make_bsdf``: load an ``elo_bse`` BSDF with the given parameters.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

#: Variables that select the LLVM library or the variant; removed from the environment of
#: subprocess tests unless a test sets them on purpose.
_ENV_KNOBS = ("DRJIT_LIBLLVM_PATH", "ELO_MITSUBA_VARIANT")


@pytest.fixture(scope="session")
def mi():
    import elo_mitsuba

    return elo_mitsuba.ensure_variant()


@pytest.fixture(scope="session")
def run_python():
    def run(*args: str, env: dict | None = None, timeout: float = 120.0, code: str | None = None):
        """Run ``python <args>`` (or ``python -c code``) from the repository root."""
        full_env = {k: v for k, v in os.environ.items() if k not in _ENV_KNOBS}
        full_env.update(env or {})
        cmd = [sys.executable]
        cmd += ["-c", code] if code is not None else list(args)
        return subprocess.run(
            cmd, cwd=REPO_ROOT, env=full_env, capture_output=True, text=True, timeout=timeout,
            stdin=subprocess.DEVNULL,
        )

    return run


@pytest.fixture(scope="session")
def make_bsdf(mi):
    def make(material: str | None = None, lobe: bool | None = None, lobe_width: float | None = None):
        d = {"type": "elo_bse"}
        if material is not None:
            d["material"] = material
        if lobe is not None:
            d["lobe"] = lobe
        if lobe_width is not None:
            d["lobe_width"] = float(lobe_width)
        return mi.load_dict(d)

    return make
