"""The mesh of a test surface known everywhere, with its own normals at the vertices.

The renderer's beam lands at the pixel centres, and with flat-shaded triangles it sees a
triangle's normal there, not the surface's: every centre falls on the same spot of its mesh cell
(the cell's diagonal at an odd oversampling), where the triangle's slope differs from the
surface's by about half the pitch times the cross curvature d2Z/dxdy, with the same sign over a
whole quadrant of a hill. On the hills at 128^2 (pitch a third of a pixel, layout zeta25, single-ray
beam) that biased the rendered slopes by 4e-3 RMS, and the inversion's model reproduced the images
of the true surface only to 0.0024 (corrected units), not to the 0.0004 of the renderer's own
accuracy. With the surface's normals at the vertices, interpolated across each triangle (Mitsuba's
smooth shading), the beam sees the surface's own normal to second order in the pitch.

Normals come from the height function by central differences of :data:`STEP_MM`; next to a cliff
(a jump within the step) the one-sided difference of smaller magnitude, the side the vertex is on.
Cells across a cliff (``part``, a label per point that changes across each cliff) keep flat
triangles with vertices of their own: a wall, whose normal the relief either side does not know.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

#: Step (mm) of the central differences (the slopes' error is about STEP^2 / 6 d3Z/dx3: < 1e-8 here).
STEP_MM = 1e-4


def surface_normals(height: Callable, x, y, gradient: Callable | None = None) -> np.ndarray:
    """Unit normals [-dZ/dx, -dZ/dy, 1] / |.| (..., 3) of ``height(x, y)`` (mm) at (x, y), from
    ``gradient(x, y)`` -> (dZ/dx, dZ/dy) where the surface gives it in closed form.

    Examples
    --------
    >>> n = surface_normals(lambda x, y: 0.5 * x, np.zeros((2, 2)), np.zeros((2, 2)))
    >>> (np.round(n[0, 0], 6) + 0.0).tolist()
    [-0.447214, 0.0, 0.894427]
    """
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    if gradient is not None:
        gx, gy = gradient(x, y)
        n = np.stack([-np.asarray(gx, float), -np.asarray(gy, float), np.ones(x.shape)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)
    z = height(x, y)

    def slope(dx, dy):
        ahead = (height(x + dx, y + dy) - z) / STEP_MM
        behind = (z - height(x - dx, y - dy)) / STEP_MM
        central = 0.5 * (ahead + behind)
        # a cliff within the step (smooth relief changes its slope by STEP d2Z/dx2 < 0.01 there):
        # the side the point is on, the one-sided slope of smaller size
        jump = np.abs(ahead - behind) > 1.0
        return np.where(jump, np.where(np.abs(ahead) < np.abs(behind), ahead, behind), central)

    n = np.stack([-slope(STEP_MM, 0.0), -slope(0.0, STEP_MM), np.ones(x.shape)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def surface_mesh(height: Callable, pitch_mm: float, extent_mm: float, *, smooth: bool = True,
                 part: Callable | None = None, gradient: Callable | None = None):
    """A square grid of ``pitch_mm`` covering ``extent_mm`` (centred), triangulated by
    :func:`elo_mitsuba.mesh.heightmap_to_mesh`; ``smooth``: with the surface's normals at the
    vertices (:func:`surface_normals`, from ``gradient`` if given), flat cells where ``part(x, y)``
    differs among a cell's corners.

    Examples
    --------
    >>> mesh = surface_mesh(lambda x, y: 0.1 * np.sin(x), 0.5, 4.0)
    >>> mesh.metadata["vertex_normals"].shape == mesh.vertices.shape
    True
    >>> step = surface_mesh(lambda x, y: np.where(x > 0.1, 1.0, 0.0), 0.5, 4.0, part=lambda x, y: x > 0.1)
    >>> len(step.vertices) - 8 * 8                          # one column of wall cells: 7 cells, 6 vertices each
    42
    """
    from ..heightmap import pixel_centres
    from ..mesh import heightmap_to_mesh

    n = int(round(extent_mm / pitch_mm))
    xc, yc = pixel_centres((n, n), pitch_mm)
    xx, yy = np.meshgrid(xc, yc)
    z = height(xx, yy)
    if not smooth:
        return heightmap_to_mesh(z, pitch_mm)
    flat = None
    if part is not None:
        lab = np.asarray(part(xx, yy))
        flat = ((lab[:-1, :-1] != lab[:-1, 1:]) | (lab[:-1, :-1] != lab[1:, :-1])
                | (lab[:-1, :-1] != lab[1:, 1:]))
    return heightmap_to_mesh(z, pitch_mm, normals=surface_normals(height, xx, yy, gradient),
                             flat_cells=flat)
