"""The strata of plugins/_strata.py: the cells partition the unit square for any count, their
areas are the weights, and the shifted lattice puts one point in each interval of 1/n."""

import numpy as np
import pytest

import elo_mitsuba as em

mi = em.ensure_variant()
import drjit as dr  # noqa: E402

from elo_mitsuba.plugins import _strata as strata  # noqa: E402


@pytest.mark.parametrize("n", [1, 2, 3, 5, 7, 8, 12, 16, 17])
def test_cells_partition_the_square(n):
    cells = strata.strata_cells(n)
    assert len(cells) == n
    assert sum(strata.cell_area(c) for c in cells) == pytest.approx(1.0, abs=1e-12)
    # a fine grid of points: each lies in exactly one cell, the one point() maps its offset from
    g = (np.arange(60) + 0.5) / 60
    x, y = [a.ravel() for a in np.meshgrid(g, g)]
    inside = np.zeros(x.size, int)
    for c in cells:
        lo = np.array(strata.cell_point(c, mi.Point2f(0.0, 0.0))).ravel()
        hi = np.array(strata.cell_point(c, mi.Point2f(1.0, 1.0))).ravel()
        assert (hi[0] - lo[0]) * (hi[1] - lo[1]) == pytest.approx(strata.cell_area(c))
        inside += (x >= lo[0]) & (x < hi[0]) & (y >= lo[1]) & (y < hi[1])
    assert np.all(inside == 1)


@pytest.mark.parametrize("n", [1, 4, 5, 8, 10, 16])
def test_shifted_lattice_has_one_point_per_interval(n):
    for shift in (0.0, 0.37, 0.999):
        u = np.array([float(strata.shifted_lattice(j, n, dr.opaque(mi.Float, shift))[0]) for j in range(n)])
        assert np.all((u >= 0) & (u < 1))
        m = ((u - shift) % 1.0) * n  # the lattice index of each point: an integer
        assert np.max(np.abs(m - np.round(m))) < 1e-4
        assert sorted(np.round(m).astype(int) % n) == list(range(n))


@pytest.mark.parametrize("k", [1, 3, 8])
def test_allocated_is_q_k_on_average_and_never_further_than_one(k):
    q = mi.Float(np.repeat(np.linspace(0.0, 1.0, 11), 4000))
    xi = mi.Float(np.tile((np.arange(4000) + 0.5) / 4000, 11))  # xi over [0, 1) evenly
    n = np.array(strata.allocated(q, k, xi)).reshape(11, 4000)
    qk = np.linspace(0.0, 1.0, 11) * k
    assert np.allclose(n.mean(axis=1), qk, atol=1e-3)
    assert np.all((n >= np.floor(qk - 1e-6)[:, None]) & (n <= np.ceil(qk + 1e-6)[:, None]))


@pytest.mark.parametrize("k, n_first", [(8, 0), (8, 3), (8, 8), (5, 2)])
def test_group_points_stratify_each_group(k, n_first):
    first, xs = [], []
    for j in range(k):
        is_first, p = strata.group_point(j, k, mi.Float(n_first), mi.Float(0.3), mi.Float(0.7), mi.Float(0.5))
        first.append(bool(is_first[0]))
        xs.append(float(p.x[0]))
        assert 0.0 <= p.x[0] < 1.0 and 0.0 <= p.y[0] < 1.0
    assert first == [j < n_first for j in range(k)]
    for group, n in ((True, n_first), (False, k - n_first)):
        cells = sorted(int(x * n) for x, f in zip(xs, first) if f == group)
        assert cells == list(range(n))  # one point in each of the group's n strata


def _toy(x, y):
    """A disc (an edge, as a shadow or a flank's rim makes) on a smooth slope; its integral over
    the unit square is pi 0.1 + (1 - cos 3) / 6 (the disc lies inside the square)."""
    return ((x - 0.4) ** 2 + (y - 0.55) ** 2 < 0.1).astype(float) + np.sin(3.0 * x) * y


