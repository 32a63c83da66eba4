"""What a render or an inversion will cost, estimated before it starts, so that a mistyped number
costs one line, not an hour or a crash.

* Memory above what this process can get (:func:`memory_limit`: the machine's MemAvailable, the
  process's own address-space limit ``ulimit -v`` and its cgroup's memory.max, whichever is
  lowest) is always refused: the work could only end in a MemoryError or a crash.
* Time above :data:`REFUSE_SECONDS` is refused unless the user asks for it (CLI ``--yes``,
  Python ``force=True``): such work is almost always a mistyped number (``--spp 1000000000``).
* Time above :data:`NOTE_SECONDS` gets a note with the estimate.

:func:`check_work` is the one rule; :func:`check_render` and :func:`check_inversion` estimate
their work and call it. The figures are measured on this project's reference machine (2 CPU
cores, llvm_ad_mono) and are meant to be right within a factor of two.
"""

from __future__ import annotations

import math
import os

from .errors import EloInputError

#: Resident memory of a render = a base (Mitsuba, Dr.Jit's caches, the scene) + bytes per pixel and
#: film channel (Mitsuba's film and its weight, the developed tensor, the numpy planes): fitted on
#: athene_flat (13 channels: 235 MB + 280 B/px) and flat_plate (5 channels: 84 B/px) at 750^2 and
#: 1500^2. Several passes add float64 sums per channel.
BASE_BYTES = 250e6
BYTES_PER_PIXEL_CHANNEL = 24
BYTES_PER_PIXEL_CHANNEL_PASSES = 32
#: Samples (pixel x spp x traced event) per second on 2 cores: flat_plate, --quality scene, 512^2 at
#: 64 spp renders 16.8 M samples in 8 s. The presets' quadrature is faster; this bounds from above.
SAMPLES_PER_SECOND_2_CORES = 2e6
#: Every traced event is unrolled into the kernel: its compile time grows with events^2
#: (athene_flat on 2 cores: events 2, 4, 8 -> 4, 23, 79 s beyond the start-up).
COMPILE_SECONDS_PER_EVENT2 = 1.3
#: Detector points sampled per event are unrolled into the kernel too (a shadow ray each): the time
#: to trace and compile them grows faster than their number (flat_plate, 4 detectors, --quality
#: scene on 2 cores: --detector-samples 64 / 256, i.e. 256 / 1024 points, add 12 / 140 s).
COMPILE_SECONDS_PER_DETECTOR_POINT = 0.017
COMPILE_SECONDS_PER_DETECTOR_POINT2 = 1.2e-4
#: Memory of the traced kernel per unrolled detector point (same measurement: 0.7 GB at 1024).
KERNEL_BYTES_PER_DETECTOR_POINT = 0.5e6
#: Work estimated to take longer than this gets a note with the estimate (and a Ctrl-C hint).
NOTE_SECONDS = 60.0
#: Work estimated to take longer than this is refused unless asked for (CLI ``--yes``, Python
#: ``force=True``): 4 hours, beyond any render or inversion this package's own studies run
#: (the full validation takes minutes) and well short of what a mistyped number asks for.
REFUSE_SECONDS = 4 * 3600.0

