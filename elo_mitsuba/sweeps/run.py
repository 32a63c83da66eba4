"""The client side of a sweep: validate, allocate the store, hand the points to Dask workers,
show progress, record what failed.

Default: a Dask ``LocalCluster`` on this machine (``workers`` processes, one Dask thread each,
Dr.Jit thread pools sized so that together they use the cores once). With ``scheduler`` the same
points go to a running ``dask scheduler`` + ``dask worker`` cluster; the workers need this package
installed and the output path on a file system they share with the client. ``workers=0`` renders
in this process without Dask (debugging, and the benchmark's reference).
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from ..errors import EloInputError
from ..schema import UNITS, event_channels
from . import store as zstore
from .metrics import METRICS, applicable
from .claims import Claims
from .extra import require
from .cost import check as estimate_cost
from .spec import SweepSpec, load_spec
from .validate import check_first_point, check_points
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
    state: str                  # "created", "resumed" or "joined" (created meanwhile by another client)
    claimed_elsewhere: int = 0  # pending points left to another client rendering the same store

    @property
    def rate(self) -> float:
        """Points rendered per second (skipped ones excluded)."""
        n = self.points - self.skipped - self.claimed_elsewhere
        return n / self.seconds if self.seconds > 0 else float("nan")


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def prepare(spec, output, *, overwrite: bool = False, workers: int = 1, force: bool = False, create: bool = True):
    """Everything before the first render: parse and check the spec, check the output, check
    every point against the scene (:func:`.validate.check_points`, no render), estimate the cost
    (:func:`.cost.check`: refused when unbounded unless ``force``), then create (or check for
    resume) the store; with ``create=False`` the store is left alone (``state`` is then None).

    Returns
    -------
    spec : SweepSpec
    layout : dict
        What workers need besides the spec (metric names, detectors, kept channels).
    state : str or None
        ``"created"``, ``"resumed"`` or ``"joined"`` (see :func:`.store.open_or_create`).
    path : Path
    store_layout : dict
        What the store is created from (for :func:`.store.open_or_create`).
    """
    spec = load_spec(spec)
    path = zstore.check_store_path(output, overwrite=overwrite)
    probe = check_first_point(spec)  # names, options, surface against the first point's scene
    dets = probe.detector_names
    events = [spec.events] + [v for a in spec.axes for m in a.members if m.key == "events" for v in m.values]
    ctx = {"events": min(events), "surface": spec.surface is not None, "detectors": dets}
    metrics = spec.metrics if spec.metrics is not None else applicable(ctx)
    if spec.channels == "all":
        channels = list(dets) + (event_channels(dets, min(events)) if min(events) > 1 else [])
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
        "units": meta[UNITS],
        "geometry": geometry,
    }
    estimate_cost(spec, probe, layout, path, workers=workers, force=force)
    del probe
    check_points(spec)  # every point's load-time values and detector moves, nothing rendered
    state = zstore.open_or_create(path, spec, layout, overwrite=overwrite) if create else None
    job_layout = {"metrics": list(metrics), "detectors": dets, "channels": channels}
    return spec, job_layout, state, path, layout


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


#: Seconds to wait for a Dask scheduler to answer (``scheduler=``) before giving up.
CONNECT_SECONDS = 10
#: Default seconds a sweep waits while no Dask worker is connected (at the start, or after all
#: were lost) before it stops with one line (``worker_wait_s``, CLI ``--worker-wait``).
WORKER_WAIT_SECONDS = 60.0
#: The longest ``worker_wait_s``: a week (given an infinite wait, Dask's wait for workers gave up at
#: once; a longer wait is a sweep left hanging, not a setting).
MAX_WORKER_WAIT_SECONDS = 7 * 86400.0
#: Most Dr.Jit threads per worker on a cluster whose hosts this client cannot see.
MAX_THREADS = 1024


def _whole(name, value, lo):
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise EloInputError(f"{name}={value!r}; must be a whole number >= {lo}")
    return value


def check_resources(workers, scheduler, threads):
    """The cluster arguments, checked before anything starts: (workers, scheduler address or
    file, threads). Local workers are processes with at least one Dr.Jit thread each: more of them
    than cores, or more threads per worker than cores, only slows every render; refused."""
    if workers is not None and scheduler is not None:
        raise EloInputError("give either workers (a local cluster) or scheduler (a running one), not both")
    cores = available_cores()
    if scheduler is None:
        workers = 1 if workers is None else workers
        if isinstance(workers, bool) or not isinstance(workers, int):
            raise EloInputError(f"workers={workers!r}; must be a whole number of local worker processes, 0 to {cores}")
        if not 0 <= workers <= cores:
            raise EloInputError(f"workers={workers}; this machine has {cores} cores: give 0 (in this process) to "
                                f"{cores} local workers (each renders with at least one thread)")
        limit = max(1, cores // max(workers, 1))
        if threads is not None:
            if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
                raise EloInputError(f"threads per worker {threads!r}; must be a whole number of Dr.Jit threads >= 1")
            if threads > limit:
                raise EloInputError(f"threads per worker {threads}; {max(workers, 1)} worker(s) on {cores} cores: at most {limit} "
                                    "Dr.Jit thread(s) per worker (more only make the renders wait for each other)")
        return workers, None, threads
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or not 1 <= threads <= MAX_THREADS):
        raise EloInputError(f"threads per worker {threads!r}; must be a whole number of Dr.Jit threads in "
                            f"[1, {MAX_THREADS}]")
    return None, _scheduler_address(scheduler), threads


def _scheduler_address(scheduler) -> dict:
    """``{"address": ...}`` or ``{"scheduler_file": ...}`` from ``scheduler``, checked (a file must
    exist and hold a scheduler's JSON; an address must be ``scheme://host:port``)."""
    import re

    if not isinstance(scheduler, (str, os.PathLike)) or not str(scheduler).strip():
        raise EloInputError(f"scheduler {scheduler!r}: give tcp://host:port or a scheduler file (.json)")
    text = str(scheduler).strip()
    if text.lower().endswith(".json"):
        try:
            info = json.loads(Path(text).read_text())
        except OSError as exc:
            raise EloInputError(f"scheduler file {text}: cannot read it ({exc.strerror or exc})") from None
        except ValueError:
            raise EloInputError(f"scheduler file {text}: not JSON (a file written by dask scheduler "
                                "--scheduler-file)") from None
        if not isinstance(info, dict) or not isinstance(info.get("address"), str):
            raise EloInputError(f"scheduler file {text}: no \"address\" (a file written by dask scheduler "
                                "--scheduler-file)")
        address = info["address"]
        where = f"scheduler file {text}: address {address!r}"
    else:
        address, where = text, f"scheduler {text!r}"
    m = re.fullmatch(r"(?:(tcp|tls|ucx|ws|wss)://)?(\[[0-9a-fA-F:]+\]|[A-Za-z0-9._-]+):(\d{1,5})", address)
    if not m or not 0 < int(m.group(3)) < 65536:
        raise EloInputError(f"{where}: not an address of the form tcp://host:port (port 1-65535)")
    return {"scheduler_file": text} if text.lower().endswith(".json") else {"address": address}


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())[:200]
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def sweep(spec, output, *, workers: int | None = None, scheduler: str | None = None,
          threads_per_worker: int | None = None, overwrite: bool = False, progress: bool | None = None,
          max_batch: int = MAX_BATCH, force: bool = False, worker_wait_s: float | None = None) -> SweepSummary:
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
        freed memory for reuse as a worker does, :func:`~elo_mitsuba.runtime.keep_freed_memory`);
        at most the machine's cores. The local cluster starts its workers by importing the main
        module: call this under ``if __name__ == "__main__":`` in a script.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:port``) or a scheduler file (``.json``);
        then ``workers`` is not used. It must answer within :data:`CONNECT_SECONDS`.
    threads_per_worker : int, optional
        Dr.Jit threads per worker (default: the cores / workers on the same host; locally at most
        that).
    overwrite : bool
        Replace an existing store.
    progress : bool, optional
        Progress line on stderr (default: when stderr is a terminal).
    force : bool
        Run a sweep whose estimate is over the limits of :mod:`.cost` (CLI ``--yes``).
    worker_wait_s : float, optional
        How long to wait while no worker is connected (at the start, or after all were lost)
        before stopping with one line; the points stored so far are kept (re-run to resume).
        Default :data:`WORKER_WAIT_SECONDS`, at most :data:`MAX_WORKER_WAIT_SECONDS`; refused with
        ``workers=0``, which has no workers to wait for.

    Returns
    -------
    SweepSummary
        The store's path, points in all, done, failed and skipped (done before), seconds, workers,
        and whether the store was created or resumed.

    Raises
    ------
    EloInputError
        Bad input (one line), before the store is created.
    EloError
        The cluster failed during the sweep (scheduler or every worker lost): one line; what was
        stored is kept and a re-run resumes it.
    EloEnvironmentError
        The ``sweep`` extra (Dask, distributed, xarray, Zarr) is not installed: one line, before anything else.

    Examples
    --------
    A detector's radius swept in this process (``workers=0``), read back with xarray; a larger
    disc collects more electrons:

    >>> import tempfile
    >>> from pathlib import Path
    >>> import xarray as xr
    >>> spec = {"scene": "flat_plate", "vary": {"right": {"radius": [20.0, 30.0]}},
    ...         "render": {"resolution": 4}, "keep": {"metrics": ["signal_mean"]}}
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     summary = sweep(spec, Path(folder) / "radii.zarr", workers=0, progress=False)
    ...     mean = xr.open_zarr(Path(folder) / "radii.zarr").signal_mean.sel(detector="right")
    ...     bigger = bool(mean.sel(right_radius=30.0) > mean.sel(right_radius=20.0))
    >>> summary.done, summary.failed, bigger
    (2, 0, True)
    """
    require("a sweep")
    workers, address, threads_per_worker = check_resources(workers, scheduler, threads_per_worker)
    if worker_wait_s is not None:
        if isinstance(worker_wait_s, bool) or not isinstance(worker_wait_s, (int, float)) \
                or not 0 < worker_wait_s <= MAX_WORKER_WAIT_SECONDS:
            raise EloInputError(f"worker_wait_s={worker_wait_s!r} (--worker-wait); must be a number of seconds > 0 "
                                f"and at most {MAX_WORKER_WAIT_SECONDS:g} (a week)")
        if workers == 0 and address is None:  # it would be accepted and do nothing
            raise EloInputError(f"worker_wait_s={worker_wait_s:g} (--worker-wait) waits for Dask workers, and "
                                "workers=0 (--workers 0) renders in this process without any; drop one of them")
    worker_wait_s = WORKER_WAIT_SECONDS if worker_wait_s is None else worker_wait_s
    max_batch = _whole("max_batch", max_batch, 1)
    spec, layout, _, path, store_layout = prepare(spec, output, overwrite=overwrite, workers=workers or 1,
                                                  force=force, create=False)
    client = cluster = None
    quiet = _QuietDask()
    if workers != 0:  # the cluster answers before the store is created
        quiet.__enter__()
        try:
            client, cluster = connect(address, workers)
        except BaseException:
            quiet.__exit__()
            raise
    try:
        state = zstore.open_or_create(path, spec, store_layout, overwrite=overwrite)
        status = zstore.read_status(path).ravel()
        pending = [int(i) for i in range(spec.n_points) if status[i] != zstore.STATUS_DONE]
        claims = Claims(path)
        try:
            mine, others = claims.claim(pending)
            skipped = spec.n_points - len(pending)
            show = sys.stderr.isatty() if progress is None else progress
            bar = _Progress(len(mine), show)
            job = {"spec": spec.to_dict(), "layout": layout}
            t0 = time.perf_counter()
            n_workers = 0
            if mine and workers == 0:
                n_workers = 1
                set_up(threads_per_worker)
                for batch in batches(spec, mine, 1, max_batch):
                    res = run_batch(str(path), job, batch)
                    claims.heartbeat()
                    bar.update(sum(s == zstore.STATUS_DONE for _, s, _ in res),
                               sum(s == zstore.STATUS_FAILED for _, s, _ in res))
            elif mine:
                n_workers = _run_dask(client, spec, path, job, mine, threads_per_worker, bar, max_batch,
                                      worker_wait_s, claims, address)
            bar.close()
            seconds = time.perf_counter() - t0
        finally:
            claims.release()
    finally:
        disconnect(client, cluster)
        quiet.__exit__()
    final = zstore.read_status(path).ravel()
    return SweepSummary(path=path, points=spec.n_points, done=int((final == zstore.STATUS_DONE).sum()),
                        failed=int((final == zstore.STATUS_FAILED).sum()), skipped=skipped, seconds=seconds,
                        workers=n_workers, state=state, claimed_elsewhere=sum(others.values()))


class _QuietDask:
    """Dask's own log records (a lost scheduler's reconnection attempts, with tracebacks) kept
    off stderr while the sweep runs: the sweep reports a fault itself, in one line."""

    def __init__(self):
        self.saved = None

    def __enter__(self):
        import distributed  # noqa: F401 -- its import configures its loggers: quiet them after it

        names = ["distributed", "tornado"] + [n for n in logging.root.manager.loggerDict if n.startswith("distributed.")]
        self.saved = {n: logging.getLogger(n).level for n in names}
        for n in names:
            logging.getLogger(n).setLevel(logging.CRITICAL)
        return self

    def __exit__(self, *exc):
        for n, level in (self.saved or {}).items():
            logging.getLogger(n).setLevel(level)
        self.saved = None


def _refused(address: str) -> bool:
    """Whether the host of a ``tcp://host:port`` address refuses a connection: it answers at once,
    where Dask's client would retry until :data:`CONNECT_SECONDS` have passed. Anything else (a
    host that does not answer, a name to resolve) is left to the client and its timeout."""
    import socket

    host, _, port = address.removeprefix("tcp://").rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=1.0):
            return False
    except ConnectionRefusedError:
        return True
    except (OSError, ValueError):
        return False


def connect(address, workers):
    """(client, local cluster or None): a local cluster of ``workers`` processes, or a client of
    the running scheduler ``address`` ({"address"} or {"scheduler_file"}), which must answer
    within :data:`CONNECT_SECONDS`."""
    from distributed import Client, LocalCluster

    if address is None:
        import dask

        # Dask's statistical profiler samples every worker thread's stack each 10 ms, under the GIL:
        # measurable next to renders of ~0.1-1 s, and nobody reads it here
        with dask.config.set({"distributed.worker.profile.enabled": False}):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                                   silence_logs=logging.ERROR)
        return Client(cluster), cluster
    where = address.get("address") or f"in {address['scheduler_file']}"
    if address.get("address") and _refused(address["address"]):
        raise EloInputError(f"cannot reach the Dask scheduler {where}: nothing listens there (connection refused); "
                            "is it running, and is the address right?")
    try:
        return Client(**address, timeout=f"{CONNECT_SECONDS}s"), None
    except Exception as exc:  # noqa: BLE001 -- refused, unreachable, malformed: one line
        raise EloInputError(f"cannot reach the Dask scheduler {where} within {CONNECT_SECONDS} s "
                            f"({_one_line(exc)}); is it running, and is the address right?") from None


def disconnect(client, cluster):
    for thing in (client, cluster):
        if thing is None:
            continue
        try:
            thing.close(timeout=5) if thing is client else thing.close()
        except Exception:  # noqa: BLE001 -- a lost scheduler: nothing left to close cleanly
            pass


def _stored(path) -> tuple[int, int]:
    final = zstore.read_status(path).ravel()
    return int((final == zstore.STATUS_DONE).sum()), final.size


def _run_dask(client, spec, path, job, pending, threads, bar, max_batch, worker_wait_s, claims, address) -> int:
    from distributed import wait
    from distributed.diagnostics.plugin import WorkerPlugin

    from ..errors import EloError

    plugin_cls = type("EloThreadsPlugin", (_ThreadsPlugin, WorkerPlugin), {})
    where = "local Dask cluster" if address is None else \
        f"Dask scheduler {address.get('address') or 'in ' + address['scheduler_file']}"

    def stop(what):
        done, total = _stored(path)
        raise EloError(f"{what}: {done} of {total} points are stored, {total - done} not; "
                       "re-run the same command to resume")

    try:
        client.wait_for_workers(1, timeout=worker_wait_s)
    except Exception:  # noqa: BLE001 -- TimeoutError, or the scheduler went away
        stop(f"no worker joined the {where} within {worker_wait_s:g} s")
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
    remaining = set(futures)
    writer = None
    no_workers_since = None
    while remaining:
        try:
            finished, _ = wait(list(remaining), timeout=1.0, return_when="FIRST_COMPLETED")
        except TimeoutError:
            finished = set()
        except Exception:  # noqa: BLE001 -- e.g. FuturesCancelledError: the scheduler is gone
            finished = {f for f in remaining if f.status in ("finished", "error", "cancelled", "lost")}
        claims.heartbeat()
        if client.status != "running" or any(f.status in ("cancelled", "lost") for f in remaining):
            stop(f"the {where} was lost")
        for fut in finished:
            remaining.discard(fut)
            try:
                res = fut.result()
            except Exception as exc:  # noqa: BLE001 -- e.g. KilledWorker after the retries: record it
                if type(exc).__name__ in ("CancelledError", "FutureCancelledError", "CommClosedError") \
                        or client.status != "running":
                    stop(f"the {where} was lost")
                writer = writer or zstore.PointWriter(path)
                failed = 0
                for i in futures[fut]:
                    idx = spec.point(i).idx
                    if writer.status(idx) != zstore.STATUS_DONE:
                        writer.write(idx, {}, zstore.STATUS_FAILED, error=_one_line(exc)[:240], worker="lost")
                        failed += 1
                bar.update(len(futures[fut]) - failed, failed)
                continue
            bar.update(sum(s == zstore.STATUS_DONE for _, s, _ in res), sum(s == zstore.STATUS_FAILED for _, s, _ in res))
        if remaining and not finished:
            try:
                connected = len(client.nthreads())
            except Exception:  # noqa: BLE001 -- the scheduler does not answer
                stop(f"the {where} was lost")
            if connected:
                no_workers_since = None
            elif no_workers_since is None:
                no_workers_since = time.monotonic()
            elif time.monotonic() - no_workers_since > worker_wait_s:
                client.cancel(list(remaining))
                stop(f"every worker of the {where} was lost and none joined within {worker_wait_s:g} s")
    return n_workers
