"""elo-mitsuba: electron-optical imaging in PBF-EB as physically based rendering.

The package is layered as the pipeline is:

* :mod:`elo_mitsuba.physics` -- the paper's equations as pure numpy functions;
* :mod:`elo_mitsuba.plugins` -- thin Mitsuba plugins (BSDF ``elo_bse``, sensor ``elo_beam``,
  integrator ``elo``) built on them;
* :mod:`elo_mitsuba.render` -- load a scene, render the detector images, write EXR;
* :mod:`elo_mitsuba.analysis` -- STSA correction, gradients (Eq. 26), height maps, design tools;
* :mod:`elo_mitsuba.cli` -- the ``elo-mitsuba`` command, thin over all of the above.

Importing the package does not touch Mitsuba's JIT; the LLVM check and the variant choice happen
at the first render (:func:`elo_mitsuba.runtime.ensure_variant`).
"""

__version__ = "0.1.0"

from .errors import EloEnvironmentError, EloError, EloInputError  # noqa: E402
from .runtime import ensure_variant  # noqa: E402
from .render import EloScene, RenderResult, load_scene, render  # noqa: E402


def _install_callback_if_mitsuba_loaded():
    """If the user already imported mitsuba, register plugins on their variant changes too."""
    import sys

    if "mitsuba" in sys.modules:
        from . import runtime

        runtime.install_variant_callback()
        runtime.register_plugins()


_install_callback_if_mitsuba_loaded()

__all__ = [
    "EloEnvironmentError", "EloError", "EloInputError", "EloScene", "RenderResult", "ensure_variant",
    "load_scene", "render", "__version__",
]
