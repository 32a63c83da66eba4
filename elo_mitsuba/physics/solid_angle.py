"""Solid angle of a plane triangle: Van Oosterom & Strackee (Eq. A1, corrected denominator).

For the vertices a, b, c of a triangle relative to the observer, ::

    tan(Omega/2) = a . (b x c) / (|a||b||c| + (a.b)|c| + (a.c)|b| + (b.c)|a|).

The paper prints the last term as (a.c)|a|; the form above is Van Oosterom & Strackee's (see
docs/paper-notes.md §2). :func:`vos_denominator` is written with plain arithmetic so that the
integrator's Dr.Jit kernel (Appendix A's quadrature) and the numpy function here share it.
"""

from __future__ import annotations

import numpy as np


def vos_denominator(la, lb, lc, ab, ac, bc):
    """The denominator of Eq. A1 from the lengths ``|a|, |b|, |c|`` and the dot products a.b, a.c, b.c
    (numpy or Dr.Jit arrays).

    Parameters
    ----------
    la, lb, lc : array_like
        Lengths of the vectors a, b, c from the viewpoint to the vertices (mm).
    ab, ac, bc : array_like
        Their dot products (mm^2).

    Returns
    -------
    array
        ``|a| |b| |c| + (a.b) |c| + (a.c) |b| + (b.c) |a|`` (mm^3).

    Examples
    --------
    >>> float(vos_denominator(1.0, 1.0, 1.0, 0.0, 0.0, 0.0))     # three orthogonal unit vectors
    1.0
    """
    return la * lb * lc + ab * lc + ac * lb + bc * la


def triangle_solid_angle(p, v1, v2, v3):
    """Signed solid angle (sr) of triangles (v1, v2, v3) seen from ``p`` (numpy, broadcasting).

    Positive when ``p`` lies on the side opposite to the normal (v2 - v1) x (v3 - v1) (the
    vertices turn clockwise as seen from ``p``), negative on the normal's side.

    Parameters
    ----------
    p : array_like (..., 3)
        Viewpoint(s) in mm.
    v1, v2, v3 : array_like (..., 3)
        Vertices in mm.

    Returns
    -------
    ndarray
        Solid angle in sr (signed).

    Examples
    --------
    An octant: the triangle (e_x, e_y, e_z) seen from the origin covers 4 pi / 8 sr:

    >>> import numpy as np
    >>> omega = triangle_solid_angle([0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1])
    >>> round(float(abs(omega)), 4), round(np.pi / 2, 4)
    (1.5708, 1.5708)
    """
    a, b, c = (np.asarray(v, float) - np.asarray(p, float) for v in (v1, v2, v3))
    la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
    num = np.sum(a * np.cross(b, c), axis=-1)
    den = vos_denominator(la, lb, lc, np.sum(a * b, axis=-1), np.sum(a * c, axis=-1), np.sum(b * c, axis=-1))
    return 2.0 * np.arctan2(num, den)