#: Resident memory of an inversion (``invert``, :func:`~elo_mitsuba.analysis.inversion.invert_heights`)
#: = a base (numpy, scipy, the four images read) + bytes per pixel (the linearised model's partials
#: per detector and disc node, the normal equations, the coarse scales): fitted on the corrugated
#: sheet at 128^2-512^2 and the 1500^2 figure of issue 23 (peak 4.2 GB).
INVERSION_BASE_BYTES = 200e6
INVERSION_BYTES_PER_PIXEL = 1800
#: Seconds per pixel and Gauss-Newton step on 2 cores (corrugated sheet at 512^2: 2.4 s per step;
#: an uncertainty probe costs a third of a step, counted here as one; the set-up as two).
INVERSION_SECONDS_PER_PIXEL_STEP = 1e-5
#: What an inversion costs whatever its size (imports, the model's kernels compiled, the model
#: gradient of the start, the local refinement of a small field): the melt plate at 32^2 on 2
#: cores takes 8.9 s with --uncertainty-probes 0, where the steps alone were estimated at 0.3 s.
#: An uncertainty probe costs what the per-pixel figure says: 4000 probes added 39 s at 32^2
#: (9.5e-6 s per pixel and probe).
INVERSION_FIXED_SECONDS = 10.0


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _address_space_left() -> int | None:
    """RLIMIT_AS (``ulimit -v``) less the address space this process already uses; None unlimited."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY or soft < 0:
        return None
    used = 0
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    used = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return max(0, soft - used)


def _read_int(path) -> int | None:
    try:
        text = open(path).read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _cgroup_left() -> int | None:
    """The least memory left under the limits of this process's cgroup and its ancestors
    (v2 memory.max, v1 memory.limit_in_bytes): limit - usage + the reclaimable page cache."""
    try:
        lines = open("/proc/self/cgroup").read().splitlines()
    except OSError:
        return None
    found = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        if parts[0] == "0" and parts[1] == "":  # v2
            root, files = "/sys/fs/cgroup", ("memory.max", "memory.current", "inactive_file")
        elif "memory" in parts[1].split(","):  # v1
            root, files = "/sys/fs/cgroup/memory", ("memory.limit_in_bytes", "memory.usage_in_bytes",
                                                    "total_inactive_file")
        else:
            continue
        rel = parts[2].strip("/")
        levels = rel.split("/") if rel else []
        for k in range(len(levels), -1, -1):  # the cgroup itself, then each ancestor
            folder = os.path.join(root, *levels[:k])
            limit, usage = _read_int(os.path.join(folder, files[0])), _read_int(os.path.join(folder, files[1]))
            if limit is None or usage is None or limit >= 1 << 60:  # "max" or unlimited
                continue
            cache = 0
            try:
                for stat_line in open(os.path.join(folder, "memory.stat")):
                    key, _, value = stat_line.partition(" ")
                    if key == files[2]:
                        cache = int(value)
            except (OSError, ValueError):
                pass
            found.append(max(0, limit - usage + cache))
    return min(found) if found else None


def memory_limit() -> tuple[int | None, str]:
    """(bytes this process can still allocate, what sets that figure): the least of the machine's
    MemAvailable, the address space left under ``ulimit -v`` (RLIMIT_AS) and the memory left under
    the cgroup's limit; (None, "unknown") where none can be read."""
    limits = [(v, what) for v, what in ((_meminfo_available(), "available on this machine"),
                                         (_address_space_left(), "left under this process's 'ulimit -v'"),
                                         (_cgroup_left(), "left under this process's cgroup memory limit"))
              if v is not None]
    return min(limits) if limits else (None, "unknown")


def available_memory() -> int | None:
    """Bytes of memory this process can still allocate (:func:`memory_limit`), None if unknown."""
    return memory_limit()[0]


def check_work(seconds: float, memory_bytes: float, force: bool = False, *, what: str = "this work",
               hint: str = "", available: int | None = None) -> None:
    """The one rule for unbounded work, checked before it starts; raises :class:`EloInputError`.

    Parameters
    ----------
    seconds, memory_bytes : float
        The work's estimated wall time and peak resident memory.
    force : bool
        The user asked for it (CLI ``--yes``, Python ``force=True``): a long estimate is allowed.
        Memory is refused regardless: it cannot be bought with patience.
    what : str
        How the message names the work (``"a 512x512 render of 1e+09 spp"``).
    hint : str
        What to lower instead (``"lower --spp"``).
    available : int, optional
        Bytes available (default :func:`memory_limit`; tests pass their own).

    Raises
    ------
    EloInputError
        Memory above what is available (naming what sets the limit), or, without ``force``, time
        above :data:`REFUSE_SECONDS`.

    Examples
    --------
    >>> check_work(10.0, 1e6, available=10**9)                 # 10 s, 1 MB: fine
    >>> check_work(1e6, 1e6, what="a long sweep", hint="fewer points", available=10**9)
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: ...
    >>> check_work(1e6, 1e6, force=True, available=10**9)     # asked for: allowed
    """
    source = "available"
    if available is None:
        available, source = memory_limit()
    hint = f"; {hint}" if hint else ""
    if available is not None and memory_bytes > available:
        raise EloInputError(f"{what} needs about {human_bytes(memory_bytes)} of memory, "
                            f"{human_bytes(available)} is {source}{hint}")
    if seconds > REFUSE_SECONDS and not force:
        raise EloInputError(f"{what} would take about {human_seconds(seconds)} (estimate; work over "
                            f"{human_seconds(REFUSE_SECONDS)} is refused as likely a mistake){hint}, or pass "
                            "--yes (Python: force=True) to run it anyway")


