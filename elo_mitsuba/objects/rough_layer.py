"""A PBF-EB-like layer: rough melt surface with pores and bumps, for height maps at local defects.

What process engineers watch a layer for are local features: pores (pits of a few tenths of a
millimetre), bulges and swelling, spatter. On a melted layer they sit on a relief of their own, a
random roughness of about 100 um RMS over a correlation length of about 2 mm. This surface puts six
pores and six bumps of 0.2-1 mm and 50-500 um height on such a relief, seeded, so that a test or a
validation study can compare a height map with the truth *at the defects*, where the beam blur
mixes the normals of a pit's rims and a smooth-surface estimate fails first.

* The roughness is a stationary Gaussian random field with covariance
  ``RMS^2 exp(-r^2 / (2 CORRELATION^2))``, drawn as a sum of :data:`N_MODES` random Fourier modes
  (random-phase spectral synthesis: wave vectors drawn from the field's Gaussian spectral density,
  amplitudes sqrt(2/M) RMS), so that :func:`rough_height` evaluates it at any point, exactly,
  without a grid. Its RMS slope is RMS / CORRELATION (0.05).
* A pore is a raised-cosine pit, ``-depth (1 + cos(pi r / R)) / 2`` for r < R; a bump the smooth
  cap ``height (1 - (r / R)^2)^2``. Both have a continuous slope, so a mesh fine enough
  (:func:`rough_mesh`, with the surface's own normals at its vertices) is the surface itself.

:func:`defects` lists them (kind, centre, radius, height); :func:`near_defects` is the mask of
pixels within a distance of any of them, where the validation reports its local errors.
"""

from __future__ import annotations

import numpy as np

#: Seed of the relief and of the defects' places and sizes.
SEED = 25
#: Roughness: RMS height (mm) and correlation length (mm) of the random field.
RMS_MM = 0.1
CORRELATION_MM = 2.0
#: Fourier modes of the random field (the RMS of a draw of M modes differs from RMS_MM by about
#: 1/sqrt(M); 256 keep it within a few per cent at a cost of 256 cosines per point).
N_MODES = 256
#: Pores: count, radius range (mm), depth range (mm).
N_PORES = 6
PORE_RADIUS_MM = (0.25, 0.35)
PORE_DEPTH_MM = (0.15, 0.4)
#: Bumps (bulges, swelling): count, radius range (mm), height range (mm).
N_BUMPS = 6
BUMP_RADIUS_MM = (0.4, 1.0)
BUMP_HEIGHT_MM = (0.05, 0.3)
#: Defect centres lie within +-CENTRE_MM of the field's centre, at least MIN_GAP_MM apart.
CENTRE_MM = 34.0
MIN_GAP_MM = 6.0


def _modes(seed: int = SEED):
    rng = np.random.default_rng(seed)
    k = rng.standard_normal((N_MODES, 2)) / CORRELATION_MM  # the Gaussian spectral density
    phase = rng.uniform(0.0, 2.0 * np.pi, N_MODES)
    return k, phase, RMS_MM * np.sqrt(2.0 / N_MODES)


def defects(seed: int = SEED) -> list[dict]:
    """The pores and bumps: ``kind`` ("pore" or "bump"), centre ``x``, ``y`` (mm), ``radius`` (mm)
    and ``height`` (mm; negative for a pore's depth).

    Examples
    --------
    >>> d = defects()
    >>> [sum(e["kind"] == k for e in d) for k in ("pore", "bump")]
    [6, 6]
    >>> all(e["height"] < 0 for e in d if e["kind"] == "pore")
    True
    """
    rng = np.random.default_rng(seed + 1)
    centres: list[np.ndarray] = []
    while len(centres) < N_PORES + N_BUMPS:
        c = rng.uniform(-CENTRE_MM, CENTRE_MM, 2)
        if all(np.hypot(*(c - o)) >= MIN_GAP_MM for o in centres):
            centres.append(c)
    out = []
    for i, (x, y) in enumerate(centres):
        if i < N_PORES:
            out.append({"kind": "pore", "x": float(x), "y": float(y), "radius": float(rng.uniform(*PORE_RADIUS_MM)),
                        "height": -float(rng.uniform(*PORE_DEPTH_MM))})
        else:
            out.append({"kind": "bump", "x": float(x), "y": float(y), "radius": float(rng.uniform(*BUMP_RADIUS_MM)),
                        "height": float(rng.uniform(*BUMP_HEIGHT_MM))})
    return out


def roughness_height(x, y, seed: int = SEED) -> np.ndarray:
    """The random relief alone (mm) at scene points (x, y) (mm).

    Examples
    --------
    >>> xx, yy = np.meshgrid(np.linspace(-40, 40, 161), np.linspace(-40, 40, 161))
    >>> 0.08 < float(roughness_height(xx, yy).std()) < 0.12
    True
    """
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    k, phase, amp = _modes(seed)
    z = np.zeros(x.shape)
    for (kx, ky), p in zip(k, phase):  # one mode at a time over all points: memory stays O(points)
        z += np.cos(kx * x + ky * y + p)
    return amp * z


