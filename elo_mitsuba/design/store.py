"""The optimiser's store: every evaluated design, in one Zarr store that xarray opens.

``OUT.zarr`` holds the dataset (dimension ``design``, one per evaluated trial; ``slot`` per
detector; the metrics, the constraint violations, ``feasible``, ``pareto``, the design parameters
and the discs' ``disc_center``, ``disc_normal``, ``disc_radius`` per slot) and, under ``OUT.zarr/.optimize/``, what a
resumed run needs: ``spec.json`` (the spec and its digest), ``evaluations.jsonl`` (one line per
evaluated design, flushed to disk before the optimiser is told: the truth the dataset is rebuilt
from) and ``journal.log`` (Optuna's journal storage: the optimiser's state).

A design of fewer detectors than the largest count has NaN in the slots it does not use, and an
asymmetric design's per-detector parameters are NaN beyond its count (attribute ``nan_means``).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from ..errors import EloInputError
from ..sweeps.store import zarr_path
from .geometry import CONSTRAINTS, design_discs

#: Folder of the resume state inside the store.
STATE = ".optimize"
#: The file a finished evaluation is appended to.
LOG = "evaluations.jsonl"


def state_dir(path) -> Path:
    """``OUT.zarr/.optimize``."""
    return Path(path) / STATE


def check_store(path, spec, *, overwrite: bool = False) -> str:
    """Check the output store before any work: ``"created"`` (new, its state folder made),
    ``"resumed"`` (the store of this same spec) or refused (one line). With ``overwrite`` an
    optimiser's store of another spec is replaced; a folder that is not an optimiser's store never is.

    Examples
    --------
    >>> import tempfile
    >>> from elo_mitsuba.design.spec import load_spec
    >>> with tempfile.TemporaryDirectory() as d:
    ...     s = load_spec({})
    ...     check_store(Path(d) / "a.zarr", s), check_store(Path(d) / "a.zarr", s)
    ('created', 'resumed')
    """
    path = zarr_path(path, "the optimiser")
    info = state_dir(path) / "spec.json"
    if path.exists():
        if not info.is_file():
            raise EloInputError(f"output {path} exists and is not an optimiser's store; choose another name")
        try:
            old = json.loads(info.read_text()).get("digest")
        except (OSError, ValueError):
            old = None
        if old == spec.digest():
            return "resumed"
        if not overwrite:
            raise EloInputError(f"output {path} holds a run of another spec (or changed settings); give another "
                                "name, or --overwrite to replace it")
        shutil.rmtree(path)
    state_dir(path).mkdir(parents=True)
    info.write_text(json.dumps({"digest": spec.digest(), "spec": spec.to_dict()}, indent=1))
    return "created"


def append_records(path, records) -> None:
    """Append evaluated designs (dicts) to the log, on disk before this returns."""
    with open(state_dir(path) / LOG, "a") as f:
        for r in records:
            f.write(json.dumps(r) + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_records(path) -> list[dict]:
    """The evaluated designs of the log (a line cut short by a kill is left out: not stored)."""
    log = state_dir(path) / LOG
    out = []
    if log.is_file():
        for line in log.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                continue
    return out


def pareto_mask(values, directions, feasible=None) -> np.ndarray:
    """Designs that no other feasible design dominates (all objectives at least as good, one better).

    Parameters
    ----------
    values : array_like (n, m)
        Objective values.
    directions : list of str
        ``minimize`` or ``maximize`` per objective.
    feasible : array_like of bool (n,), optional
        Only feasible designs can be on the front (default: all).

    Returns
    -------
    ndarray of bool (n,)

    Examples
    --------
    >>> pareto_mask([[1, 3], [2, 2], [3, 3], [0, 9]], ["minimize", "minimize"], [True, True, True, False]).tolist()
    [True, True, False, False]
    """
    v = np.asarray(values, float).reshape(len(values), -1) * np.array(
        [1.0 if d == "minimize" else -1.0 for d in directions])
    ok = np.ones(len(v), bool) if feasible is None else np.asarray(feasible, bool)
    le = np.all(v[None, :, :] <= v[:, None, :], axis=-1)  # [i, j]: j at least as good as i everywhere
    lt = np.any(v[None, :, :] < v[:, None, :], axis=-1)
    dominated = np.any(le & lt & ok[None, :], axis=1)
    return ok & ~dominated


def records_dataset(records, spec):
    """The xarray Dataset of evaluated designs (see the module's description)."""
    import xarray as xr

    records = sorted(records, key=lambda r: r["trial"])
    n, slots = len(records), max(spec.counts)
    metric_names = sorted({k for r in records for k in r["metrics"]})
    pnames = spec.parameter_names(slots)
    data = {k: ("design", np.array([r["metrics"].get(k, np.nan) for r in records], float)) for k in metric_names}
    for c in CONSTRAINTS:
        data[f"violation_{c}"] = ("design", np.array([r["violations"][c] for r in records], float))
    feasible = np.array([r["feasible"] for r in records], bool)
    data["feasible"] = ("design", feasible)
    data["count"] = ("design", np.array([r["count"] for r in records], int))
    data["seconds"] = ("design", np.array([r["seconds"] for r in records], float))
    for p in pnames:
        data[p] = ("design", np.array([r["params"].get(p, np.nan) for r in records], float))
    centers = np.full((n, slots, 3), np.nan)
    normals = np.full((n, slots, 3), np.nan)
    radii = np.full((n, slots), np.nan)
    for i, r in enumerate(records):
        for k, d in enumerate(design_discs(r["params"], r["count"], spec.symmetric).values()):
            centers[i, k], normals[i, k], radii[i, k] = d.center, d.normal, d.radius
    data["disc_center"] = (("design", "slot", "xyz"), centers)
    data["disc_normal"] = (("design", "slot", "xyz"), normals)
    data["disc_radius"] = (("design", "slot"), radii)
    values = np.array([[r["metrics"][o] for o in spec.objectives] for r in records], float).reshape(n, -1)
    data["pareto"] = ("design", pareto_mask(values, spec.directions, feasible) if n else np.zeros(0, bool))
    # xyz as 0, 1, 2 (x, y, z): zarr has no settled encoding of strings
    ds = xr.Dataset(data, coords={"design": np.array([r["trial"] for r in records], int),
                                  "slot": np.arange(slots), "xyz": np.arange(3)})
    ds.attrs.update({"objectives": list(spec.objectives), "directions": spec.directions,
                     "spec": json.dumps(spec.to_dict()), "digest": spec.digest(), "units": "mm, deg; sigma_*: slope units",
                     "nan_means": "no detector in this slot / no such parameter in this design"})
    return ds


def write_dataset(path, records, spec) -> None:
    """(Re)write the dataset of ``records`` into the store, leaving its state folder alone: written
    to a folder inside the state first, then moved into place entry by entry."""
    path = Path(path)
    tmp = state_dir(path) / "dataset.zarr"
    if tmp.exists():
        shutil.rmtree(tmp)
    records_dataset(records, spec).to_zarr(tmp, mode="w", consolidated=False)
    for entry in list(path.iterdir()):
        if entry.name != STATE:
            shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
    for entry in tmp.iterdir():
        os.replace(entry, path / entry.name)
    shutil.rmtree(tmp)


def read_designs(path):
    """The store's dataset, loaded (xarray)."""
    import warnings

    import xarray as xr

    with warnings.catch_warnings():
        # zarr notes the state folder (.optimize) as "not a component of a Zarr hierarchy"
        warnings.simplefilter("ignore")
        return xr.open_zarr(path, consolidated=False).load()
