"""Design sweeps: many renders of one scene over a grid of parameters, on this machine or a Dask
cluster, into one Zarr store readable by ``xarray.open_zarr``.

* :mod:`.spec`    the TOML spec, validated before any render (:func:`load_spec`), and
  :func:`dimension_name`, the store's name of a swept key (``right.radius`` -> ``right_radius``,
  so that ``ds.sel(right_radius=25)``);
* :mod:`.validate` every point's values checked against the scene, without rendering;
* :mod:`.cost`    the sweep's estimate (time, memory, store size); unbounded work refused;
* :mod:`.claims`  per-point claims: two clients resuming one store never render a point twice;
* :mod:`.metrics` the design metrics computed on the workers (a registry);
* :mod:`.store`   the Zarr layout, per-point status, resume;
* :mod:`.worker`  what a worker does: load once, re-render in place, write its own point;
* :mod:`.run`     the client: cluster, tasks, progress (:func:`sweep`);
* :mod:`.plot`    a metric over one or two swept parameters (:func:`plot_metric`);
* :mod:`.extra`   the optional packages a sweep needs (the ``sweep`` extra), checked first.

Dask, distributed, xarray and Zarr are the extra ``sweep`` (``pip install 'elo-mitsuba[sweep]'``),
imported inside the functions that use them: importing ``elo_mitsuba`` neither needs them nor
pays for them.
"""

from .metrics import GRADIENT_METHODS, METRICS, register_gradient_method
from .plot import plot_metric
from .run import SweepSummary, sweep
from .spec import SweepSpec, dimension_name, load_spec

__all__ = ["GRADIENT_METHODS", "METRICS", "SweepSpec", "SweepSummary", "dimension_name", "load_spec",
           "plot_metric", "register_gradient_method", "sweep"]
