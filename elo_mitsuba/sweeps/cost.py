"""What a sweep will cost, estimated before its store is created, and the refusal of unbounded work.

Per point the render estimate of :func:`elo_mitsuba.budget.estimate` (samples over this machine's
throughput, all cores: workers share them) at the largest ``spp``/``events`` of the spec, doubled
with a test surface (the flat reference); the store's size and file count from its layout (a chunk
per point and variable, each at least a file-system block); the memory of creating it (the
``status``/``error``/``worker`` arrays are built in memory: ~1.2 kB per point, copied by xarray) and
of the workers' renders.

The rule is :func:`elo_mitsuba.budget.check_work`'s (time above its ``REFUSE_SECONDS`` refused
unless forced, memory above what is available always), plus: a store larger than the free disk
space is always refused, and one of more than :data:`MAX_FILES` files unless forced. The message
names all three figures (time, memory, store size) and how to lower them.
"""

from __future__ import annotations

import shutil

from ..errors import EloInputError
from .store import ERROR_CHARS, WORKER_CHARS

#: Bytes in memory per point while the store is created (status int8, error <U240, worker <U64,
#: each built by numpy and copied about twice on the way into Zarr).
CREATE_BYTES_PER_POINT = 3 * (1 + 4 * ERROR_CHARS + 4 * WORKER_CHARS)
#: Smallest space one chunk file takes on disk (a file-system block).
FILE_BLOCK_BYTES = 4096
#: Per-point bookkeeping variables (status, error, worker, render_seconds, worker_rss_mb,
#: finished_at, worker_cpu_s) and one claim file per point while it renders.
BOOKKEEPING_FILES = 8
#: More chunk files than this is refused unless forced: a typo (10^6 points) would otherwise
#: spend minutes creating millions of files.
MAX_FILES = 2_000_000
#: Seconds per point besides the render (metrics, Zarr writes, Dask), measured at 64^2.
OVERHEAD_SECONDS = 0.02


def estimate(spec, probe, layout: dict, workers: int) -> dict:
    """The sweep's estimated cost: ``seconds`` (all points, this machine), ``memory_bytes`` (peak
    on this machine: the store's creation or ``workers`` renders at once), ``store_bytes``,
    ``files``, and what the per-point figure was taken at (``spp``, ``events``, ``resolution``)."""
    from ..budget import estimate as render_estimate

    events = max([spec.events] + [v for a in spec.axes for m in a.members if m.key == "events" for v in m.values])
    qualities = {spec.quality} | {v for a in spec.axes for m in a.members if m.key == "quality" for v in m.values}
    spps = [v for a in spec.axes for m in a.members if m.key == "spp" for v in m.values]
    saved = probe.integrator.options
    try:
        probe.configure(events=events)
        if spps or spec.spp:
            spp = max(spps + ([spec.spp] if spec.spp else []))
        else:
            spp = max(probe.set_quality(q) for q in sorted(qualities))
        traced = int(probe.integrator.traced_events())
        channels = len(probe.integrator.channel_names()) + 1
    finally:
        probe.integrator.configure(saved)
    resolution = tuple(int(v) for v in probe.sensor.resolution)
    one = render_estimate(resolution, channels, spp, traced, 2 if spp > 1 else 1)
    renders = 2 if spec.surface is not None else 1
    n = spec.n_points
    seconds = n * (renders * one["render_seconds"] + OVERHEAD_SECONDS)
    h, w = layout["image_shape"]
    image_bytes = len(layout["channels"]) * h * w * 4
    variables = len(layout["channels"]) + len(layout["metrics"]) + BOOKKEEPING_FILES
    files = n * variables
    store_bytes = n * image_bytes + files * FILE_BLOCK_BYTES
    memory = max(n * CREATE_BYTES_PER_POINT, max(1, workers) * one["memory_bytes"])
    return {"seconds": seconds, "memory_bytes": memory, "store_bytes": store_bytes, "files": files,
            "spp": spp, "events": events, "resolution": resolution, "points": n}


def check(spec, probe, layout: dict, output, *, workers: int, force: bool = False) -> dict:
    """Refuse a sweep whose estimate is out of bounds (see the module docstring); returns the
    estimate. Raises EloInputError (one line with the figures)."""
    from ..budget import REFUSE_SECONDS, human_bytes, human_seconds, memory_limit

    est = estimate(spec, probe, layout, workers)
    w, h = est["resolution"]
    figures = (f"{est['points']} points at {w}x{h} px, {est['spp']} spp, {est['events']} event(s): about "
               f"{human_seconds(est['seconds'])} on this machine, {human_bytes(est['memory_bytes'])} of memory, "
               f"a store of {human_bytes(est['store_bytes'])} in {est['files']:,} files")
    hint = "lower the points, spp or resolution (or split the sweep)"
    available, source = memory_limit()
    if available is not None and est["memory_bytes"] > available:
        raise EloInputError(f"{spec.source}: {figures}; {human_bytes(available)} of memory is {source}; {hint}")
    try:
        free = shutil.disk_usage(output.parent).free
    except OSError:
        free = None
    if free is not None and est["store_bytes"] > free:
        raise EloInputError(f"{spec.source}: {figures}; {human_bytes(free)} is free in {output.parent}; {hint}")
    if force:
        return est
    if est["seconds"] > REFUSE_SECONDS:
        why = f"work over {human_seconds(REFUSE_SECONDS)} is refused as likely a mistake"
    elif est["files"] > MAX_FILES:
        why = f"a store of over {MAX_FILES:,} files is refused as likely a mistake"
    else:
        return est
    raise EloInputError(f"{spec.source}: {figures}; {why}: {hint}, or pass --yes (Python: force=True) to run it")
