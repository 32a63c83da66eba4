"""What runs on a sweep worker: load each scene once, re-render it per point by changing
parameters in place, compute the metrics, write the point into the store.

A worker process keeps a small cache of loaded scenes keyed by their load-time parameters
(:attr:`~.spec.Point.load_key`); the client sends the points grouped by that key, so each worker
loads each key about once. Between points the integrator options are put back as loaded and the point's detector moves are
applied (:meth:`LoadedScene.prepare`); a cached scene whose moved detectors the point does not
move (an earlier sweep on the same worker moved them) is loaded afresh instead of being put back,
as a transform rewritten from its float32 copy gets an inverse that differs in the last bit from a
fresh load's (up to 2e-7 relative in the images). So a point's numbers do not depend on which
points the worker rendered before: they equal a fresh ``load_scene(...)``, ``set_detector(...)``,
``render(...)`` with the same seed, bit for bit (tests/test_sweep_faults.py).
"""

from __future__ import annotations

import gc
import json
import os
import sys
import threading
import time
import traceback
from collections import OrderedDict

import numpy as np

from .metrics import METRICS, PointContext, true_gradient
from .spec import ALL_DETECTORS, SweepSpec
from .store import STATUS_DONE, STATUS_FAILED, PointWriter, image_variable

#: Loaded scenes kept per worker (LRU). Two: the object scene and, with a test surface, its flat
#: reference; a third key evicts the oldest (Mitsuba frees a scene's memory when dropped).
MAX_SCENES = 3
#: Flat reference renders kept per worker: points that differ only in what the flat does not see
#: (nothing, for now: its render depends on every load-time parameter and move) share one.
MAX_FLATS = 2

_STATE = {"scenes": OrderedDict(), "flats": OrderedDict(), "specs": {}, "writers": {}, "loads": 0}
_LOCK = threading.Lock()  # dask may run a worker with several threads; Dr.Jit state is per process


def set_up(threads: int | None = None) -> int:
    """Worker set-up: the Dr.Jit thread pool size (so that workers sharing a machine do not
    oversubscribe its cores), freed memory kept for reuse (:func:`~elo_mitsuba.runtime.keep_freed_memory`)
    and the variant with our plugins. Returns the thread count."""
    import drjit as dr

    from ..runtime import ensure_variant, keep_freed_memory

    keep_freed_memory()
    if threads:
        dr.set_thread_count(int(threads))
    ensure_variant()
    return int(dr.thread_count())


class LoadedScene:
    """An :class:`~elo_mitsuba.EloScene` plus what is needed to put it back as loaded."""

    def __init__(self, scene_path, load: dict, integrator: dict):
        from ..render import load_scene

        self.scene = load_scene(scene_path, **load)
        if integrator:
            self.scene.configure(**integrator)
        self.options = self.scene.options
        self.moved: set[str] = set()

    def moved_by(self, moves: dict) -> set[str]:
        names = set()
        for det in moves:
            names |= set(self.scene.detector_names) if det == ALL_DETECTORS else {det}
        return names

    def reusable(self, moves: dict) -> bool:
        """Whether a point with detector ``moves`` can reuse this scene bit for bit: every
        detector moved before is moved again (its transform is then computed afresh, as in a
        fresh scene). A detector moved before and not now would have to be put back from its
        float32 copy, whose recomputed inverse differs in the last bit from a fresh load's."""
        return not (self.moved - self.moved_by(moves))

    def prepare(self, moves: dict):
        """Put the scene back as loaded for a point with detector ``moves``, then apply them.

        Detectors moved before and not moved now are put back as loaded
        (:meth:`~elo_mitsuba.EloScene.restore_detectors`; last-bit differences, see
        :meth:`reusable`: the worker reloads such a scene instead)."""
        names = self.moved_by(moves)
        self.scene.restore_detectors(sorted(self.moved - names))
        self.scene.integrator.configure(self.options)
        # detectors first (all), then single ones, so that right.radius refines detectors.radius
        for det in sorted(moves, key=lambda d: d != ALL_DETECTORS):
            m = moves[det]
            for name in (self.scene.detector_names if det == ALL_DETECTORS else [det]):
                self.scene.set_detector(name, center=m.get("center"), radius=m.get("radius"), normal=m.get("normal"))
        self.moved = names
        self.scene.check_detectors()  # the moved system as a whole (discs that intersect), as the spec's check sees it


def _scene(path, load: dict, integrator: dict, moves: dict | None = None) -> LoadedScene:
    key = json.dumps([str(path), load, integrator], sort_keys=True, default=str)
    cache = _STATE["scenes"]
    if key in cache and cache[key].reusable(moves or {}):
        cache.move_to_end(key)
        return cache[key]
    if key in cache:  # it would have to put a detector back from float32: load it afresh
        del cache[key]
        gc.collect()
    while len(cache) >= MAX_SCENES:
        cache.popitem(last=False)
        gc.collect()
    cache[key] = LoadedScene(path, load, integrator)
    _STATE["loads"] += 1
    return cache[key]


def render_point(spec: SweepSpec, point) -> tuple:
    """Render one point (and its flat reference with a test surface); returns
    ``(RenderResult, flat channels or None)``. Numbers equal a direct render of the same
    parameters and seed."""
    scene = _scene(spec.scene, point.load, spec.integrator, point.moves)
    scene.prepare(point.moves)
    r = point.render
    result = scene.scene.render(spp=r["spp"], seed=r["seed"], events=r["events"], quality=r["quality"], progress=False)
    if scene.scene.integrator.in_beam:  # a geometry no design can have: the point fails with the render's note
        from ..errors import EloInputError

        name = scene.scene.integrator.in_beam[0][0]
        raise EloInputError(next(n for n in result.metadata["notes"] if n.startswith(f"detector {name!r} lies in")))
    flat = None
    if spec.surface is not None:
        flat = _flat(spec, point, scene)
    return result, flat


