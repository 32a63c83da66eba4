"""The sweep's output: one Zarr store (format 2: stable, read by ``xarray.open_zarr`` and by any
Zarr library), preallocated on the client and filled point by point by the workers.

Layout: dimensions = the sweep's axes (+ ``detector`` for per-detector metrics, + ``y``, ``x`` for
images), each named by :func:`.spec.dimension_name`, a Python identifier: the spec's
``right.radius`` is the dimension ``right_radius`` (``ds.sel(right_radius=25)``), its ``long_name``
the spec key; a ``[zip.NAME]`` group is the dimension ``NAME`` (0, 1, ...) with one coordinate per
member; a ``center``/``normal`` move has its labels ``"(127, 0, 272)"`` as the coordinate and the
vectors as ``<name>_xyz`` (dimension ``xyz``). Chunks of one point along every axis, so that each
point writes its own chunks and workers never write the same file. Variables:

* ``status`` (int8): 0 = not done, 1 = done, 2 = failed (``error`` holds the one-line reason);
  written *after* the point's data, so a worker killed half-way leaves 0 and the point is redone;
* one variable per metric (``signal_mean`` ...) and per kept channel (``image_<channel>``);
* ``render_seconds``, ``worker_rss_mb``, ``worker_cpu_s``, ``finished_at``, ``worker``: what each point
  cost, when and where it ran.

Attributes: the spec (TOML text, parsed form and digest), the scan geometry, the package version.

Stores written before the dimensions were identifiers (``right.radius``) resume unchanged (the
digest is the spec's, and points are written by index); :func:`.plot.plot_metric` reads them with
their names mapped by :func:`.spec.dimension_name`.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import EloInputError
from ..files import check_parent_folder

STATUS_PENDING, STATUS_DONE, STATUS_FAILED = 0, 1, 2
#: Longest error text kept per point (fixed-width strings: Zarr 2 stores them natively).
ERROR_CHARS = 240
#: Longest worker name kept per point.
WORKER_CHARS = 64
ZARR_FORMAT = 2
#: The store's own dimensions and variables (besides the metrics and ``image_<channel>``): no swept
#: name may take one (checked when the spec is parsed).
RESERVED_NAMES = ("detector", "x", "y", "xyz", "status", "error", "worker", "render_seconds", "worker_rss_mb",
                  "worker_cpu_s", "finished_at")


def image_variable(channel: str) -> str:
    return f"image_{channel}"


def zarr_path(path, writer: str) -> Path:
    """``path`` as a Path if it names a ``*.zarr`` store in an existing folder that takes new files
    (:func:`~elo_mitsuba.files.check_parent_folder`; ``writer`` says who writes it, for the
    message); else one line.

    Examples
    --------
    >>> zarr_path("out.zarr", "a sweep").name
    'out.zarr'
    """
    if not isinstance(path, (str, os.PathLike)) or not str(path):
        raise EloInputError(f"output {path!r}: give the path of a .zarr store (a string or Path)")
    path = Path(path)
    if path.suffix.lower() != ".zarr":
        raise EloInputError(f"output {path}: {writer} writes a Zarr store; the name must end in .zarr")
    if path.exists() and not path.is_dir():
        raise EloInputError(f"output {path} is a file; {writer} writes a Zarr store (a folder): choose another name")
    check_parent_folder(path, "output")  # missing, a file, or taking no new files (/proc): one line, before any work
    return path


def check_store_path(path, *, overwrite: bool = False) -> Path:
    """The output store: ``*.zarr``, in an existing folder; an existing path must be a Zarr
    store (it is then resumed, or replaced with ``overwrite``), never a user's other folder."""
    path = zarr_path(path, "a sweep")
    if path.exists() and not (path / ".zgroup").is_file():
        raise EloInputError(f"output {path} exists and is not a sweep's Zarr store; choose another name")
    return path


def open_or_create(path, spec, layout: dict, *, overwrite: bool = False) -> str:
    """Create the store for ``spec`` or check that an existing one was made by the same spec.

    Returns ``"created"``, ``"resumed"`` or ``"joined"`` (another client created the same
    sweep's store while this one prepared it: exactly one creates it, the other resumes it);
    raises EloInputError for a store of another spec (unless ``overwrite``, which replaces it).

    The store is built in a private folder next to ``path`` and renamed into place: ``rename``
    onto an existing non-empty folder fails, so creation is exclusive, and an interrupted creation
    never leaves a half-made store behind."""
    path = check_store_path(path, overwrite=overwrite)
    if path.exists():
        if not overwrite:
            _check_same_spec(path, spec)
            return "resumed"
        shutil.rmtree(path)
    tmp = path.with_name(f".{path.name}.creating-{os.getpid()}-{time.time_ns()}")
    try:
        _create(tmp, spec, layout)
        os.rename(tmp, path)
    except OSError as exc:
        if not (path / ".zgroup").is_file():
            raise EloInputError(f"output {path}: cannot create the store ({exc.strerror or exc})") from None
        _check_same_spec(path, spec, meanwhile=True)  # another client won the race
        return "joined"
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return "created"


