"""Strata for a few samples of one point: cells of the unit square (rows x columns as square as n
allows, one sample per cell, jittered, each weighted by its cell's area: unbiased for any n, the
cells partition the square), used for the detector points of ``detector_sampling = stratified``
and, where g_BSE's tables are not available, for the continuation paths a sample splits into
(``bounce_samples``); the s x s grid of the far field's cheap samples (:func:`stratum`); the
split of the continuation paths between g_BSE's two components (:func:`allocated`,
:func:`group_point`); and one point set spread over all the samples of a geometry class
(:func:`spread_point`, and :func:`spread_later` for the later continuations)."""

import math

import drjit as dr
import mitsuba as mi

_GOLDEN = 0.6180339887498949
#: The golden ratio's fractional part in 32-bit fixed point: (i * _GOLDEN_U32) mod 2^32 / 2^32 is
#: frac(i * golden) without the float32 rounding of a large i * golden.
_GOLDEN_U32 = 2654435769
#: 1/g, 1/g^2, 1/g^3 (g = 1.22074408..., the real root of x^4 = x + 1) in 32-bit fixed point: the
#: steps of a 3D Kronecker (R3) sequence, frac(i alpha), low-discrepancy in every projection.
_R3_U32 = (3518319155, 2882110345, 2360945575)
#: 1/p, 1/p^2 (p = 1.32471795..., the plastic number, x^3 = x + 1) in 32-bit fixed point: the steps
#: of a 2D Kronecker (R2) sequence, low-discrepancy in the plane (a pair of steps chosen apart,
#: such as the golden ratio's and 1/p, nearly repeat: 7 (1/p - golden) = 0.96).
_R2_U32 = (3242174889, 2447445414)
#: Most continuation paths per sample for which a class's point set also picks their components
#: (:func:`spread_pick`); above it each sample counts its own (:func:`spread_point`).
PICK_MAX_PATHS = 4
#: The largest float32 below 1: a point of a stratum must stay inside the unit square.
_BELOW_ONE = 0.99999994


