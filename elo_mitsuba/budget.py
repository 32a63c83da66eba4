"""What a render will cost, estimated before it starts: memory (refused above what the machine has),
samples and kernel size (a note above a threshold), so a mistyped number costs one line, not an hour.

The figures are measured on this project's reference machine (2 CPU cores, llvm_ad_mono) and
are meant to be right within a factor of two; ``elo-mitsuba render`` prints them as notes.
"""

from __future__ import annotations

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
#: A render estimated to take longer than this gets a note with the estimate (and Ctrl-C hint).
NOTE_SECONDS = 60.0


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux: MemAvailable), None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _human_bytes(n: float) -> str:
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n / 1e3:.3g} kB"


def _human_seconds(s: float) -> str:
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    if s < 2 * 86400:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.3g} days"


def estimate(resolution, channels: int, spp: int, traced_events: int, passes: int) -> dict:
    """Memory (bytes), samples and seconds (render, kernel compilation) of one render."""
    w, h = (int(v) for v in resolution)
    pixels = w * h
    per = BYTES_PER_PIXEL_CHANNEL_PASSES if passes > 1 else BYTES_PER_PIXEL_CHANNEL
    samples = pixels * int(spp) * max(1, int(traced_events))
    cores = max(1, os.cpu_count() or 1)
    return {
        "memory_bytes": BASE_BYTES + pixels * channels * per,
        "samples": samples,
        "render_seconds": samples / (SAMPLES_PER_SECOND_2_CORES * cores / 2),
        "compile_seconds": COMPILE_SECONDS_PER_EVENT2 * traced_events ** 2 if traced_events > 2 else 0.0,
    }


def check_render(resolution, channels: int, spp: int, traced_events: int, passes: int,
                 available: int | None = None) -> list[str]:
    """Refuse a render that cannot fit in memory; return notes on long ones.

    Raises
    ------
    EloInputError
        When the estimated memory exceeds what is available (``available`` bytes; default
        :func:`available_memory`), naming both numbers and what sets them.
    """
    est = estimate(resolution, channels, spp, traced_events, passes)
    available = available_memory() if available is None else available
    w, h = (int(v) for v in resolution)
    if available is not None and est["memory_bytes"] > available:
        raise EloInputError(
            f"a {w}x{h} render with {channels - 1} channels needs about {_human_bytes(est['memory_bytes'])} of memory, "
            f"{_human_bytes(available)} is available; lower the resolution (memory grows with its square) or the events")
    notes = []
    if est["compile_seconds"] > NOTE_SECONDS / 2:
        notes.append(f"{traced_events} traced events: compiling the kernel takes about "
                     f"{_human_seconds(est['compile_seconds'])} (it grows with events^2; the event shares printed "
                     "after a render show how many matter)")
    if est["render_seconds"] > NOTE_SECONDS:
        notes.append(f"{est['samples']:.3g} samples ({w}x{h} px x {spp} spp x {traced_events} event(s)): up to about "
                     f"{_human_seconds(est['render_seconds'])} (progress below; Ctrl-C stops it)")
    return notes