def _check_same_spec(path: Path, spec, meanwhile: bool = False) -> None:
    attrs = _attrs(path)
    if attrs.get("elo_sweep_digest") != spec.digest():
        made = "was created meanwhile by another client for" if meanwhile else "holds a sweep of"
        raise EloInputError(
            f"output {path} {made} another spec (digest {attrs.get('elo_sweep_digest')}, this spec "
            f"{spec.digest()}); resuming needs the same spec: choose another -o, or --overwrite to replace it")


def _attrs(path: Path) -> dict:
    try:
        return json.loads((path / ".zattrs").read_text())
    except (OSError, ValueError):
        return {}


def _create(path: Path, spec, layout: dict) -> None:
    import dask.array as da
    import xarray as xr

    axes = [a.dim for a in spec.axes]
    shape = spec.shape
    one = (1,) * len(axes)
    coords = _coordinates(spec)
    data = {}
    encoding = {}

    def lazy(name, dims_extra, sizes_extra, dtype, attrs):
        data[name] = xr.Variable(axes + dims_extra, da.full(shape + sizes_extra, np.nan, dtype=dtype,
                                                             chunks=one + sizes_extra), attrs)
        encoding[name] = {"chunks": one + sizes_extra}

    from .metrics import SIGNAL_UNITS

    for name, m in layout["metrics"].items():
        units = layout["units"] if m.units == SIGNAL_UNITS else m.units  # the render's own label
        if m.per_detector:
            lazy(name, ["detector"], (len(layout["detectors"]),), np.float64,
                 {"units": units, "description": m.description})
        else:
            lazy(name, [], (), np.float64, {"units": units, "description": m.description})
    h, w = layout["image_shape"]
    for ch in layout["channels"]:
        lazy(image_variable(ch), ["y", "x"], (h, w), np.float32,
             {"units": layout["units"], "description": f"detector channel {ch} (box-averaged "
              f"{spec.downsample}x{spec.downsample})" if spec.downsample > 1 else f"detector channel {ch}"})
    lazy("render_seconds", [], (), np.float32, {"units": "s", "description": "render time on the worker (with the flat reference)"})
    lazy("worker_rss_mb", [], (), np.float32, {"units": "MB", "description": "worker's resident memory after the point"})
    lazy("finished_at", [], (), np.float64, {"units": "s", "description": "when the point was stored (Unix time)"})
    lazy("worker_cpu_s", [], (), np.float64, {"units": "s", "description": "CPU time of the worker process (all "
                                              "threads) when the point was stored: differences = cost per point"})
    # status, error and worker are written now (real values, not fill values): resume reads them
    status = np.zeros(shape, np.int8)
    data["status"] = xr.Variable(axes, status, {"flag_values": [0, 1, 2], "flag_meanings": "pending done failed"})
    data["error"] = xr.Variable(axes, np.full(shape, "", dtype=f"<U{ERROR_CHARS}"),
                                {"description": "one-line error of a failed point"})
    data["worker"] = xr.Variable(axes, np.full(shape, "", dtype=f"<U{WORKER_CHARS}"),
                                 {"description": "the worker that rendered the point"})
    for name in ("status", "error", "worker"):
        encoding[name] = {"chunks": one}
    if any(m.per_detector for m in layout["metrics"].values()):
        coords["detector"] = ("detector", np.array(layout["detectors"]), {"description": "detector id (channel name)"})
    ds = xr.Dataset(data, coords=coords)
    if layout["channels"]:
        xs, ys = layout["pixel_axes"]
        ds = ds.assign_coords(x=("x", xs, {"units": "mm", "description": "pixel centre (build plane)"}),
                              y=("y", ys, {"units": "mm", "description": "pixel centre; row 0 = +y edge"}))
    ds.attrs = {
        "title": f"elo-mitsuba sweep of {Path(spec.scene).name}",
        "generator": f"elo-mitsuba {__version__}",
        "elo_sweep_digest": spec.digest(),
        "spec_toml": spec.text,
        "spec": json.dumps(spec.to_dict(), default=str),
        "scan_geometry": json.dumps(layout["geometry"]),
        "points": spec.n_points,
        "load_time_parameters": ", ".join(sorted({m.key for a in spec.axes for m in a.members if m.target == "scene"}))
        or "none",
    }
    ds.to_zarr(str(path), mode="w-", compute=False, zarr_format=ZARR_FORMAT, encoding=encoding, consolidated=True)


def _coordinates(spec) -> dict:
    coords = {}
    for a in spec.axes:
        if not a.zipped:
            coords.update(_member_coords(a.dim, a.members[0], index=True))
        else:
            coords[a.dim] = (a.dim, np.arange(len(a)), {"description": "zipped group: "
                                                        + ", ".join(m.dim for m in a.members),
                                                        "long_name": a.name})
            for m in a.members:
                coords.update(_member_coords(a.dim, m, index=False))
    return coords


