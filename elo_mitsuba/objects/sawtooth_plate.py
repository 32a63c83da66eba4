"""A test plate of sawtooth patches: known slopes 0.2-1.0, three orientations, over the whole field.

Nine 16 mm patches on a 28 mm grid (centres at x, y in {-28, 0, +28} mm, reaching +-36 mm of the
80 mm field) on a plane plate z = 0. Each patch is a zigzag (triangle wave) of planar facets with
slope ``|grad Z| = s``: ridges along y (slope in x), along x (slope in y), or along the diagonal
x = y (slope along (1, -1)/sqrt 2). Slopes and orientations form a Latin square, so every slope
is seen at the centre, at an edge and at a corner of the field and in each orientation:

    row y = +28:  0.6 x     1.0 y     0.2 diag
    row y =   0:  0.2 y     0.6 diag  1.0 x
    row y = -28:  1.0 diag  0.2 x     0.6 y

Facets are 2 mm wide across the ridges (2.12 mm for the diagonal patches, whose ridges fall on the
mesh's cell diagonals), so the heights reach 2 mm; the patch edges are cliffs, as on a cut test
specimen. Unlike the
shipped scenes' objects (one 45-degree corrugation, millimetre-level melt squares) it covers the
range of slopes and positions a gradient method must handle.
"""

from __future__ import annotations

import math

import numpy as np

from ..grid import pixel_coordinates

#: Patch centres along x and y (mm), patch half-width (mm).
PATCH_CENTRES_MM = (-28.0, 0.0, 28.0)
PATCH_HALF_MM = 8.0
#: Facet width across the ridges (mm): axis patches, diagonal patches (ridge spacing 3 mm in x - y).
FACET_MM = 2.0
FACET_DIAG_MM = 3.0 / math.sqrt(2.0)
#: (slope, orientation) by (row from +y, column from -x).
PATCHES = (
    ((0.6, "x"), (1.0, "y"), (0.2, "diag")),
    ((0.2, "y"), (0.6, "diag"), (1.0, "x")),
    ((1.0, "diag"), (0.2, "x"), (0.6, "y")),
)
#: Ridges and valleys are shifted off the patch centre by this (mm, across the ridges): then no
#: pixel centre of a 160, 256, 512 or 1024-pixel scan of the 80 mm field lies on a ridge (the beam
#: hits one facet or the other there by a sub-micrometre nudge, and the truth is ambiguous), and
#: they still fall on mesh lines (multiples of MESH_PITCH_MM in x, y or x - y).
RIDGE_OFFSET_MM = 0.375
RIDGE_OFFSET_DIAG_MM = 0.75 / math.sqrt(2.0)
#: Mesh pitch (mm): ridges and patch edges fall on grid lines.
MESH_PITCH_MM = 0.125
#: Half-width of the meshed plate (mm): the 80 mm field plus 4 mm.
PLATE_HALF_MM = 44.0


def _patch_table():
    rows = []
    for r, cy in enumerate(PATCH_CENTRES_MM[::-1]):
        for c, cx in enumerate(PATCH_CENTRES_MM):
            slope, orient = PATCHES[r][c]
            rows.append((cx, cy, slope, orient))
    return rows


def patches() -> list[dict]:
    """The nine patches: centre (mm), slope, orientation and the unit slope direction."""
    out = []
    for cx, cy, slope, orient in _patch_table():
        direction = {"x": (1.0, 0.0), "y": (0.0, 1.0), "diag": (1 / math.sqrt(2), -1 / math.sqrt(2))}[orient]
        diag = orient == "diag"
        out.append({"center": (cx, cy), "slope": slope, "orientation": orient, "direction": direction,
                    "facet_mm": FACET_DIAG_MM if diag else FACET_MM,
                    "offset_mm": RIDGE_OFFSET_DIAG_MM if diag else RIDGE_OFFSET_MM})
    return out


def _tri(t):
    """Triangle wave: 0 at even t, 1 at odd t, slope +-1."""
    return np.abs(t - 2.0 * np.floor((t + 1.0) / 2.0))


