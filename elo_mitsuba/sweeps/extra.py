"""The optional dependencies of the sweeps (the ``sweep`` extra): Dask, distributed, xarray, Zarr.

``import elo_mitsuba`` works without them; a sweep, or a plot of its store, that finds one
missing stops in one line naming it and the command that installs the extra.
"""

from __future__ import annotations

import importlib.util

from ..errors import EloEnvironmentError

#: What a sweep imports: the cluster (dask, distributed) and the store (xarray, zarr).
SWEEP_MODULES = ("dask", "distributed", "xarray", "zarr")
#: What reading a sweep's store imports (xarray opens Zarr stores as Dask arrays).
STORE_MODULES = ("dask", "xarray", "zarr")
#: The command that installs them.
INSTALL = "python3 -m pip install 'elo-mitsuba[sweep]'"


def _importable(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):  # a finder that refuses it, or a module without a spec
        return False


def require(what: str, modules=SWEEP_MODULES) -> None:
    """Raise :class:`~elo_mitsuba.errors.EloEnvironmentError` (one line) unless ``modules`` can be
    imported.

    Parameters
    ----------
    what : str
        What needs them, for the message (``"elo-mitsuba sweep"``).
    modules : tuple of str
        The top-level modules needed.
    """
    missing = [name for name in modules if not _importable(name)]
    if missing:
        raise EloEnvironmentError(
            f"{what} needs the optional packages {', '.join(modules)} ({', '.join(missing)} missing): "
            f"install them with {INSTALL} (in a checkout: python3 -m pip install -e '.[sweep]')")
