"""Where a number was measured: machine, software and source state, for the headers of
reports (``validation/REPORT.md``, ``benchmarks/RESULTS.md``). Read-only: git is only queried.
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
from pathlib import Path


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=20,
                             stdin=subprocess.DEVNULL)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def source_state(root: str | Path) -> dict:
    """``commit`` (hash, or a sentence where ``root`` is not a git checkout) and ``state``
    ('clean' or how many tracked files are modified and untracked files exist)."""
    root = Path(root)
    commit = _git(root, "rev-parse", "HEAD")
    if commit is None:
        return {"commit": "unknown (not a git checkout)", "state": "unknown"}
    changed = [ln for ln in (_git(root, "diff-index", "--name-only", "HEAD") or "").splitlines() if ln]
    untracked = [ln for ln in (_git(root, "ls-files", "--others", "--exclude-standard") or "").splitlines() if ln]
    state = "clean" if not (changed or untracked) else f"{len(changed)} modified, {len(untracked)} untracked files"
    return {"commit": commit, "state": state}


def _first_field(path: str, key: str) -> str | None:
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(key):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def machine() -> dict:
    """``cpu`` (model name), ``cores`` (usable by this process), ``mem_gib`` (total RAM, or
    None), ``load`` (1/5/15-minute load averages, or None), ``system``."""
    cpu = _first_field("/proc/cpuinfo", "model name") or platform.processor() or "unknown"
    mem = _first_field("/proc/meminfo", "MemTotal")
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count()
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    return {"cpu": cpu, "cores": cores, "mem_gib": int(mem.split()[0]) / 2**20 if mem else None,
            "load": load, "system": f"{platform.system()} {platform.machine()}"}


def software() -> dict:
    """Versions of Python, numpy, Mitsuba (and the active variant), Dr.Jit, LLVM, elo-mitsuba."""
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    from ._version import __version__

    try:
        llvm = ".".join(map(str, dr.detail.llvm_version()))
    except Exception:  # noqa: BLE001 - no LLVM backend loaded: say so, do not fail a report
        llvm = "?"
    return {"elo_mitsuba": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "mitsuba": mi.__version__, "variant": mi.variant(), "drjit": dr.__version__, "llvm": llvm}


def utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
