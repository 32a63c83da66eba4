"""The client side of a sweep: validate, allocate the store, hand the points to Dask workers,
show progress, record what failed.

Default: a Dask ``LocalCluster`` on this machine (``workers`` processes, one Dask thread each,
Dr.Jit thread pools sized so that together they use the cores once). With ``scheduler`` the same
points go to a running ``dask scheduler`` + ``dask worker`` cluster; the workers need this package
installed and the output path on a file system they share with the client. ``workers=0`` renders
in this process without Dask (debugging, and the benchmark's reference).
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from ..errors import EloInputError
from . import store as zstore
from .metrics import METRICS, applicable
from .spec import SweepSpec, check_against_scene, check_parameters, load_spec
from .worker import run_batch, set_up

#: Most points per task: small enough that a lost worker costs little and progress moves, large
#: enough that Dask's per-task overhead (~ms) stays far below a render (~0.1-2 s).
MAX_BATCH = 4


@dataclass
class SweepSummary:
    """What a sweep did."""

    path: Path
    points: int
    done: int
    failed: int
    skipped: int
    seconds: float
    workers: int
    state: str                  # "created" or "resumed"

    @property
    def rate(self) -> float:
        """Points rendered per second (skipped ones excluded)."""
        n = self.points - self.skipped
        return n / self.seconds if self.seconds > 0 else float("nan")


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def prepare(spec, output, *, overwrite: bool = False):
    """Everything before the first render: parse and check the spec, check the output, load the
    scene once to check names against it, create (or check for resume) the store.

    Returns
    -------
    spec : SweepSpec
    layout : dict
        What workers need besides the spec (metric names, detectors, kept channels).
    state : str
        ``"created"`` or ``"resumed"``.
    """
    spec = load_spec(spec)
    path = zstore.check_store_path(output, overwrite=overwrite)
    from ..render import load_scene

    first = spec.point(0)
    try:  # the first point's scene: names, detectors and channels are checked against it
        check_parameters(spec)
        probe = load_scene(spec.scene, **first.load)
    except EloInputError as exc:
        raise EloInputError(f"{spec.source}: {exc}") from None
    check_against_scene(spec, probe)
    if spec.integrator:
        probe.configure(**spec.integrator)
    dets = probe.detector_names
    events = [spec.events] + [v for a in spec.axes for m in a.members if m.key == "events" for v in m.values]
    ctx = {"events": min(events), "surface": spec.surface is not None, "detectors": dets}
    metrics = spec.metrics if spec.metrics is not None else applicable(ctx)
    if spec.channels == "all":
        channels = list(dets) + ([f"{d}.e{k}" for d in dets for k in range(1, min(events) + 1)] if min(events) > 1 else [])
    else:
        channels = list(spec.channels)
    w, h = (int(x) for x in probe.sensor.resolution)
    f = spec.downsample
    if channels and (w % f or h % f):
        raise EloInputError(f"{spec.source}: keep.downsample = {f} does not divide the film {w} x {h}")
    meta = probe.metadata(spp=spec.spp or 1, seed=spec.seed)
    from ..grid import pixel_axes

    geometry = {k: meta[k] for k in ("scene", "parameters", "field_mm", "resolution", "pixel_size_mm",
                                     "work_distance_mm", "projection", "beam_fwhm_mm", "detectors", "orientation",
                                     "units", "variant")}
    geometry["detectors_note"] = "as loaded for the first point, before its detector moves"
    layout = {
        "metrics": {m: METRICS[m] for m in metrics},
        "detectors": dets,
        "channels": channels,
        "image_shape": (h // f, w // f),
        "pixel_axes": pixel_axes((h // f, w // f), meta["field_mm"]),
        "units": meta["units"],
        "geometry": geometry,
    }
    del probe
    state = zstore.open_or_create(path, spec, layout, overwrite=overwrite)
    job_layout = {"metrics": list(metrics), "detectors": dets, "channels": channels}
    return spec, job_layout, state, path


def batches(spec: SweepSpec, indices, n_workers: int, max_batch: int = MAX_BATCH) -> list[list[int]]:
    """The pending points as tasks: grouped by load-time key (sorted, so a worker meets each key
    in one run), each group split into about ``n_workers`` batches of at most ``max_batch``."""
    groups = defaultdict(list)
    for i in indices:
        groups[spec.point(i).load_key].append(i)
    out = []
    for key in sorted(groups):
        g = groups[key]
        size = max(1, min(max_batch, math.ceil(len(g) / max(n_workers, 1))))
        out += [g[j:j + size] for j in range(0, len(g), size)]
    return out


class _Progress:
    """One stderr line: points done of total, failures, rate and time left."""

    def __init__(self, total, show):
        self.total, self.show, self.t0 = total, show, time.perf_counter()
        self.done = self.failed = 0

    def update(self, done, failed):
        self.done += done
        self.failed += failed
        if not self.show:
            return
        elapsed = time.perf_counter() - self.t0
        n = self.done + self.failed
        rate = n / elapsed if elapsed > 0 else 0.0
        eta = (self.total - n) / rate if rate > 0 else float("nan")
        width = 30
        filled = int(width * n / max(self.total, 1))
        print(f"\r  [{'#' * filled}{'.' * (width - filled)}] {n}/{self.total} points"
              f"{f' ({self.failed} failed)' if self.failed else ''}, {rate:.2f} points/s, "
              f"{elapsed:.0f} s, {eta:.0f} s left ", end="", file=sys.stderr, flush=True)

    def close(self):
        if self.show:
            print(file=sys.stderr)


class _ThreadsPlugin:
    """Dask worker plugin: Dr.Jit's thread pool on each worker = the host's cores / the number
    of workers on that host (or ``threads`` when given), set before any render."""

    def __init__(self, threads: int | None, per_host: dict):
        self.threads, self.per_host, self.name = threads, per_host, "elo-mitsuba-threads"

    def setup(self, worker):
        threads = self.threads
        if not threads:
            n = self.per_host.get(worker.address.split("://")[-1].rsplit(":", 1)[0], 1)
            threads = max(1, available_cores() // max(n, 1))
        set_up(threads)


def sweep(spec, output, *, workers: int | None = None, scheduler: str | None = None,
          threads_per_worker: int | None = None, overwrite: bool = False, progress: bool | None = None,
          max_batch: int = MAX_BATCH) -> SweepSummary:
    """Run a design sweep into a Zarr store (see :mod:`elo_mitsuba.sweeps`).

    Parameters
    ----------
    spec : str, Path, dict or SweepSpec
        The sweep spec (TOML file, TOML text or parsed table).
    output : str or Path
        The ``.zarr`` store. An existing store of the same spec is resumed (points done are
        skipped, failed ones retried); one of another spec is refused unless ``overwrite``.
    workers : int, optional
        Local Dask worker processes (default 1; 0 = in this process, without Dask, which then keeps
        freed memory for reuse as a worker does, :func:`~elo_mitsuba.runtime.keep_freed_memory`). The local
        cluster starts its workers by importing the main module: call this under
        ``if __name__ == "__main__":`` in a script.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:port``) or a scheduler file (``.json``);
        then ``workers`` is not used.
    threads_per_worker : int, optional
        Dr.Jit threads per worker (default: the cores / workers on the same host).
    overwrite : bool
        Replace an existing store.
    progress : bool, optional
        Progress line on stderr (default: when stderr is a terminal).

    Returns
    -------
    SweepSummary
    """
    if workers is not None and scheduler is not None:
        raise EloInputError("give either workers (a local cluster) or scheduler (a running one), not both")
    workers = 1 if workers is None and scheduler is None else workers
    if workers is not None and workers < 0:
        raise EloInputError(f"workers={workers}; must be >= 0")
    spec, layout, state, path = prepare(spec, output, overwrite=overwrite)
    status = zstore.read_status(path).ravel()
    pending = [int(i) for i in range(spec.n_points) if status[i] != zstore.STATUS_DONE]
    skipped = spec.n_points - len(pending)
    show = sys.stderr.isatty() if progress is None else progress
    bar = _Progress(len(pending), show)
    job = {"spec": spec.to_dict(), "layout": layout}
    t0 = time.perf_counter()
    n_workers = 0
    if pending and workers == 0:
        n_workers = 1
        set_up(threads_per_worker)
        for batch in batches(spec, pending, 1, max_batch):
            res = run_batch(str(path), job, batch)
            bar.update(sum(s == zstore.STATUS_DONE for _, s, _ in res), sum(s == zstore.STATUS_FAILED for _, s, _ in res))
    elif pending:
        n_workers = _run_dask(spec, path, job, pending, workers, scheduler, threads_per_worker, bar, max_batch)
    bar.close()
    seconds = time.perf_counter() - t0
    final = zstore.read_status(path).ravel()
    return SweepSummary(path=path, points=spec.n_points, done=int((final == zstore.STATUS_DONE).sum()),
                        failed=int((final == zstore.STATUS_FAILED).sum()), skipped=skipped, seconds=seconds,
                        workers=n_workers, state=state)


def _run_dask(spec, path, job, pending, workers, scheduler, threads, bar, max_batch) -> int:
    from distributed import Client, LocalCluster, as_completed
    from distributed.diagnostics.plugin import WorkerPlugin

    plugin_cls = type("EloThreadsPlugin", (_ThreadsPlugin, WorkerPlugin), {})
    cluster = None
    if scheduler is None:
        cores = available_cores()
        threads = threads or max(1, cores // workers)
        import dask

        # Dask's statistical profiler samples every worker thread's stack each 10 ms, under the GIL:
        # measurable next to renders of ~0.1-1 s, and nobody reads it here
        with dask.config.set({"distributed.worker.profile.enabled": False}):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                                   silence_logs=logging.ERROR)
        client = Client(cluster)
    else:
        try:
            if str(scheduler).endswith(".json"):
                client = Client(scheduler_file=str(scheduler), timeout="30s")
            else:
                client = Client(str(scheduler), timeout="30s")
        except (OSError, TimeoutError) as exc:
            raise EloInputError(f"cannot reach the Dask scheduler {scheduler} ({exc})") from None
    try:
        client.wait_for_workers(1, timeout=120)
        info = client.scheduler_info()["workers"]
        per_host = defaultdict(int)
        for addr in info:
            per_host[addr.split("://")[-1].rsplit(":", 1)[0]] += 1
        client.register_plugin(plugin_cls(threads, dict(per_host)), name="elo-mitsuba-threads")
        n_workers = len(info)
        tasks = batches(spec, pending, n_workers, max_batch)
        run_id = f"{spec.digest()}-{time.time_ns()}"
        futures = {client.submit(run_batch, str(path), job, b, key=f"elo-sweep-{run_id}-{k}", pure=False): b
                   for k, b in enumerate(tasks)}
        writer = None
        for fut in as_completed(futures):
            try:
                res = fut.result()
            except Exception as exc:  # noqa: BLE001 -- e.g. KilledWorker after the retries: record it
                writer = writer or zstore.PointWriter(path)
                failed = 0
                for i in futures[fut]:
                    idx = spec.point(i).idx
                    if writer.status(idx) != zstore.STATUS_DONE:
                        writer.write(idx, {}, zstore.STATUS_FAILED, error=f"{type(exc).__name__}: {exc}"[:240],
                                     worker="lost")
                        failed += 1
                bar.update(len(futures[fut]) - failed, failed)
                continue
            bar.update(sum(s == zstore.STATUS_DONE for _, s, _ in res), sum(s == zstore.STATUS_FAILED for _, s, _ in res))
        return n_workers
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
