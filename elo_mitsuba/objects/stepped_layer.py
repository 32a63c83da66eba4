"""A powder layer with parts beside it: patches of relief that end in cliffs of 0.1 to 1 mm.

Eight patches (seeded positions) over the 80 mm field, two for each cliff height 0.1, 0.2, 0.5 and
1.0 mm: a raised rectangle (a part standing above the powder) and a sunk disc (a part below the
powder line, or a crater). Three of the raised parts carry a gentle relief of their own (a dome of
50 µm), and the whole layer a mild roughness (10 µm RMS, wavelengths 2-8 mm, a seeded sum of
cosines so that it can be evaluated at any point). The cliffs are vertical; a mesh samples them
as walls one mesh cell wide.

It is the test surface of issue 25's steps: integrating a gradient across a cliff recovers only
the part of the jump that the gradient holds, and least squares spreads any inconsistency of the
walls' gradients over the relief beside them. :func:`steps` lists each cliff's nominal height and
outline, :func:`step_height` measures a recovered step from a height map (median of the patch's
interior, inset from the cliff, minus the median of a ring outside it).

:func:`stepped_height` evaluates the layer at any (x, y) (scene mm); :func:`stepped_mesh`
triangulates it at a third of the image pixel, as :mod:`.hills` does, the walls as flat cells.
"""

from __future__ import annotations

import numpy as np

#: Seed of the positions and of the roughness.
SEED = 25
#: Cliff heights (mm), each present twice: a raised rectangle and a sunk disc.
CLIFF_MM = (0.1, 0.2, 0.5, 1.0)
#: Roughness: RMS (mm), wavelength range (mm), number of cosines.
ROUGHNESS_MM = 0.010
WAVELENGTH_MM = (2.0, 8.0)
N_WAVES = 40
#: Amplitude (mm) of the dome on the raised parts that carry one.
DOME_MM = 0.05


def steps() -> list[dict]:
    """The patches: nominal cliff height and outline of each.

    Returns
    -------
    list of dict
        One per patch: ``name``, ``shape`` (``"rect"`` or ``"disc"``), ``centre`` (x, y in mm),
        ``half`` ((half width, half height) of a rectangle, mm) or ``radius`` (mm, a disc),
        ``height_mm`` (signed: positive = raised above the powder) and ``dome_mm`` (the
        amplitude of the gentle relief on top, 0 for none).

    Examples
    --------
    >>> s = steps()
    >>> len(s), sorted({abs(p["height_mm"]) for p in s})
    (8, [0.1, 0.2, 0.5, 1.0])
    >>> s[0]["shape"], s[0]["height_mm"], s[1]["shape"], s[1]["height_mm"]
    ('rect', 0.1, 'disc', -0.1)
    """
    rng = np.random.default_rng(SEED)
    # a 4 x 2 grid of cells 18 mm apart, each patch jittered inside its cell: rings of >= 3 mm of
    # powder between neighbours and >= 6 mm to the field's edge
    cells = [(x, y) for y in (15.0, -15.0) for x in (-27.0, -9.0, 9.0, 27.0)]
    order = rng.permutation(len(cells))
    out = []
    for k, h in enumerate(CLIFF_MM):
        for j, sign in enumerate((1.0, -1.0)):
            cx, cy = cells[order[2 * k + j]]
            cx, cy = cx + rng.uniform(-1.0, 1.0), cy + rng.uniform(-1.0, 1.0)
            p = {"name": f"{'raised' if sign > 0 else 'sunk'} {h:g} mm", "centre": (float(cx), float(cy)),
                 "height_mm": sign * h, "dome_mm": 0.0}
            if sign > 0:
                p["shape"] = "rect"
                p["half"] = (float(rng.uniform(5.0, 6.0)), float(rng.uniform(4.0, 5.5)))
                p["dome_mm"] = DOME_MM if k > 0 else 0.0
            else:
                p["shape"] = "disc"
                p["radius"] = float(rng.uniform(4.5, 5.5))
            out.append(p)
    return out


def cliff_distance(patch: dict, x, y) -> np.ndarray:
    """Signed distance (mm) from the patch's cliff: negative inside, positive outside.

    Parameters
    ----------
    patch : dict
        One entry of :func:`steps`.
    x, y : array_like
        Scene points (mm).

    Returns
    -------
    ndarray
        The distance (exact for a disc; for a rectangle the Chebyshev-like ``max`` of the two
        axis distances, exact along the sides, which is what an inset needs).

    Examples
    --------
    >>> p = steps()[1]                                     # a disc
    >>> cx, cy = p["centre"]
    >>> round(float(cliff_distance(p, cx, cy)), 3) == -round(p["radius"], 3)
    True
    """
    x = np.asarray(x, float) - patch["centre"][0]
    y = np.asarray(y, float) - patch["centre"][1]
    if patch["shape"] == "disc":
        return np.hypot(x, y) - patch["radius"]
    a, b = patch["half"]
    return np.maximum(np.abs(x) - a, np.abs(y) - b)