def strata_cells(n: int) -> list[tuple[int, int, int, int]]:
    """The n cells as (row, column, columns in that row, rows), row-major: ``isqrt(n)`` rows, the
    columns spread over them (rows differ by at most one column)."""
    rows = max(1, int(math.isqrt(n)))
    cols = [n // rows + (1 if r < n % rows else 0) for r in range(rows)]
    return [(r, c, cols[r], rows) for r in range(rows) for c in range(cols[r])]


def stratum(i, s, u):
    """The point of cell ``i`` (row-major, s x s cells of the unit square) at offset ``u`` in it."""
    row = i // s
    col = i - row * s
    return mi.Point2f((mi.Float(col) + u.x) / s, (mi.Float(row) + u.y) / s)


def cell_area(cell) -> float:
    """The cell's area: its weight in an estimate that takes one sample per cell."""
    _, _, n_cols, rows = cell
    return 1.0 / (rows * n_cols)


def cell_point(cell, u):
    """The point at offset ``u`` (uniform on the unit square) inside ``cell``."""
    row, col, n_cols, rows = cell
    return mi.Point2f((col + u.x) / n_cols, (row + u.y) / rows)


def shifted_lattice(j: int, n: int, shift):
    """The j-th of n points of a randomly shifted 1D lattice, (shift + pi(j)/n) mod 1: each point
    uniform, together one per interval of 1/n. pi is a scrambled order (j*p mod n, p coprime to n
    near n/golden ratio), so that in the row-major cells above neighbouring cells take distant
    intervals."""
    p = max(1, round(_GOLDEN * n))
    while math.gcd(p, n) != 1:
        p += 1
    # j: a Python int or a UInt32 loop counter. A quotient then a sum, each rounded once: a
    # product and a sum could be fused into one FMA on one CPU and not on another, and the lobe
    # choice (u < q) would then differ between instruction sets
    u = shift + mi.Float((j * p) % n) / n
    return u - dr.floor(u)


def allocated(q, k: int, xi):
    """How many of k samples go to a component of probability q: ceil(q k - xi), xi uniform, so
    that its expectation is q k exactly (each of the k samples is then one cell of a shifted 1D
    lattice of the component choice); the rest go to the other component."""
    return dr.clip(dr.ceil(q * k - xi), 0.0, float(k))


def group_point(j: int, k: int, n_first, rot_first, rot_second, u):
    """Sample j of k when the first ``n_first`` go to one component and the others to the second:
    (is_first, its point in that component's unit square). The m-th of a group of n takes the
    m-th of n strata along x, jittered by ``u``, and along y the m-th point of a golden-ratio
    lattice rotated by the group's ``rot_*``: each point uniform (so every sample is unbiased
    however the groups split), the group spread over its square."""
    is_first = mi.Float(j) < n_first
    m = dr.select(is_first, mi.Float(j), mi.Float(j) - n_first)
    n = dr.maximum(dr.select(is_first, n_first, float(k) - n_first), 1.0)
    x = dr.minimum((m + u) / n, _BELOW_ONE)
    y = dr.select(is_first, rot_first, rot_second) + m * _GOLDEN
    return is_first, mi.Point2f(x, y - dr.floor(y))


def spread_point(j: int, k: int, n_first, sample, n_samples, shift_x, rot_first, rot_second, u):
    """As :func:`group_point`, but one point set for all ``n_samples`` samples that share their
    estimate (the pixels of a geometry class, ``bounce_share``): path j of sample ``sample`` (0 ..
    n_samples - 1, UInt32) takes index i = sample k + m of its group (m its rank in the group), x
    = (i + u) / (n_samples k) + shift_x and y = i golden + rot, both mod 1. The class's paths
    then stratify the sample space together (not k at a time), and with ``shift_x`` and ``rot_*``
    uniform (a random shift per class and render) every point is uniform on the square: each
    pixel's estimate stays unbiased."""
    is_first = mi.Float(j) < n_first
    m = dr.select(is_first, mi.UInt32(j), mi.UInt32(j) - mi.UInt32(n_first))
    i = sample * k + m
    n = mi.Float(n_samples * k)
    x = mi.Float(i) / n + u / n + shift_x
    y = mi.Float(i * _GOLDEN_U32) * (1.0 / 4294967296.0) + dr.select(is_first, rot_first, rot_second)
    return is_first, mi.Point2f(dr.minimum(x - dr.floor(x), _BELOW_ONE), y - dr.floor(y))


def spread_pick(j: int, k: int, sample, n_samples, q, shift_pick, shift_x, rot, u):
    """As :func:`spread_point`, for few paths per sample (k <= :data:`PICK_MAX_PATHS`): (is_first,
    its point in that component's unit square) for a first component of probability ``q``, the
    class's point set making the choice too. Path i = sample k + j takes the first component where
    i a1 + ``shift_pick`` < q and the point ((i + u) / (n_samples k) + ``shift_x``, i a2 + ``rot``),
    all mod 1, (a1, a2) the steps of a 2D Kronecker (R2) sequence. A count of first-component
    paths drawn per sample (:func:`spread_point`) leaves each component a random subset of the
    class's points at k = 1 or 2; here the class's paths stratify the choice and the square
    together (from k = 8 on the count does as well or better: tests/test_strata.py).
    The choice compares with each path's own q, so pixels of one class whose q differs (the beam's
    incidence changes across a block) keep their own mixture. With the shifts uniform (one random
    shift each per class and render) every path's choice and point are as one independent
    sample's: each pixel's estimate stays unbiased."""
    i = sample * k + mi.UInt32(j)
    n = mi.Float(n_samples * k)
    x = mi.Float(i) / n + u / n + shift_x
    y = mi.Float(i * _R2_U32[1]) * (1.0 / 4294967296.0) + rot
    pick = mi.Float(i * _R2_U32[0]) * (1.0 / 4294967296.0) + shift_pick
    return (pick - dr.floor(pick) < q,
            mi.Point2f(dr.minimum(x - dr.floor(x), _BELOW_ONE), y - dr.floor(y)))


def spread_later(i, shifts):
    """The sample point (u1, u2) of a later continuation (events >= 3) of path ``i`` (UInt32, its
    index among the class's paths): the i-th point of a 3D Kronecker sequence, shifted by the
    class's ``shifts`` (three uniform numbers per class and render) mod 1. Each point is uniform
    (the shifts), and the class's paths spread over g_BSE's component choice and direction
    together; its steps differ from :func:`spread_point`'s, so the two continuations of a path do
    not repeat each other."""
    u = [mi.Float(i * a) * (1.0 / 4294967296.0) + s for a, s in zip(_R3_U32, shifts)]
    u = [dr.minimum(v - dr.floor(v), _BELOW_ONE) for v in u]
    return u[0], mi.Point2f(u[1], u[2])