def _local(x, y, patch):
    """Coordinate along the slope direction (mm), and whether (x, y) lies on the patch."""
    cx, cy = patch["center"]
    inside = (np.abs(x - cx) <= PATCH_HALF_MM) & (np.abs(y - cy) <= PATCH_HALF_MM)
    ux, uy = patch["direction"]
    return (x - cx) * ux + (y - cy) * uy - patch["offset_mm"], inside


def sawtooth_height(x, y) -> np.ndarray:
    """Height Z(x, y) in mm (0 off the patches)."""
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    z = np.zeros(x.shape)
    for patch in patches():
        u, inside = _local(x, y, patch)
        w = patch["facet_mm"]
        z = np.where(inside, patch["slope"] * w * _tri(u / w), z)
    return z


def sawtooth_gradient(x, y) -> tuple[np.ndarray, np.ndarray]:
    """Exact (dZ/dx, dZ/dy) inside the facets (0 off the patches; one side's value on a ridge)."""
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    gx = np.zeros(x.shape)
    gy = np.zeros(x.shape)
    for patch in patches():
        u, inside = _local(x, y, patch)
        w = patch["facet_mm"]
        t = u / w
        sign = np.where(np.mod(np.floor(t), 2) == 0, 1.0, -1.0)  # rising on [0, 1), falling on [1, 2)
        ux, uy = patch["direction"]
        gx = np.where(inside, patch["slope"] * sign * ux, gx)
        gy = np.where(inside, patch["slope"] * sign * uy, gy)
    return gx, gy