def _member_coords(dim, m, index: bool) -> dict:
    """The coordinate(s) of swept member ``m`` along dimension ``dim``: named ``dim`` itself
    (``index``) or, in a zipped group, ``m.dim``; ``long_name`` is the spec key."""
    attrs = {"units": m.units, "long_name": m.key,
             "load_time": "yes: a scene load per value" if m.target == "scene" else "no: changed in place"}
    vals = m.values
    name = dim if index else m.dim
    if m.attribute in ("center", "normal"):
        labels = np.array(["(" + ", ".join(f"{c:g}" for c in v) + ")" for v in vals])
        return {f"{m.dim}_xyz": ((dim, "xyz"), np.array(vals, dtype=float), attrs),
                name: (dim, labels, dict(attrs))}
    return {name: (dim, np.array(vals), attrs)}


def read_status(path) -> np.ndarray:
    """The status array (0 pending, 1 done, 2 failed), shape = the sweep's shape. A store whose
    status cannot be read (a damaged chunk) is refused with one line naming the chunk."""
    import zarr

    try:
        arr = zarr.open_group(str(path), mode="r")["status"]
    except Exception as exc:  # noqa: BLE001 -- any reader failure is a damaged store for the user
        raise EloInputError(f"output {path}: its status array cannot be opened ({_one_line(exc)}); the store is "
                            "damaged: --overwrite to start again, or choose another -o") from None
    try:
        status = np.asarray(arr[...])
    except Exception as exc:  # noqa: BLE001
        where = ""
        for k, idx in enumerate(np.ndindex(arr.shape)):  # name the first unreadable chunk
            if k >= 10000:
                break
            try:
                arr[idx]
            except Exception:  # noqa: BLE001
                where = f" (point {list(idx)}: chunk status/{'.'.join(map(str, idx)) or '0'})"
                break
        raise EloInputError(f"output {path}: the status of its points cannot be read{where}: {_one_line(exc)}; the "
                            "store is damaged: --overwrite to start again, or choose another -o") from None
    if not np.isin(status, (STATUS_PENDING, STATUS_DONE, STATUS_FAILED)).all():
        bad = np.argwhere(~np.isin(status, (STATUS_PENDING, STATUS_DONE, STATUS_FAILED)))[0].tolist()
        raise EloInputError(f"output {path}: point {bad} has status {int(status[tuple(bad)])} (0, 1 or 2 expected); "
                            "the store is damaged: --overwrite to start again, or choose another -o")
    return status


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())[:200] or type(exc).__name__
    return f"{type(exc).__name__}: {text}"


class PointWriter:
    """Writes one point's results into its own chunks (used on the workers).

    The arrays are opened once (opening one reads its metadata files) and a point's variables
    are written concurrently through Zarr's asynchronous API, then ``status`` last: Zarr-Python
    3 spends ~3 ms per synchronous write, which for a dozen variables would be ~10 % of a
    0.4 s render."""

    def __init__(self, path):
        import zarr.api.asynchronous as za
        from zarr.core.sync import sync

        self._sync = sync
        self._group = sync(za.open_group(str(path), mode="r+"))
        self._arrays = {}

    def _array(self, name):
        if name not in self._arrays:
            import zarr

            # write_empty_chunks: store every chunk without first scanning it for the fill value
            # (a point's chunk is never empty; the scan is a quarter of a write's CPU time)
            with zarr.config.set({"array.write_empty_chunks": True}):
                self._arrays[name] = self._sync(self._group.getitem(name))
        return self._arrays[name]

    def status(self, idx) -> int:
        return int(self._sync(self._array("status").getitem(idx)))

    def statuses(self, idxs) -> list[int]:
        """The status of several points, read concurrently (one chunk each)."""
        import asyncio

        arr = self._array("status")

        async def read():
            return await asyncio.gather(*(arr.getitem(idx) for idx in idxs))

        return [int(v) for v in self._sync(read())]

    def write(self, idx, values: dict, status: int = STATUS_DONE, error: str | None = "", worker: str = "") -> None:
        """Store ``values`` (variable -> array for this point), then ``error``, ``worker`` and,
        last, ``status``: a crash in between leaves the point pending. ``error=None`` leaves the
        stored error text as it is (it is "" unless the point failed before)."""
        import asyncio

        values = dict(values)
        if error is not None:
            values["error"] = error[:ERROR_CHARS]
        values["worker"] = worker[:WORKER_CHARS]
        arrays = {name: self._array(name) for name in values}

        async def data():
            await asyncio.gather(*(arrays[n].setitem(idx, v) for n, v in values.items()))

        self._sync(data())
        self._sync(self._array("status").setitem(idx, status))
