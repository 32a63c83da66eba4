"""Shared fixtures of the test suite.

* ``mi``: Mitsuba with our variant set and our plugins registered (``elo_mitsuba.ensure_variant``),
  once per session;
* ``run_python``: run a Python snippet (or ``-m module ...``) in a fresh interpreter, so that
  environment and variant state do not leak between tests; returns ``CompletedProcess``;
* ``make_bsdf``: load an ``elo_bse`` BSDF with the given parameters;
* ``background_run``: the result of a command that was started in its own process when the
  collection finished (:data:`BACKGROUND`), so that it runs beside the other tests.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

#: Variables that select the LLVM library or the variant; removed from the environment of
#: subprocess tests unless a test sets them on purpose.
_ENV_KNOBS = ("DRJIT_LIBLLVM_PATH", "ELO_MITSUBA_VARIANT")


#: Long, self-contained subprocess runs that the tests of one module check: started when the
#: collection ends (if that module's tests are selected), so that they overlap the rest of the
#: suite. The suite keeps one of the two cores busy most of the time (Dr.Jit compiles a kernel on
#: one thread; most tests are small renders), so the validation's quick run (~1 min) and the
#: golden cases (~12 s) cost little wall time beside it. name -> (test module, a file it needs, argv after ``python`` with
#: ``{out}`` for a fresh temporary folder).
BACKGROUND = {
    "validation-quick": ("test_validation_quick.py", REPO_ROOT / "validation" / "runner.py",
                         ["-m", "validation", "--quick", "--output-dir", "{out}", "--json", "{out}/rows.json"]),
    "golden": ("test_golden.py", REPO_ROOT / "tests" / "golden_cases.py",
               ["tests/golden_cases.py", "--digests", "{out}/digests.json"]),
    "golden-other-isa": ("test_golden.py", REPO_ROOT / "tests" / "golden_cases.py",
                         ["tests/golden_cases.py", "--digests", "{out}/digests.json", "--other-isa"]),
}


def _environment(extra: dict | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in _ENV_KNOBS}
    env.update(extra or {})
    return env


def pytest_addoption(parser):
    parser.addoption("--other-isa", action="store_true",
                     help="compile this process's Dr.Jit kernels for AVX2 instead of the host's widest vectors "
                          "(golden_cases.OTHER_ISA: 8 lanes on an AVX-512 host, 4 on an AVX2 one): another "
                          "CPU's rounding on this machine, to check that no tolerance depends on the host")


def pytest_configure(config):
    if not config.getoption("--other-isa", default=False):
        return
    import platform

    from golden_cases import OTHER_ISA, llvm_target, set_llvm_target

    width = llvm_target()["vector_width"]
    if platform.machine() not in ("x86_64", "AMD64") or width not in OTHER_ISA:
        raise pytest.UsageError(f"--other-isa: an x86-64 host with {' or '.join(map(str, OTHER_ISA))}-lane vectors "
                                f"is needed (this one: {platform.machine()}, {width} lanes)")
    set_llvm_target(*OTHER_ISA[width])


def same_isa_as_subprocesses(request) -> None:
    """Skip a test that compares this process's renders bit for bit with another process's (a Dask
    worker's): under --other-isa only this process compiles for the other instruction set."""
    if request.config.getoption("--other-isa", default=False):
        pytest.skip("--other-isa switches this process's instruction set, not its worker processes'")


def pytest_collection_finish(session):
    started = session.config.stash.setdefault(_BACKGROUND_KEY, {})
    modules = {Path(str(item.fspath)).name for item in session.items}
    for name, (module, needs, argv) in BACKGROUND.items():
        if module not in modules or name in started or not needs.is_file():
            continue
        out = Path(tempfile.mkdtemp(prefix=f"elo-{name}-"))
        log = open(out / "output.log", "w+")
        proc = subprocess.Popen([sys.executable, *[a.format(out=out) for a in argv]], cwd=REPO_ROOT,
                                env=_environment(), stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        started[name] = (proc, out, log)


def pytest_unconfigure(config):
    for proc, out, log in config.stash.get(_BACKGROUND_KEY, {}).values():
        if proc.poll() is None:  # a test run stopped early (-x, Ctrl-C): do not leave it running
            proc.kill()
            proc.wait()
        log.close()
        shutil.rmtree(out, ignore_errors=True)


_BACKGROUND_KEY = pytest.StashKey[dict]()


@pytest.fixture(scope="session")
def background_run(request):
    def result(name: str, timeout: float = 600.0):
        """(exit status, output, folder) of the background run ``name``; waits for it."""
        started = request.config.stash.get(_BACKGROUND_KEY, {})
        if name not in started:
            pytest.fail(f"background run {name!r} was not started (is its module collected?)")
        proc, out, log = started[name]
        proc.wait(timeout=timeout)
        log.seek(0)
        return proc.returncode, log.read(), out

    return result


@pytest.fixture(scope="session")
def mi():
    import elo_mitsuba

    return elo_mitsuba.ensure_variant()


@pytest.fixture(scope="session")
def run_python():
    def run(*args: str, env: dict | None = None, timeout: float = 120.0, code: str | None = None):
        """Run ``python <args>`` (or ``python -c code``) from the repository root."""
        full_env = _environment(env)
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


def raw_exr(path, channels, header_json: str) -> None:
    """An EXR written past write_exr's checks (NaN pixels, any header text), as other tools may."""
    import numpy as np
    import OpenEXR

    header = {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage, "elo_mitsuba": header_json}
    with OpenEXR.File(header, {k: np.asarray(v, np.float32) for k, v in channels.items()}) as f:
        f.write(str(path))


def one_line_error(call) -> str:
    """The message of the EloInputError that ``call()`` raises, checked to be one line."""
    from elo_mitsuba import EloInputError

    with pytest.raises(EloInputError) as err:
        call()
    message = str(err.value)
    assert "\n" not in message, message
    return message
