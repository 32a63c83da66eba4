"""elo-mitsuba: electron-optical imaging in PBF-EB as physically based rendering.

The package is layered as the pipeline is:

* :mod:`elo_mitsuba.physics` -- the paper's equations as pure numpy functions;
* :mod:`elo_mitsuba.plugins` -- thin Mitsuba plugins (BSDF ``elo_bse``, sensor ``elo_beam``,
  integrator ``elo``) built on them;
* :mod:`elo_mitsuba.render` -- load a scene, render the detector images, write EXR;
* :mod:`elo_mitsuba.analysis` -- STSA correction, gradients (Eq. 26), height maps, design tools;
* :mod:`elo_mitsuba.sweeps` -- design sweeps on one machine or a Dask cluster, into Zarr;
* :mod:`elo_mitsuba.cli` -- the ``elo-mitsuba`` command, thin over all of the above.

Importing the package imports Mitsuba but compiles nothing; the LLVM check and the variant choice
happen at the first render (:func:`elo_mitsuba.runtime.ensure_variant`), which stops with one
actionable line instead of the abort that Debian 12's LLVM 15/16 would cause. The ``elo-mitsuba``
command itself does not import Mitsuba until a sub-command needs it (a rejected argument costs
a fraction of a second; ``gradient`` and ``reconstruct`` never load it).
"""

import os as _os
import sys as _sys


def _cli_process() -> bool:
    """True when this interpreter runs the ``elo-mitsuba`` command (console script, or
    ``python -m elo_mitsuba``, during whose import ``sys.argv[0]`` is ``-m``): no user code can set
    a variant there, and :func:`ensure_variant` does the hooking when a command needs Mitsuba."""
    argv0 = _sys.argv[0] if _sys.argv else ""
    return _os.path.basename(argv0) in ("elo-mitsuba", "elo-mitsuba.exe") or (
        argv0 == "-m" and "mitsuba" not in _sys.modules)


if _cli_process() and "numpy" not in _sys.modules:
    # numpy's OpenBLAS threads spin for a while after each matrix product (the bounce filter's
    # interpolation), on the cores Dr.Jit's next kernel needs: 4-5 % of a command's CPU time on
    # 2 cores. The command's products are small; with one thread they give the same bits.
    _os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ._version import __version__  # noqa: E402
from .errors import EloEnvironmentError, EloError, EloInputError  # noqa: E402
from .runtime import ensure_variant  # noqa: E402
from .render import EloScene, RenderResult, load_scene, render  # noqa: E402


def __getattr__(name):
    # the sweep client (and its imports: 50 ms) only when it is used; Dask, xarray and Zarr are
    # imported when it runs
    if name == "sweep":
        from .sweeps import sweep

        return sweep
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _hook_mitsuba():
    """Import Mitsuba and register our plugins on every switch to a supported variant.

    Then ``mi.set_variant(...)`` works before or after ``import elo_mitsuba``. Nothing is
    compiled here: the LLVM check runs in :func:`ensure_variant`, at the first render.
    """
    from . import runtime

    runtime.import_backend()
    runtime.install_variant_callback()
    runtime.register_plugins()


if not _cli_process() or "mitsuba" in _sys.modules:
    _hook_mitsuba()

__all__ = [
    "EloEnvironmentError", "EloError", "EloInputError", "EloScene", "RenderResult", "ensure_variant",
    "load_scene", "render", "sweep", "__version__",
]
