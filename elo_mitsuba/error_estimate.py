"""The per-render error estimate: two independent halves of the samples, A and B (Dr.Jit, numpy).

A render is the weighted mean ``w_a A + w_b B`` of two independent estimates with ``w_a + w_b = 1``
(the halves' shares of the samples). For unbiased halves with variances s^2/w_a and s^2/w_b
(s^2 the variance of the mean), ``E[(A - B)^2] = s^2 / (w_a w_b)``, so ::

    err = sqrt(w_a w_b) |A - B|        (|A - B| / 2 for equal halves)

estimates the standard error of each pixel of the mean. One pixel's estimate has one degree of
freedom (it is itself noisy); averaged over many pixels it is accurate (tests/test_error_estimate.py,
benchmarks section ``presets``). It measures noise only: a bias common to both halves (e.g. the
bounce filter's on relief) is not seen, which is why the presets do not filter where it would
be biased (:func:`elo_mitsuba.options.quality_options`).

The relative error of a pixel is ``err / max(|value|, FLOOR x mean |value|)``, as in benchmarks/
(the floor keeps dark pixels from dominating).
"""

from __future__ import annotations

import math

import numpy as np

from .options import half_budgets, paths_per_sample
from .schema import event_channel

#: Relative errors are taken against ``max(|value|, FLOOR x the image mean of |value|)``, as in benchmarks/.
FLOOR = 0.05
#: Status of a channel's estimate: from the halves, or none because the channel has no sampling
#: error (both halves identical: a deterministic estimator such as the 1st event by the triangle
#: quadrature with a single-ray beam, or a channel that is exactly zero), or not estimated.
ESTIMATED, DETERMINISTIC, NOT_ESTIMATED = "estimated", "deterministic", "not estimated"
#: Halves closer than this, relative to the channel's largest value, are one deterministic result:
#: float32 sums of a pixel's samples in another order differ in the last bits (measured <= 2e-6).
ROUNDING = 1e-5


