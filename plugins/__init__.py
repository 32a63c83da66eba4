"""Mitsuba plugins of elo-mitsuba (installed as ``elo_mitsuba.plugins``).

One module per concept, each thin over :mod:`elo_mitsuba.physics`:

* ``elo_bse``  (BSDF, :mod:`.bsdf_elo_bse`): g_BSE of Eq. 13;
* ``elo_beam`` (sensor, :mod:`.sensor_elo_beam`): the scanned electron gun;
* ``elo``      (integrator, :mod:`.integrator_elo`): the multi-event detector integrator.

The modules define classes deriving from variant-specific Mitsuba types, so they can only be
imported after a variant is set; :func:`register_all` is called by
:func:`elo_mitsuba.runtime.ensure_variant` and by a variant-change callback.
"""

import importlib
import sys

#: (module, registration function name, plugin name)
PLUGINS = (
    ("bsdf_elo_bse", "register_bsdf", "elo_bse"),
    ("sensor_elo_beam", "register_sensor", "elo_beam"),
    ("integrator_elo", "register_integrator", "elo"),
)


def register_all() -> None:
    """(Re-)import the plugin modules for the active variant and register their classes."""
    import mitsuba as mi

    for module_name, register_fn, plugin_name in PLUGINS:
        qualified = f"{__name__}.{module_name}"
        if qualified in sys.modules:
            # after a variant switch the classes must derive from the new variant's base types
            module = importlib.reload(sys.modules[qualified])
        else:
            module = importlib.import_module(qualified)
        getattr(mi, register_fn)(plugin_name, module.PLUGIN_CLASS)
