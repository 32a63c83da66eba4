"""The passes of a render: its error estimate's two halves (:func:`~elo_mitsuba.error_estimate.split_render`),
each rendered in passes of at most a pass's samples and summed, or both halves in one pass.

* A 1st event that every pass computes alike (the quadrature under a single-ray beam) is traced in
  the first pass only; the later passes take its planes.
* At 1 spp with events >= 2, where the integrator can (``merges_halves``: that 1st event, no
  sampled far field), one pass traces both halves' continuation paths, each half from its own
  seed: the second pass's beam rays, set-up and film are saved (athene_flat 1500^2, `default`:
  1.27 -> 1.08 s; corrugated_chamber 1.84 -> 1.76 s; interleaved in one process, the shared 2-core
  AMD EPYC, 2026-12-06), where both halves' channels fit in memory (``merge``).
* A render of the 1st event alone whose first half draws nothing at random stops after it
  (:func:`~elo_mitsuba.error_estimate.first_half_suffices`).
"""

from __future__ import annotations

import time

import numpy as np

from .error_estimate import DETERMINISTIC, first_half_suffices
from .sample_counts import each_pass


def may_merge(spp: int, halves, integrator) -> bool:
    """Whether the halves of ``halves`` may render in one pass (1 spp, events >= 2 traced: each
    half takes half the continuation paths), if the integrator's set-up allows it (the film then
    holds both halves' channels)."""
    return spp == 1 and len(halves) == 2 and halves[0][1] is not None and integrator.traced_events() > 1


def render_passes(integrator, scene, halves, passes, spp: int, seed: int, report, first_status, merge=True):
    """Render the halves of a split render, in one pass or in passes of each.

    Parameters
    ----------
    integrator
        The scene's ``elo`` integrator (its options are set per half and left at the last half's).
    scene
        The Mitsuba scene (its sensor 0).
    halves : list of (int, EloOptions or None)
        :func:`~elo_mitsuba.error_estimate.split_render`'s halves.
    passes : list
        Per half its passes' sizes (:func:`~elo_mitsuba.sample_counts.pass_sizes`).
    spp, seed : int
        The render's samples per pixel and seed (pass p renders with seed ``seed * 65537 + p``).
    report : callable
        ``report(samples done, seconds)`` after each pass.
    first_status : str or None
        The status :func:`~elo_mitsuba.error_estimate.split_render` forced.
    merge : bool
        One pass for both halves where :func:`may_merge` and the integrator allow it (False:
        two passes, e.g. where both halves' channels would not fit in memory).

    Returns
    -------
    sums : list of ndarray (channels, H, W)
        Each half's mean over its passes.
    first_status : str or None
        ``first_status``, or :data:`~elo_mitsuba.error_estimate.DETERMINISTIC` where the first half sufficed.
    """
    t0 = time.perf_counter()
    seeds = [(seed * 65537 + p) % (1 << 32) for p in range(sum(1 for sizes in passes for _ in each_pass(sizes)))]
    if merge and may_merge(spp, halves, integrator):  # one pass for both, where the set-up allows it
        integrator.configure(halves[0][1])
        both = integrator.render_halves(scene, 0, seeds[:2], options=[options for _, options in halves])
        if both is not None:
            report(sum(n for n, _ in halves), time.perf_counter() - t0)
            return both, first_status
    sums, first, done, p = [], None, 0, 0
    for (n_half, options), sizes in zip(halves, passes):
        if options is not None:
            integrator.configure(options)
        acc = None
        for n in each_pass(sizes):
            planes, _ = integrator.render_planes(scene, 0, seeds[p], n, first=first)
            if first is None and integrator.reuses_first_event():
                first = integrator.first_event_planes(planes)
            if acc is None and n == n_half:
                acc = planes  # one pass: its own mean
            else:
                if acc is None:
                    acc = np.zeros(planes.shape, np.float64)
                acc += planes * (n / n_half)
            del planes
            p += 1
            done += n
            report(done, time.perf_counter() - t0)
        sums.append(acc)
        if first_half_suffices(spp, integrator, halves):  # the other half: this render again
            return sums, DETERMINISTIC
    return sums, first_status