def _roughness(x, y):
    rng = np.random.default_rng(SEED + 1)
    lam = rng.uniform(*WAVELENGTH_MM, N_WAVES)
    phi = rng.uniform(0, 2 * np.pi, N_WAVES)
    ang = rng.uniform(0, np.pi, N_WAVES)
    amp = ROUGHNESS_MM * np.sqrt(2.0 / N_WAVES)  # each cosine has RMS amp / sqrt(2)
    z = np.zeros(np.broadcast(x, y).shape)
    for lk, pk, ak in zip(lam, phi, ang):
        z = z + amp * np.cos(2 * np.pi * (x * np.cos(ak) + y * np.sin(ak)) / lk + pk)
    return z


def stepped_height(x, y) -> np.ndarray:
    """Height (mm) of the layer at scene points (x, y).

    Parameters
    ----------
    x, y : array_like
        Scene coordinates (mm), broadcast together.

    Returns
    -------
    ndarray
        Powder level 0 plus roughness; on each patch its cliff height plus its dome.

    Examples
    --------
    >>> p = steps()[6]                                     # the raised 1 mm part
    >>> cx, cy = p["centre"]
    >>> inside, outside = stepped_height([cx, cx + p["half"][0] + 2.0], [cy, cy])
    >>> round(float(inside - outside), 1)
    1.0
    """
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    z = _roughness(x, y)
    for p in steps():
        d = cliff_distance(p, x, y)
        inside = d < 0
        if p["dome_mm"]:
            size = min(p["half"]) if p["shape"] == "rect" else p["radius"]
            r2 = (x - p["centre"][0]) ** 2 + (y - p["centre"][1]) ** 2
            top = p["height_mm"] + p["dome_mm"] * np.exp(-r2 / (2 * (0.5 * size) ** 2))
        else:
            top = p["height_mm"]
        z = z + np.where(inside, top, 0.0)
    return z


def stepped_mesh(field_mm: float, resolution: int, *, oversample: int = 3, margin_mm: float = 4.0,
                 smooth: bool = True):
    """The layer as a :class:`trimesh.Trimesh` over the field plus ``margin_mm``.

    Parameters
    ----------
    field_mm : float
        Scan field (mm).
    resolution : int
        Image pixels across the field; the mesh pitch is ``field_mm / resolution / oversample``.
    oversample : int
        Mesh cells per image pixel (3: a cliff becomes a wall a third of a pixel wide).
    margin_mm : float
        Extra width beyond the field (the beam lands off its aim point on relief).
    smooth : bool
        The relief with its own normals at the vertices, the walls flat
        (:func:`.surface_mesh.surface_mesh`); False: flat triangles everywhere.

    Returns
    -------
    trimesh.Trimesh
        One vertex per mesh node (:func:`elo_mitsuba.mesh.heightmap_to_mesh`), and vertices of
        their own for the walls' cells.

    Examples
    --------
    >>> mesh = stepped_mesh(80.0, 16, oversample=1, smooth=False)
    >>> len(mesh.vertices) == 17 ** 2, round(float(mesh.vertices[:, 2].max()), 1)
    (True, 1.0)
    """
    from .surface_mesh import surface_mesh

    def part(x, y):  # which patches a point lies in: it changes across every cliff
        return sum((cliff_distance(p, x, y) < 0).astype(int) << k for k, p in enumerate(steps()))

    return surface_mesh(stepped_height, field_mm / resolution / oversample, field_mm + margin_mm,
                        smooth=smooth, part=part)


def step_height(height, field_mm, patch: dict, *, inset_mm: float = 1.0, ring_mm: float = 2.0,
                mask=None, coordinates=None) -> float:
    """A step's height as a height map shows it: the median over the patch's interior (at least
    ``inset_mm`` inside the cliff) minus the median over the ring from ``inset_mm`` to
    ``inset_mm + ring_mm`` outside it.

    Medians, so that the walls' own pixels, a dome on top and the roughness barely move it.

    Parameters
    ----------
    height : ndarray (H, W)
        Heights (mm), package orientation (row 0 at +y).
    field_mm : float or (float, float)
        Scan field (mm).
    patch : dict
        One entry of :func:`steps`.
    inset_mm, ring_mm : float
        Distance kept from the cliff, and the ring's width.
    mask : ndarray of bool (H, W), optional
        Pixels without a height (True) are left out.
    coordinates : (ndarray, ndarray), optional
        The (x, y) each pixel shows (e.g. the beam's landing points); default the pixel centres.

    Returns
    -------
    float
        The step (mm, signed like ``patch["height_mm"]``); NaN when the interior or the ring
        holds no pixel.

    Examples
    --------
    >>> from elo_mitsuba.grid import pixel_coordinates
    >>> x, y = pixel_coordinates((200, 200), 80.0)
    >>> p = steps()[4]                                     # raised 0.5 mm, with a dome
    >>> round(step_height(stepped_height(x, y), 80.0, p), 2)
    0.52
    """
    from ..grid import pixel_coordinates

    height = np.asarray(height, float)
    x, y = pixel_coordinates(height.shape, field_mm) if coordinates is None else coordinates
    d = cliff_distance(patch, x, y)
    ok = np.isfinite(height) if mask is None else np.isfinite(height) & ~np.asarray(mask, bool)
    inner = ok & (d <= -inset_mm)
    ring = ok & (d >= inset_mm) & (d <= inset_mm + ring_mm)
    if not inner.any() or not ring.any():
        return float("nan")
    return float(np.median(height[inner]) - np.median(height[ring]))