def human_bytes(n: float) -> str:
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n / 1e3:.3g} kB"


def human_seconds(s: float) -> str:
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    if s < 2 * 86400:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.3g} days"


def detector_points(integrator) -> tuple[int, int]:
    """(detector points unrolled into the kernel, points sampled per path and event) of an
    integrator (plugins/integrator_elo.py): each detector's ``detector_samples`` on the 1st event
    (none where the quadrature integrates it) and ``bounce_detector_samples`` on each of the
    ``bounce_samples`` continuation paths of every later event."""
    detectors = len(getattr(integrator, "detectors", ())) or 1
    first = 0 if getattr(integrator, "detector_sampling", "") == "quadrature" else int(integrator.detector_samples)
    later = max(0, integrator.traced_events() - 1)
    bounce = int(getattr(integrator, "bounce_detector_samples", 1) or 1)
    paths = int(getattr(integrator, "bounce_samples", 1) or 1)
    unrolled = detectors * (first + later * paths * bounce)
    return unrolled, max(1, first, bounce if later else 1)


def estimate(resolution, channels: int, spp: int, traced_events: int, passes: int,
             detector_points: tuple[int, int] = (0, 1)) -> dict:
    """Memory (bytes), samples and seconds (render, kernel compilation) of one render;
    ``detector_points``: :func:`detector_points` of its integrator.

    Parameters
    ----------
    resolution : (int, int)
        Film size (W, H) in pixels.
    channels : int
        Film channels (detector channels + 1).
    spp : int
        Samples per pixel.
    traced_events : int
        Scattering events traced per sample.
    passes : int
        Passes of the kernel.
    detector_points : (int, int)
        :func:`detector_points` of the integrator.

    Returns
    -------
    dict
        ``memory_bytes`` (bytes), ``samples``, ``render_seconds`` and ``compile_seconds`` (s).

    Examples
    --------
    >>> work = estimate((64, 64), channels=5, spp=16, traced_events=1, passes=1)
    >>> work["samples"], work["memory_bytes"] > 0, work["render_seconds"] < 1
    (65536, True, True)
    """
    w, h = (int(v) for v in resolution)
    pixels = w * h
    unrolled, per_path = (int(v) for v in detector_points)
    per = BYTES_PER_PIXEL_CHANNEL_PASSES if passes > 1 else BYTES_PER_PIXEL_CHANNEL
    samples = pixels * int(spp) * max(1, int(traced_events)) * max(1, per_path)
    cores = max(1, os.cpu_count() or 1)
    compile_s = COMPILE_SECONDS_PER_EVENT2 * traced_events ** 2 if traced_events > 2 else 0.0
    compile_s += COMPILE_SECONDS_PER_DETECTOR_POINT * unrolled + COMPILE_SECONDS_PER_DETECTOR_POINT2 * unrolled ** 2
    return {
        "memory_bytes": BASE_BYTES + pixels * channels * per + KERNEL_BYTES_PER_DETECTOR_POINT * unrolled,
        "samples": samples,
        "render_seconds": samples / (SAMPLES_PER_SECOND_2_CORES * cores / 2),
        "compile_seconds": compile_s,
    }


def fits_in_memory(resolution, channels: int, spp: int, traced_events: int, passes: int,
                   available: int | None = None, *, detector_points: tuple[int, int] = (0, 1)) -> bool:
    """Whether a render's estimated memory (:func:`estimate`) fits in ``available`` bytes
    (default :func:`memory_limit`; unknown counts as fitting, as :func:`check_work` does): one
    pass that holds both halves of a render's channels is taken only where it fits, two passes
    need less.

    Examples
    --------
    >>> fits_in_memory((1500, 1500), 25, 1, 2, 1, available=10**10)
    True
    >>> fits_in_memory((10**5, 10**5), 25, 1, 2, 1, available=10**10)
    False
    """
    if available is None:
        available = memory_limit()[0]
    memory = estimate(resolution, channels, spp, traced_events, passes, detector_points)["memory_bytes"]
    return available is None or memory <= available


