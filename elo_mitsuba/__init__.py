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
actionable line instead of the abort that Debian 12's LLVM 15/16 would cause.
"""

from ._version import __version__  # noqa: E402
from .errors import EloEnvironmentError, EloError, EloInputError  # noqa: E402
from .runtime import ensure_variant  # noqa: E402
from .render import EloScene, RenderResult, load_scene, render  # noqa: E402
from .sweeps import sweep  # noqa: E402  (Dask, xarray, Zarr are imported when it runs)


def _hook_mitsuba():
    """Import Mitsuba and register our plugins on every switch to a supported variant.

    Then ``mi.set_variant(...)`` works before or after ``import elo_mitsuba``. Nothing is
    compiled here: the LLVM check runs in :func:`ensure_variant`, at the first render.
    """
    from . import runtime

    runtime.import_backend()
    runtime.install_variant_callback()
    runtime.register_plugins()


_hook_mitsuba()

__all__ = [
    "EloEnvironmentError", "EloError", "EloInputError", "EloScene", "RenderResult", "ensure_variant",
    "load_scene", "render", "sweep", "__version__",
]