def _class_estimates(points, reps, n_samples=100, k=8, q=0.37, seed=3, second=1.0):
    """``reps`` estimates of the mixture integral q f(x, y) + (1 - q) f(y, x) by ``n_samples``
    samples of k paths each (the lobe's L = allocated(q, k, xi) of them, weight 1/k), their mean
    taken as the class's estimate; ``points(rng)`` makes one estimate's point set: a function of
    (j, n_lobe) giving path j's group and point."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(reps):
        n_lobe = strata.allocated(mi.Float(q), k, mi.Float(rng.random(n_samples)))
        point = points(rng)
        total = np.zeros(n_samples)
        for j in range(k):
            is_first, p = point(j, n_lobe)
            x, y = np.array(p.x, dtype=float), np.array(p.y, dtype=float)
            assert np.all((x >= 0) & (x < 1) & (y >= 0) & (y < 1))
            total += np.where(np.array(is_first), _toy(x, y), second * _toy(y, x)) / k
        out.append(total.mean())
    return np.array(out)


def test_spread_points_are_unbiased_and_stratify_a_class_together():
    """A class's samples taking one point set (spread_point) against each sample its own k points
    (group_point): both unbiased, the spread one with less than half the noise on an integrand with
    an edge (measured: 0.0042 against 0.0110 at 100 samples of 8 paths)."""
    n, k, reps = 100, 8, 200
    exact = np.pi * 0.1 + (1.0 - np.cos(3.0)) / 6.0

    def spread(rng):
        sx, r1, r2 = (mi.Float(float(v)) for v in rng.random(3))  # the class's shifts
        return lambda j, n_lobe: strata.spread_point(j, k, n_lobe, dr.arange(mi.UInt32, n), mi.UInt32(n),
                                                     sx, r1, r2, mi.Float(rng.random(n)))

    def own(rng):
        r1, r2 = mi.Float(rng.random(n)), mi.Float(rng.random(n))  # each sample's rotations
        return lambda j, n_lobe: strata.group_point(j, k, n_lobe, r1, r2, mi.Float(rng.random(n)))

    a = _class_estimates(spread, reps, n, k)
    b = _class_estimates(own, reps, n, k)
    for est in (a, b):
        assert abs(est.mean() - exact) < 4.0 * est.std(ddof=1) / np.sqrt(reps)
    assert a.std(ddof=1) < 0.5 * b.std(ddof=1)


def test_a_spread_point_is_uniform_over_the_class_shifts():
    """Each path's point, over the class's random shifts, is uniform on the square (so each pixel's
    estimate is unbiased on its own): chi-square of a 4 x 4 histogram, for paths of both groups."""
    rng = np.random.default_rng(5)
    m, k, n = 20000, 8, 50
    n_lobe = mi.Float(3.0)
    for j in (1, 6):  # a lobe path and a diffuse one
        for sample in (0, 37):
            shifts = [mi.Float(rng.random(m)) for _ in range(3)]
            is_first, p = strata.spread_point(j, k, n_lobe, mi.UInt32(sample), mi.UInt32(n), *shifts,
                                              mi.Float(rng.random(m)))
            assert bool(is_first[0]) == (j < 3)
            h, _, _ = np.histogram2d(np.array(p.x), np.array(p.y), bins=4, range=[[0, 1], [0, 1]])
            chi2 = ((h - m / 16) ** 2 / (m / 16)).sum()
            assert chi2 < 37.7  # 15 degrees of freedom, p = 0.001


def _pick(n, k, q):
    """A class's point set that picks the components too (spread_pick) as ``_class_estimates`` takes it: path j's component and
    point."""
    def points(rng):
        sp, sx, rot = (mi.Float(float(v)) for v in rng.random(3))  # the class's shifts
        return lambda j, n_lobe: strata.spread_pick(j, k, dr.arange(mi.UInt32, n), mi.UInt32(n), mi.Float(q),
                                                     sp, sx, rot, mi.Float(rng.random(n)))
    return points


def _counted(n, k):
    """The class's point set with each sample's own count of first-component paths (spread_point,
    the count drawn by ``_class_estimates``)."""
    def points(rng):
        sx, r1, r2 = (mi.Float(float(v)) for v in rng.random(3))
        return lambda j, n_lobe: strata.spread_point(j, k, n_lobe, dr.arange(mi.UInt32, n), mi.UInt32(n), sx, r1, r2,
                                                     mi.Float(rng.random(n)))
    return points


@pytest.mark.parametrize("k", [1, 2, 4])
def test_picked_points_stratify_the_component_choice_too(k):
    """Up to PICK_MAX_PATHS paths per sample, a class's point set that picks the components too
    (spread_pick) against the same set with each sample's own count of lobe paths (spread_point:
    at small k each component then takes a random subset of the set's points) and against each
    sample's own k points (group_point), on a mixture whose components differ (an integrand with
    an edge, and its transpose at 0.3 of it): all unbiased; the picked set has less than 0.7 of
    the counted set's noise and less than half the own points' (measured at 100 samples, picked /
    counted / own: 0.0152 / 0.0339 / 0.0454 at k = 1, 0.0087 / 0.0171 / 0.0286 at k = 2, 0.0058 /
    0.0106 / 0.0187 at k = 4; at k = 8 0.0036 / 0.0036 / 0.0083, and with equal components 0.0049
    / 0.0042 / 0.0110: hence the count above PICK_MAX_PATHS)."""
    assert k <= strata.PICK_MAX_PATHS
    n, reps, q = 100, 200, 0.37
    exact = np.pi * 0.1 + (1.0 - np.cos(3.0)) / 6.0

    def own(rng):
        r1, r2 = mi.Float(rng.random(n)), mi.Float(rng.random(n))  # each sample's rotations
        return lambda j, n_lobe: strata.group_point(j, k, n_lobe, r1, r2, mi.Float(rng.random(n)))

    a, b, c = (_class_estimates(points, reps, n, k, q, second=0.3) for points in (_pick(n, k, q), _counted(n, k), own))
    for est in (a, b, c):
        assert abs(est.mean() - (q + 0.3 * (1 - q)) * exact) < 4.0 * est.std(ddof=1) / np.sqrt(reps)
    assert a.std(ddof=1) < 0.7 * b.std(ddof=1), (a.std(ddof=1), b.std(ddof=1))
    assert a.std(ddof=1) < 0.5 * c.std(ddof=1), (a.std(ddof=1), c.std(ddof=1))


def test_a_picked_point_is_as_an_independent_sample():
    """Each path's component and point, over the class's random shifts, are as one independent
    sample's (so each pixel's estimate is unbiased on its own): the first component with
    probability q (binomial, 4 sigma), and the point uniform on the square given either component
    (chi-square of a 4 x 4 histogram), for several paths and samples."""
    rng = np.random.default_rng(5)
    m, k, n, q = 20000, 8, 50, 0.37
    for j in (1, 6):
        for sample in (0, 37):
            shifts = [mi.Float(rng.random(m)) for _ in range(3)]
            first, p = strata.spread_pick(j, k, mi.UInt32(sample), mi.UInt32(n), mi.Float(q), *shifts,
                                           mi.Float(rng.random(m)))
            first = np.array(first)
            assert abs(first.mean() - q) < 4.0 * np.sqrt(q * (1 - q) / m)
            for group in (first, ~first):
                h, _, _ = np.histogram2d(np.array(p.x)[group], np.array(p.y)[group], bins=4, range=[[0, 1], [0, 1]])
                expected = group.sum() / 16
                assert ((h - expected) ** 2 / expected).sum() < 37.7  # 15 degrees of freedom, p = 0.001


def test_a_later_spread_point_is_uniform_over_the_class_shifts():
    """spread_later: each path's (u1, u2) uniform in the cube over the class's shifts (chi-square of
    a 3 x 3 x 3 histogram)."""
    rng = np.random.default_rng(6)
    m = 27000
    for i in (0, 5, 123456):
        u1, u2 = strata.spread_later(mi.UInt32(i), [mi.Float(rng.random(m)) for _ in range(3)])
        h, _ = np.histogramdd(np.stack([np.array(u1), np.array(u2.x), np.array(u2.y)], axis=1), bins=3,
                              range=[[0, 1]] * 3)
        assert ((h - m / 27) ** 2 / (m / 27)).sum() < 54.1  # 26 degrees of freedom, p = 0.001


def test_later_spread_points_fill_the_cube_evenly():
    """A class's 1000 paths with fixed shifts fill 10 x 10 x 10 cells far more evenly than
    independent points (the sum below is about 1000 +- 45 for those, 956 with numpy's generator
    seeded 1; measured 454 for the sequence)."""
    u1, u2 = strata.spread_later(dr.arange(mi.UInt32, 1000), [mi.Float(0.3), mi.Float(0.6), mi.Float(0.1)])
    pts = np.stack([np.array(u1), np.array(u2.x), np.array(u2.y)], axis=1)
    h, _ = np.histogramdd(pts, bins=10, range=[[0, 1]] * 3)
    assert ((h - 1.0) ** 2).sum() < 700.0