def check_render(resolution, channels: int, spp: int, traced_events: int, passes: int,
                 available: int | None = None, *, detector_points: tuple[int, int] = (0, 1),
                 force: bool = False) -> list[str]:
    """Refuse a render that cannot fit in memory or (without ``force``) would run longer than
    :data:`REFUSE_SECONDS` (:func:`check_work`); return notes on long ones.

    Raises
    ------
    EloInputError
        When the estimated memory exceeds what is available (``available`` bytes; default
        :func:`memory_limit`), naming both numbers and what sets them; or the time, with the
        estimate and how to ask for it anyway.
    """
    est = estimate(resolution, channels, spp, traced_events, passes, detector_points)
    w, h = (int(v) for v in resolution)
    seconds = est["render_seconds"] + est["compile_seconds"]
    points = f", {detector_points[0]} detector points in the kernel" if detector_points[0] > 64 else ""
    check_work(seconds, est["memory_bytes"], force, available=available,
               what=f"a {w}x{h} render with {channels - 1} channels",
               hint=f"{est['samples']:.3g} samples ({spp} spp x {traced_events} event(s) per pixel{points}); lower "
                    "the resolution (memory grows with its square), --spp, --events or --detector-samples")
    notes = []
    if est["compile_seconds"] > NOTE_SECONDS / 2:
        notes.append(f"{traced_events} traced events{points}: compiling the kernel takes about "
                     f"{human_seconds(est['compile_seconds'])} (it grows with events^2 and the detector points; "
                     "the event shares printed after a render show how many events matter)")
    if est["render_seconds"] > NOTE_SECONDS:
        notes.append(f"{est['samples']:.3g} samples ({w}x{h} px x {spp} spp x {traced_events} event(s)): up to about "
                     f"{human_seconds(est['render_seconds'])} (progress below; Ctrl-C stops it)")
    return notes


def estimate_inversion(shape, iterations: int, scales: int, uncertainty_probes: int) -> dict:
    """Peak memory (bytes) and the longest time (seconds) of an inversion of ``shape`` (H, W):
    :data:`INVERSION_FIXED_SECONDS`, the set-up (two steps), ``iterations`` steps at full
    resolution, twice where coarse-to-fine runs (``scales`` > 1), a third more for the coarse
    scales, and one step per uncertainty probe.

    Examples
    --------
    >>> estimate_inversion((32, 32), 10, 4, 100000)["seconds"] > NOTE_SECONDS   # 2 cores: about 17 min
    True
    """
    pixels = int(shape[0]) * int(shape[1])
    steps = 2 + max(1, int(iterations)) * (2 + 1 / 3 if int(scales) > 1 else 1) + int(uncertainty_probes)
    cores = max(1, os.cpu_count() or 1)
    return {"memory_bytes": INVERSION_BASE_BYTES + INVERSION_BYTES_PER_PIXEL * pixels,
            "seconds": INVERSION_FIXED_SECONDS + steps * pixels * INVERSION_SECONDS_PER_PIXEL_STEP / (cores / 2),
            "steps": steps}


def check_inversion(shape, iterations: int, scales: int, uncertainty_probes: int, force: bool = False,
                    available: int | None = None) -> list[str]:
    """Refuse an inversion that cannot fit in memory or (without ``force``) would run longer than
    :data:`REFUSE_SECONDS` (:func:`check_work`), before it starts; return a note when it is
    estimated to take longer than :data:`NOTE_SECONDS` (as :func:`check_render`)."""
    est = estimate_inversion(shape, iterations, scales, uncertainty_probes)
    h, w = (int(v) for v in shape)
    what = (f"inverting {w}x{h} px ({math.ceil(est['steps'])} steps at most, counting "
            f"{int(uncertainty_probes)} uncertainty probes)")
    check_work(est["seconds"], est["memory_bytes"], force, available=available, what=what,
               hint="crop or bin the images (memory grows with the pixels), or lower --iterations or "
                    "--uncertainty-probes")
    if est["seconds"] > NOTE_SECONDS:
        return [f"{what}: up to about {human_seconds(est['seconds'])} (estimate; Ctrl-C stops it)"]
    return []