def defect_height(x, y, seed: int = SEED) -> np.ndarray:
    """The pores and bumps alone (mm) at scene points (x, y) (mm).

    Examples
    --------
    >>> pore = defects()[0]
    >>> round(float(defect_height(pore["x"], pore["y"])), 6) == round(pore["height"], 6)
    True
    """
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    z = np.zeros(x.shape)
    for d in defects(seed):
        t = np.hypot(x - d["x"], y - d["y"]) / d["radius"]
        inside = t < 1.0
        if d["kind"] == "pore":
            shape = 0.5 * (1.0 + np.cos(np.pi * np.minimum(t, 1.0)))
        else:
            shape = (1.0 - np.minimum(t, 1.0) ** 2) ** 2
        z = z + np.where(inside, d["height"] * shape, 0.0)
    return z


def rough_height(x, y, seed: int = SEED) -> np.ndarray:
    """Height (mm) of the layer, relief and defects, at scene points (x, y) (mm).

    Examples
    --------
    >>> float(rough_height(0.0, 0.0)) == float(roughness_height(0.0, 0.0) + defect_height(0.0, 0.0))
    True
    """
    return roughness_height(x, y, seed) + defect_height(x, y, seed)


def rough_gradient(x, y, seed: int = SEED) -> tuple[np.ndarray, np.ndarray]:
    """(dZ/dx, dZ/dy) of :func:`rough_height` at scene points (x, y), in closed form (a pore's
    slope d (pi / 2R) sin(pi r / R) outward, a bump's -4 h r (1 - (r/R)^2) / R^2).

    Examples
    --------
    >>> gx, gy = rough_gradient(3.0, -2.0)
    >>> e = 1e-5
    >>> bool(abs(gx - (rough_height(3.0 + e, -2.0) - rough_height(3.0 - e, -2.0)) / (2 * e)) < 1e-7)
    True
    """
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    k, phase, amp = _modes(seed)
    gx, gy = np.zeros(x.shape), np.zeros(x.shape)
    for (kx, ky), p in zip(k, phase):
        s = np.sin(kx * x + ky * y + p)
        gx -= kx * s
        gy -= ky * s
    gx, gy = amp * gx, amp * gy
    for d in defects(seed):
        dx, dy = x - d["x"], y - d["y"]
        t = np.hypot(dx, dy) / d["radius"]
        inside = t < 1.0
        if d["kind"] == "pore":  # d/dr of h (1 + cos(pi t)) / 2, over r: -h pi^2 sinc(t) / (2 R^2)
            per_r = -0.5 * np.pi ** 2 * d["height"] * np.sinc(t) / d["radius"] ** 2
        else:  # d/dr of h (1 - t^2)^2, over r
            per_r = -4.0 * d["height"] * (1.0 - t * t) / d["radius"] ** 2
        gx += np.where(inside, per_r * dx, 0.0)
        gy += np.where(inside, per_r * dy, 0.0)
    return gx, gy


def near_defects(x, y, distance_mm: float = 1.0, seed: int = SEED, kind: str | None = None) -> np.ndarray:
    """True where a point lies within ``distance_mm`` of a defect's rim (or inside it); with
    ``kind`` (``"pore"`` or ``"bump"``) of that kind's only.

    Examples
    --------
    >>> d = defects()[0]
    >>> bool(near_defects(d["x"] + d["radius"] + 0.9, d["y"])), bool(near_defects(d["x"] + d["radius"] + 1.1, d["y"]))
    (True, False)
    >>> other = "bump" if d["kind"] == "pore" else "pore"
    >>> bool(near_defects(d["x"], d["y"], 0.0, kind=d["kind"])), bool(near_defects(d["x"], d["y"], 0.0, kind=other))
    (True, False)
    """
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    out = np.zeros(x.shape, bool)
    for d in defects(seed):
        if kind is None or d["kind"] == kind:
            out |= np.hypot(x - d["x"], y - d["y"]) <= d["radius"] + distance_mm
    return out


def rough_mesh(field_mm: float, resolution: int, *, oversample: int = 3, margin_mm: float = 4.0,
               seed: int = SEED, smooth: bool = True):
    """The layer as a :class:`trimesh.Trimesh` over the field plus ``margin_mm``, at a pitch of
    ``field_mm / resolution / oversample`` (and at most a fifth of the smallest pore's radius, so
    that its rims are resolved); ``smooth``: with its own normals at the vertices
    (:func:`.surface_mesh.surface_mesh`), else flat triangles.

    Examples
    --------
    >>> mesh = rough_mesh(4.0, 8)
    >>> mesh.is_watertight, len(mesh.vertices) > 0
    (False, True)
    """
    from .surface_mesh import surface_mesh

    pitch = min(field_mm / resolution / oversample, PORE_RADIUS_MM[0] / 5.0)
    return surface_mesh(lambda x, y: rough_height(x, y, seed), pitch, field_mm + margin_mm, smooth=smooth,
                        gradient=lambda x, y: rough_gradient(x, y, seed))
