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