def _flat(spec, point, obj: LoadedScene):
    from ..scene_files import declared_parameters, resolve_scene_path

    path = resolve_scene_path(spec.surface["flat"])
    declared = declared_parameters(path, {k: str(v) for k, v in point.load.items()})
    load = {k: v for k, v in point.load.items() if k in declared}
    key = json.dumps([str(path), load, spec.integrator, point.moves, point.render], sort_keys=True, default=str)
    cache = _STATE["flats"]
    if key in cache:
        return cache[key]
    flat = _scene(path, load, spec.integrator, point.moves)
    flat.prepare(point.moves)
    r = point.render
    channels = flat.scene.render(spp=r["spp"], seed=r["seed"], events=r["events"], quality=r["quality"],
                                 progress=False).channels
    while len(cache) >= MAX_FLATS:
        cache.popitem(last=False)
    cache[key] = channels
    return channels


def point_values(spec: SweepSpec, layout: dict, result, flat) -> dict:
    """The store's variables of one point, from its render: metrics and kept images."""
    dets = layout["detectors"]
    ctx = PointContext(result.channels, result.metadata, [d for d in dets if d in result.channels], flat=flat)
    if spec.surface is not None:
        shape = result.channels[dets[0]].shape
        ctx.true_gradient = true_gradient(spec.surface, shape, ctx.field_mm)
    out = {}
    for name in layout["metrics"]:
        value = METRICS[name].function(ctx)
        out[name] = np.array([value.get(d, np.nan) for d in dets]) if isinstance(value, dict) else float(value)
    f = spec.downsample
    for ch in layout["channels"]:
        img = result.channels[ch]
        if f > 1:
            h, w = img.shape
            img = img.reshape(h // f, f, w // f, f).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
        out[image_variable(ch)] = img
    return out


def _spec(spec_dict) -> SweepSpec:
    key = spec_dict["text"] + json.dumps(spec_dict.get("axes"), default=str)
    if key not in _STATE["specs"]:
        _STATE["specs"] = {key: SweepSpec.from_dict(spec_dict)}
    return _STATE["specs"][key]


def _writer(store) -> PointWriter:
    if store not in _STATE["writers"]:
        _STATE["writers"] = {store: PointWriter(store)}
    return _STATE["writers"][store]


def worker_name() -> str:
    """The Dask worker's name, or ``pid<N>`` outside Dask (without importing it there)."""
    if "distributed" in sys.modules:
        try:
            return str(sys.modules["distributed"].get_worker().name)
        except ValueError:  # not in a worker
            pass
    return f"pid{os.getpid()}"


def rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 1e6


def one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{type(exc).__name__}: {text}"


def _failed(writer, point, exc, name) -> tuple[int, int, str]:
    error = one_line(exc)
    if os.environ.get("ELO_SWEEP_TRACEBACK"):
        traceback.print_exc()
    writer.write(point.idx, {}, STATUS_FAILED, error=error, worker=name)
    return point.index, STATUS_FAILED, error


def _finish(spec, layout, writer, point, result, flat, seconds, before, name) -> tuple[int, int, str]:
    """Metrics and the write of one rendered point (runs beside the next point's render)."""
    try:
        values = point_values(spec, layout, result, flat)
        values["render_seconds"] = seconds
        values["worker_rss_mb"] = rss_mb()
        values["finished_at"] = time.time()
        values["worker_cpu_s"] = time.process_time()
        writer.write(point.idx, values, STATUS_DONE, error="" if before == STATUS_FAILED else None, worker=name)
    except Exception as exc:  # noqa: BLE001 -- a failed point is recorded, the sweep goes on
        return _failed(writer, point, exc, name)
    return point.index, STATUS_DONE, ""


def run_batch(store: str, job: dict, indices: list[int]) -> list[tuple[int, int, str]]:
    """Render the points ``indices`` of a sweep into ``store``; the task each worker runs.

    A point already done (a retried batch after a worker was lost) is skipped. A point that
    raises is recorded as failed with its one-line error; the others go on. The metrics and the
    Zarr write of a point run in a second thread while the next point renders (at most one
    point waits: memory stays bounded); the task returns when every point is stored.

    Returns
    -------
    list of (index, status, error)
    """
    from concurrent.futures import ThreadPoolExecutor

    with _LOCK, ThreadPoolExecutor(1, thread_name_prefix="elo-sweep-write") as pool:
        spec = _spec(job["spec"])
        writer = _writer(store)
        name = worker_name()
        out, waiting = [], None
        points = [spec.point(i) for i in indices]
        for i, point, before in zip(indices, points, writer.statuses([p.idx for p in points])):
            if before == STATUS_DONE:  # a retried batch (its worker was lost): done already
                out.append((i, STATUS_DONE, ""))
                continue
            t0 = time.perf_counter()
            try:
                result, flat = render_point(spec, point)
            except Exception as exc:  # noqa: BLE001 -- a failed point is recorded, the sweep goes on
                out.append(_failed(writer, point, exc, name))
                continue
            seconds = time.perf_counter() - t0
            if waiting is not None:
                out.append(waiting.result())
            waiting = pool.submit(_finish, spec, job["layout"], writer, point, result, flat, seconds, before, name)
            del result, flat
        if waiting is not None:
            out.append(waiting.result())
        return sorted(out)