def same_result(a: np.ndarray, b: np.ndarray) -> bool:
    """True when the halves agree to float32 rounding (:data:`ROUNDING`): no sampling error."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    scale = max(float(np.max(np.abs(a), initial=0.0)), float(np.max(np.abs(b), initial=0.0)))
    return float(np.max(np.abs(a - b), initial=0.0)) <= ROUNDING * scale


def halves_error(a: np.ndarray, b: np.ndarray, share_a: float) -> np.ndarray:
    """Per-pixel standard error of ``share_a a + (1 - share_a) b`` from the two independent halves.

    Parameters
    ----------
    a, b : ndarray
        The two halves' estimates of one channel (same shape).
    share_a : float
        The share of ``a`` in the mean, in (0, 1).

    Returns
    -------
    ndarray, float32
        ``sqrt(share_a (1 - share_a)) |a - b|``.
    """
    w = float(share_a)
    diff = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))
    return (np.sqrt(w * (1.0 - w)) * diff).astype(np.float32)


def relative(err: np.ndarray, value: np.ndarray) -> np.ndarray:
    """``err / max(|value|, FLOOR x mean |value|)`` per pixel (zero where the channel is zero)."""
    value = np.abs(np.asarray(value, np.float64))
    floor = FLOOR * float(value.mean()) if value.size else 0.0
    denom = np.maximum(value, floor)
    return np.divide(np.asarray(err, np.float64), denom, out=np.zeros(value.shape), where=denom > 0)


def summarise(value: np.ndarray, err: np.ndarray | None, status: str) -> dict:
    """The summary of one channel's estimate: ``status``, ``rms_rel`` (RMS over pixels of the
    relative error), ``p99_rel`` (99th percentile) and ``rms_abs`` (RMS standard error, channel units);
    the numbers are 0 for a deterministic channel and absent when not estimated."""
    if status == DETERMINISTIC:
        return {"status": DETERMINISTIC, "rms_rel": 0.0, "p99_rel": 0.0, "rms_abs": 0.0}
    if status == NOT_ESTIMATED or err is None:
        return {"status": NOT_ESTIMATED}
    rel = relative(err, value)
    e = np.asarray(err, np.float64)
    return {"status": ESTIMATED, "rms_rel": float(np.sqrt(np.mean(rel * rel))),
            "p99_rel": float(np.percentile(rel, 99)), "rms_abs": float(np.sqrt(np.mean(e * e)))}


def describe(summary: dict) -> str:
    """One channel's estimate as text: ``0.21 % RMS (99 %: 0.6 %)``, ``deterministic (no sampling
    error)`` or ``not estimated``."""
    status = summary.get("status")
    if status == DETERMINISTIC:
        return "deterministic (no sampling error)"
    if status != ESTIMATED:
        return "not estimated"
    return f"{100 * summary['rms_rel']:.3g} % RMS (99 %: {100 * summary['p99_rel']:.3g} %)"


def percentile_99(values: np.ndarray) -> float:
    """``np.percentile(values, 99)`` (linear interpolation) of a flat array, found among the values
    above a threshold read from every 64th value (about 2 % of them) instead of partitioning all:
    at 1500^2 3 ms instead of 9 ms a channel. Falls back to the whole array where the threshold
    leaves too few (ties)."""
    v = np.asarray(values).reshape(-1)
    n = v.size
    if n < 4096:
        return float(np.percentile(v, 99))
    k = 0.99 * (n - 1)
    lo = int(math.floor(k))
    hi = min(lo + 1, n - 1)
    sample = v[::64]
    threshold = np.partition(sample, int(0.98 * (sample.size - 1)))[int(0.98 * (sample.size - 1))]
    above = v >= threshold
    below = n - int(np.count_nonzero(above))
    if below > lo:  # the threshold lies above the order statistics sought: partition them all
        return float(np.percentile(v, 99))
    cand = np.partition(v[above], [lo - below, hi - below])
    a, b = float(cand[lo - below]), float(cand[hi - below])
    return a + (b - a) * (k - lo)


def combine_halves(a: np.ndarray, b: np.ndarray, share_a: float):
    """The mean of two halves of one channel, its per-pixel error and summary, in place.

    The same numbers as ``share_a a + (1 - share_a) b`` (float64, stored as float32),
    :func:`same_result`, :func:`halves_error` and :func:`summarise` (to rounding in the summary),
    in a few Dr.Jit kernels of the active Mitsuba variant (all cores; numpy's whole-image float64
    temporaries cost more than the arithmetic at 1500^2 x 12 channels, and its blocked passes ran
    on one core: 0.34 s a render at 1500^2 against 0.115 s here, benchmarks/RESULTS.md).

    Parameters
    ----------
    a, b : ndarray (H, W)
        The halves' estimates. A float32 ``a`` is overwritten by the mean and a float32 ``b`` by
        the error (other dtypes get new float32 arrays).
    share_a : float
        The share of ``a`` in the mean, in (0, 1).

    Returns
    -------
    mean : ndarray, float32
    err : ndarray, float32, or None when the halves agree (:data:`DETERMINISTIC`)
    summary : dict, as :func:`summarise`
    """
    w = float(share_a)
    if a.dtype == np.float32 and b.dtype == np.float32 and np.array_equal(a.flat[:4096], b.flat[:4096]) \
            and np.array_equal(a, b):
        # bit-identical float32 halves (a 1st event traced once and reused): the float64 mean
        # is a(1 + eps) with |eps| < 2^-50, which rounds back to a, so it is a itself
        return a, None, summarise(a, None, DETERMINISTIC)
    import drjit as dr
    import mitsuba as mi

    f32, f64 = mi.Float, mi.Float64
    n = a.size

    def load(v):
        return f32(np.ascontiguousarray(v).reshape(-1)) if v.dtype == np.float32 else f64(
            np.ascontiguousarray(v, np.float64).reshape(-1))

    x, y = load(a), load(b)
    dx, dy = f64(x), f64(y)
    # the weights and the floor as opaque values: as literals each render would compile anew
    wa, wb, k = (dr.opaque(f64, c) for c in (w, 1.0 - w, np.sqrt(w * (1.0 - w))))
    m = f32(wa * dx + wb * dy)
    e = f32(k * dr.abs(dx - dy))
    dr.eval(m, e)

    def reduce(op, v):
        return float(np.asarray(dr.block_reduce(op, v, n))[0]) if n else 0.0

    top = reduce(dr.ReduceOp.Max, dr.maximum(dr.abs(dx), dr.abs(dy)))
    top_d = reduce(dr.ReduceOp.Max, dr.abs(dx - dy))
    mean = a if a.dtype == np.float32 else np.empty(a.shape, np.float32)
    mean.reshape(-1)[...] = np.asarray(m)
    if top_d <= ROUNDING * top:  # no sampling error at all: not 0 from a split
        return mean, None, summarise(mean, None, DETERMINISTIC)
    err = b if b.dtype == np.float32 else np.empty(b.shape, np.float32)
    err.reshape(-1)[...] = np.asarray(e)
    m64, e64 = f64(m), f64(e)
    floor = dr.opaque(f64, FLOOR * reduce(dr.ReduceOp.Add, dr.abs(m64)) / n)
    denom = dr.maximum(dr.abs(m64), floor)
    rel = dr.select(denom > 0, e64 / denom, 0.0)
    dr.eval(rel)
    summary = {"status": ESTIMATED, "rms_rel": float(np.sqrt(reduce(dr.ReduceOp.Add, dr.square(rel)) / n)),
               "p99_rel": percentile_99(np.asarray(rel)),
               "rms_abs": float(np.sqrt(reduce(dr.ReduceOp.Add, dr.square(e64)) / n))}
    return mean, err, summary


def later_events_error(errors, names, events: int) -> dict | None:
    """Per detector the standard error of its events >= 2 together, from the per-channel errors
    ``errors`` (``<id>.e<k>`` -> ndarray, k >= 2; a channel without an entry has none): their
    errors added in quadrature, their correlation left out. None when no such channel has an
    error (nothing was estimated)."""
    out, found = {}, False
    for n in names:
        var = None
        for k in range(2, int(events) + 1):
            e = errors.get(event_channel(n, k))
            if e is not None:
                found = True
                var = np.asarray(e, float) ** 2 if var is None else var + np.asarray(e, float) ** 2
        out[n] = var
    if not found:
        return None
    shape = next(v.shape for v in out.values() if v is not None)
    return {n: np.zeros(shape) if v is None else np.sqrt(v) for n, v in out.items()}


#: How a render's errors were estimated, as its metadata states it.
METHOD = ("two independent halves of the samples (A, B): standard error per pixel "
          "sqrt(w_A w_B) |A - B|; relative to max(|value|, 5 % of the channel's mean)")


def split_render(spp: int, integrator, beam_fwhm: float):
    """How a render of ``spp`` samples per pixel splits into two independent halves.

    spp >= 2: the samples split in two (same options). 1 spp with events >= 2 traced: two
    renders of 1 spp with about half the continuation paths each (:func:`~elo_mitsuba.options.half_budgets`:
    where the classes share paths, k paths a sample split as ceil(k/2) and floor(k/2); the halves are
    then weighed by their paths, :func:`half_weights`).
    1 spp, 1st event only, by the quadrature with a single-ray beam: with one ray per triangle
    (``triangle`` visibility) the result is deterministic (one render, no sampling error); with
    the sampled visibility two renders (partly occluded detectors are sampled; identical halves
    are reported as deterministic), of which :meth:`elo_mitsuba.EloScene.render` keeps the first
    alone where its set-up finds no shadow ray that could be blocked (:func:`first_half_suffices`).
    1 spp of sampled detectors: one render, not estimated (one
    sample per pixel cannot be split).

    Parameters
    ----------
    spp : int
        Samples per pixel of the whole render.
    integrator
        The scene's ``elo`` integrator (its options, traced events and detector sampling).
    beam_fwhm : float
        The beam's FWHM in mm (0: a single ray).

    Returns
    -------
    halves : list of (int, EloOptions or None)
        Per half its spp and the options it renders with (None: the integrator's own).
    status : str or None
        The status forced on every channel (:data:`DETERMINISTIC`, :data:`NOT_ESTIMATED`), or None.
    """
    if spp >= 2:
        return [((spp + 1) // 2, None), (spp // 2, None)], None
    if integrator.traced_events() > 1:
        return [(1, half) for half in half_budgets(integrator.options)], None
    if integrator.detector_sampling == "quadrature" and not beam_fwhm > 0:
        if integrator.quadrature_visibility == "triangle":
            return [(1, None)], DETERMINISTIC
        return [(1, integrator.options), (1, integrator.options)], None
    return [(1, None)], NOT_ESTIMATED


def first_half_suffices(spp: int, integrator, halves) -> bool:
    """Whether a render split by :func:`split_render` may stop after its first half: 1 spp of the
    1st event alone where the set-up of that half found nothing drawn at random (a single-ray
    beam, the quadrature, no shadow ray that could be blocked: the integrator's
    ``first_event_fixed``), so that the other half would be the same render again."""
    return spp == 1 and len(halves) == 2 and integrator.traced_events() == 1 and bool(integrator.first_event_fixed)


def half_weights(halves) -> list[float]:
    """What each half of :func:`split_render` weighs in the render's mean: its samples per pixel
    where the samples split, its continuation paths per sample where a 1-spp render split them
    (the estimate of each half's events >= 2 has a variance about inversely proportional to them)."""
    if halves[0][1] is None or len(halves) < 2:
        return [float(n) for n, _ in halves]
    paths = [paths_per_sample(options) for _, options in halves]
    return paths if all(p > 0 for p in paths) else [1.0] * len(halves)


def combine_channels(names, sums, weights, forced_status):
    """The channels of a render, their per-pixel errors and summaries, from its halves.

    Parameters
    ----------
    names : list of str
        The channel names, in the order of the planes.
    sums : list of ndarray (channels, H, W)
        Each half's mean (one entry: a render that was not split); overwritten.
    weights : list of float
        What each half weighs in the mean (:func:`half_weights`).
    forced_status : str or None
        The status of every channel of a render that was not split (:func:`split_render`).

    Returns
    -------
    channels : dict of str to ndarray, float32
    errors : dict of str to ndarray, float32
        Only the channels with an estimated error.
    summary : dict of str to dict, as :func:`summarise`
    """
    if len(sums) == 1:
        planes = sums[0]
        channels = {name: np.asarray(planes[i], np.float32) for i, name in enumerate(names)}
        return channels, {}, {name: summarise(channels[name], None, forced_status) for name in names}
    share_a = weights[0] / sum(weights)
    a, b = sums
    channels, errors, summary = {}, {}, {}
    for i, name in enumerate(names):
        channels[name], err, summary[name] = combine_halves(a[i], b[i], share_a)
        if err is not None:
            errors[name] = err
    return channels, errors, summary