def landing_points(x, y, wd_mm: float | None, iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Where the beam aimed at (x, y) on z = 0 from the pivot (0, 0, ``wd_mm``) meets the plate
    (None: an orthographic beam lands at (x, y)). On a 2 mm high facet at x = 26 mm the landing
    point is 0.13 mm closer to the axis than the aim point: next to a ridge that is the other
    facet. Fixed-point iteration x_l = x (1 - Z(x_l, y_l) / wd), a contraction (|grad Z| <= 1,
    |x| / wd < 0.1)."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    if wd_mm is None:
        return x, y
    xl, yl = x, y
    for _ in range(iterations):
        t = 1.0 - sawtooth_height(xl, yl) / float(wd_mm)
        xl, yl = x * t, y * t
    return xl, yl


def facet_interiors(x, y, margin_mm: float) -> np.ndarray:
    """Index of the patch (0..8) whose facet interior holds (x, y), farther than ``margin_mm``
    from any ridge, valley or patch edge; -1 elsewhere."""
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    out = np.full(x.shape, -1, dtype=int)
    for i, patch in enumerate(patches()):
        cx, cy = patch["center"]
        u, _ = _local(x, y, patch)
        w = patch["facet_mm"]
        frac = np.mod(u / w, 1.0) * w
        inner = (np.abs(x - cx) <= PATCH_HALF_MM - margin_mm) & (np.abs(y - cy) <= PATCH_HALF_MM - margin_mm)
        inner &= (frac >= margin_mm) & (frac <= w - margin_mm)
        out = np.where(inner, i, out)
    return out


def sawtooth_heightmap(pitch_mm: float = MESH_PITCH_MM, half_mm: float = PLATE_HALF_MM) -> np.ndarray:
    """The height map on a square grid of ``pitch_mm`` covering +-``half_mm`` (package orientation)."""
    n = int(round(2 * half_mm / pitch_mm)) + 1
    x, y = pixel_coordinates((n, n), n * pitch_mm)
    return sawtooth_height(x, y)


def sawtooth_mesh(pitch_mm: float = MESH_PITCH_MM):
    """The plate as a :class:`trimesh.Trimesh` (flat areas meshed coarsely)."""
    from ..mesh import heightmap_to_mesh

    return heightmap_to_mesh(sawtooth_heightmap(pitch_mm), pitch_mm, tolerance_mm=1e-9)


def patch_errors(dzdx, dzdy, field_mm, *, margin_mm: float, mask=None, wd_mm: float | None = 400.0) -> list[dict]:
    """Per patch, over its facet interiors (pixels whose beam lands there, :func:`landing_points`):

    * ``median_error``: the median over pixels of |g_est - g| / |g| (includes per-pixel noise);
    * ``facet_error``: the error of the patch's facet slopes, |median g_est - g| / |g| for the
      rising and the falling facets, the larger of the two (the bias; noise averages out);
    * ``pixels`` used and ``masked`` (left out).

    ``dzdx``, ``dzdy`` are a gradient image of the plate (package orientation, scan field
    ``field_mm``); ``wd_mm`` the beam's pivot height (None: orthographic).
    """
    dzdx = np.asarray(dzdx, float)
    dzdy = np.asarray(dzdy, float)
    x, y = landing_points(*pixel_coordinates(dzdx.shape, field_mm), wd_mm)
    gx, gy = sawtooth_gradient(x, y)
    idx = facet_interiors(x, y, margin_mm)
    err = np.hypot(dzdx - gx, dzdy - gy) / np.maximum(np.hypot(gx, gy), 1e-12)
    keep = np.ones(dzdx.shape, bool) if mask is None else ~np.asarray(mask, bool)
    rows = []
    for i, patch in enumerate(patches()):
        sel = idx == i
        good = sel & keep
        facet = []
        for sign in (1.0, -1.0):
            rising = (gx * patch["direction"][0] + gy * patch["direction"][1]) > 0
            f = good & (rising == (sign > 0))
            if f.any():
                tx, ty = np.median(gx[f]), np.median(gy[f])
                facet.append(np.hypot(np.median(dzdx[f]) - tx, np.median(dzdy[f]) - ty) / np.hypot(tx, ty))
        rows.append({**{k: patch[k] for k in ("center", "slope", "orientation")},
                     "median_error": float(np.median(err[good])) if good.any() else float("nan"),
                     "facet_error": float(max(facet)) if facet else float("nan"),
                     "pixels": int(good.sum()), "masked": int((sel & ~keep).sum())})
    return rows


def patch_height_errors(dzdx, dzdy, field_mm, *, margin_mm: float, reference: str = "truth",
                        wd_mm: float | None = 400.0) -> list[float]:
    """Per patch: RMSE (mm) of the height integrated from ``dzdx``, ``dzdy`` over the patch alone
    (inset by ``margin_mm``, so no cliff is crossed), both with their mean removed, against

    * ``reference="truth"``: the true relief at the pixel centres (includes the integration's own
      error on a sampled zigzag, ~ slope x pixel / 2 at the ridges), or
    * ``reference="integrated"``: the same integration of the true gradient where each pixel's
      beam lands (:func:`landing_points`; only what the gradient's error does to the height).

    Integration: :func:`elo_mitsuba.analysis.integrate_gradient` (DCT).
    """
    from ..analysis import integrate_gradient

    if reference not in ("truth", "integrated"):
        raise ValueError(f"reference {reference!r}: 'truth' or 'integrated'")
    dzdx = np.asarray(dzdx, float)
    x, y = pixel_coordinates(dzdx.shape, field_mm)
    gx, gy = sawtooth_gradient(*landing_points(x, y, wd_mm))
    out = []
    for patch in patches():
        cx, cy = patch["center"]
        cols = np.nonzero(np.abs(x[0] - cx) <= PATCH_HALF_MM - margin_mm)[0]
        rows = np.nonzero(np.abs(y[:, 0] - cy) <= PATCH_HALF_MM - margin_mm)[0]
        sl = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        sub_field = (len(cols) * field_mm[0] / dzdx.shape[1], len(rows) * field_mm[1] / dzdx.shape[0])
        h, _ = integrate_gradient(dzdx[sl], np.asarray(dzdy, float)[sl], sub_field, method="dct")
        if reference == "truth":
            ref = sawtooth_height(*landing_points(x[sl], y[sl], wd_mm))
        else:
            ref, _ = integrate_gradient(gx[sl], gy[sl], sub_field, method="dct")
        d = (h - h.mean()) - (ref - ref.mean())
        out.append(float(np.sqrt(np.mean(d * d))))
    return out
