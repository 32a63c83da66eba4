"""A steep test relief of smooth hills and dips, for the inversion: shadows and masking without edges.

Fourteen Gaussian hills and dips (seeded), 3-6 mm wide (standard deviation), 3-6 mm high or deep,
centres within +-34 mm: slopes up to 1.26 (52 deg), so that detectors 40 deg above the horizon
(Table 1, zeta = 50) are hidden from the steepest flanks and detectors 15 deg up (zeta = 75) are
shadowed by neighbouring hills over a third of the field. Unlike the sawtooth plate it has no
ridge or cliff, so the smooth surface an inversion reconstructs can be exact; unlike the melt
plate its relief is millimetres, far above the images' noise.

:func:`hills_height` evaluates it at any (x, y) (scene mm); :func:`hills_mesh` triangulates it at a
third of the image pixel, with the surface's own normals at the vertices
(:mod:`.surface_mesh`: the beam sees the surface's normal, not a triangle's).
"""

from __future__ import annotations

import numpy as np

#: Seed, number of hills, ranges of width (sigma, mm), height (mm) and centre (mm).
SEED = 11
N_HILLS = 14
WIDTH_MM = (3.0, 6.0)
HEIGHT_MM = (3.0, 6.0)
CENTRE_MM = 34.0


def _hills():
    rng = np.random.default_rng(SEED)
    out = []
    for _ in range(N_HILLS):
        cx, cy = rng.uniform(-CENTRE_MM, CENTRE_MM, 2)
        s = rng.uniform(*WIDTH_MM)
        a = rng.uniform(*HEIGHT_MM) * rng.choice([-1, 1])
        out.append((cx, cy, s, a))
    return out


def hills_height(x, y) -> np.ndarray:
    """Height (mm) at scene points (x, y)."""
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    z = np.zeros(x.shape)
    for cx, cy, s, a in _hills():
        z = z + a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
    return z


def hills_mesh(field_mm: float, resolution: int, *, oversample: int = 3, margin_mm: float = 4.0,
               smooth: bool = True):
    """The relief as a :class:`trimesh.Trimesh` over the field plus ``margin_mm``, at a pitch of
    ``field_mm / resolution / oversample``; ``smooth``: with its own normals at the vertices
    (:func:`.surface_mesh.surface_mesh`), else flat triangles."""
    from .surface_mesh import surface_mesh

    return surface_mesh(hills_height, field_mm / resolution / oversample, field_mm + margin_mm, smooth=smooth)
