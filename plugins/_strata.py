"""Strata of the unit square for n samples: rows x columns as square as n allows, one sample per
cell (jittered), each weighted by its cell's area. Unbiased for any n: the cells partition the
square. Used for the detector points of ``detector_sampling = stratified`` and for the
continuation paths a sample splits into (``bounce_samples``)."""

import math

import drjit as dr
import mitsuba as mi

_GOLDEN = 0.6180339887498949


def strata_cells(n: int) -> list[tuple[int, int, int, int]]:
    """The n cells as (row, column, columns in that row, rows), row-major: ``isqrt(n)`` rows, the
    columns spread over them (rows differ by at most one column)."""
    rows = max(1, int(math.isqrt(n)))
    cols = [n // rows + (1 if r < n % rows else 0) for r in range(rows)]
    return [(r, c, cols[r], rows) for r in range(rows) for c in range(cols[r])]


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
