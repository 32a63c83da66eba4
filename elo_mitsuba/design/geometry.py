"""A detector system's geometry: design parameters -> discs, and the constraints of the chamber.

A design places ``count`` discs at azimuths ``azimuth + k 360/count`` (deg from +x), each at height
``dh`` (centre z) and distance ``dw`` from the z-axis, of radius ``radius``, its front normal aimed at
the point (0, 0, ``aim_z``) of the axis (``aim_z = 0``: facing the origin, as Table 1's layouts
do). Symmetric designs share one value of each; otherwise each detector k has its own ``dh_k``,
``dw_k``, ``radius_k``, ``aim_z_k`` and an azimuth offset ``azimuth_k`` from its nominal slot.
With four detectors the slots are named right (+x), back (+y), left (-x), front (-y), the
channels of the shipped scenes.

Constraints (:func:`violations`), each an amount in mm (> 0: violated by that much), checked at
points of every disc (centre, a ring at half the radius, the rim), with a clearance margin:

* ``chamber``: inside the ATHENE-like chamber's walls, floor (above the build plane) and ceiling
  (:data:`~elo_mitsuba.constants.CHAMBER_INTERIOR_MM`);
* ``sheet``: clear of the radiation-protection sheet hanging from the ceiling near the back wall
  (a disc below its lower edge is seen from the field under it);
* ``beam``: outside the beam's cone from the pivot (0, 0, wd) to the scan field (the field's line
  of sight to the gun);
* ``column``: outside the gun column (abs(x), abs(y) < COLUMN_HALF_WIDTH_MM above the pivot);
* ``overlap``: no two discs' bounding spheres within the clearance of each other;
* ``occlusion``: no disc's bounding sphere on the line of sight from the field (centre, corners,
  edge midpoints) to another disc's centre;
* ``facing``: every field point in front of every disc.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..analysis.scan_geometry import Disc
from ..constants import (
    CHAMBER_INTERIOR_MM,
    COLUMN_HALF_WIDTH_MM,
    SHEET_BOTTOM_MM,
    SHEET_Y_MM,
)

#: Design parameters and their units; per detector in an asymmetric design (``dh_0``, ...).
PARAMETERS = {"dh": "mm", "dw": "mm", "radius": "mm", "aim_z": "mm", "azimuth": "deg"}
#: Names of the slots of a four-detector design (azimuths 0, 90, 180, 270 deg).
FOUR_NAMES = ("right", "back", "left", "front")
#: The constraints, in the order of :func:`violations`.
CONSTRAINTS = ("chamber", "sheet", "beam", "column", "overlap", "occlusion", "facing")
#: Points per disc: rim and half-radius ring.
RIM_POINTS, RING_POINTS = 24, 8


def slot_names(count: int) -> tuple[str, ...]:
    """Detector names of a design of ``count`` detectors.

    Examples
    --------
    >>> slot_names(4), slot_names(3)
    (('right', 'back', 'left', 'front'), ('d0', 'd1', 'd2'))
    """
    return FOUR_NAMES if int(count) == 4 else tuple(f"d{k}" for k in range(int(count)))


def detector_value(params: Mapping, name: str, k: int, symmetric: bool) -> float:
    """Parameter ``name`` of detector ``k`` (its own ``name_k`` in an asymmetric design)."""
    return float(params[name] if symmetric else params[f"{name}_{k}"])


def design_discs(params: Mapping, count: int, symmetric: bool = True) -> dict[str, Disc]:
    """The discs of a design (see the module's description of the parameters).

    Parameters
    ----------
    params : mapping
        ``dh``, ``dw``, ``radius``, ``aim_z``, ``azimuth`` (symmetric) or ``dh_0``, ... (per detector).
    count : int
        Number of detectors.
    symmetric : bool
        One value of each parameter for all detectors.

    Returns
    -------
    dict of str to Disc

    Examples
    --------
    Table 1's zeta = 25 deg layout:

    >>> d = design_discs({"dh": 272, "dw": 127, "radius": 25, "aim_z": 0, "azimuth": 0}, 4)
    >>> list(d), [round(v, 3) for v in d["back"].center], d["back"].radius
    (['right', 'back', 'left', 'front'], [0.0, 127.0, 272.0], 25.0)
    """
    out = {}
    count = int(count)
    for k, name in enumerate(slot_names(count)):
        v = {p: detector_value(params, p, k, symmetric) for p in PARAMETERS}
        phi = np.radians(v["azimuth"] + 360.0 * k / count)
        c = np.array([v["dw"] * np.cos(phi), v["dw"] * np.sin(phi), v["dh"]])
        # exact zeros off the axes: a layout printed or exported reads as the symmetric one it is
        c[np.abs(c) < 1e-9] = 0.0
        out[name] = Disc(tuple(c), tuple(np.array([0.0, 0.0, v["aim_z"]]) - c), v["radius"])
    return out


def disc_points(disc: Disc) -> np.ndarray:
    """Centre, half-radius ring and rim of a disc, (1 + RING_POINTS + RIM_POINTS, 3) in mm."""
    n = np.asarray(disc.normal, float)
    a = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.99 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    rings = []
    for r, m in ((0.5 * disc.radius, RING_POINTS), (disc.radius, RIM_POINTS)):
        t = np.arange(m) * 2 * np.pi / m
        rings.append(r * (np.cos(t)[:, None] * a + np.sin(t)[:, None] * b))
    return np.asarray(disc.center, float) + np.concatenate([np.zeros((1, 3))] + rings)


def field_points(field_mm: float) -> np.ndarray:
    """Centre, corners and edge midpoints of the square scan field on z = 0, (9, 3)."""
    h = 0.5 * float(field_mm)
    g = np.array([-h, 0.0, h])
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel(), y.ravel(), np.zeros(9)], axis=-1)


def _segment_distance(points, a, b):
    """Distance of each of ``points`` (m, 3) to each segment a_i -> b (a (n, 3), b (3,)): (m, n)."""
    ab = b - a
    t = np.clip(np.einsum("mnc,nc->mn", points[:, None, :] - a[None], ab) / np.einsum("nc,nc->n", ab, ab), 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=-1)


def violations(discs: Mapping, *, field_mm: float, work_distance_mm: float, clearance: float = 10.0) -> dict[str, float]:
    """How far a design violates each constraint (mm; 0 = met), see the module's description.

    Parameters
    ----------
    discs : mapping of str to Disc
        The detectors.
    field_mm : float
        Side of the square scan field.
    work_distance_mm : float
        Height of the beam pivot.
    clearance : float
        Margin (mm) every constraint keeps.

    Returns
    -------
    dict
        ``{constraint: mm}`` in the order of :data:`CONSTRAINTS`.

    Examples
    --------
    Table 1's zeta = 25 deg layout fits; discs of radius 100 mm there overlap each other, and
    discs 30 mm from the axis reach into the beam's cone:

    >>> p = {"dh": 272, "dw": 127, "radius": 25, "aim_z": 0, "azimuth": 0}
    >>> v = violations(design_discs(p, 4), field_mm=80, work_distance_mm=400)
    >>> max(v.values())
    0.0
    >>> v = violations(design_discs({**p, "radius": 100}, 4), field_mm=80, work_distance_mm=400)
    >>> sorted(k for k, x in v.items() if x > 0)
    ['overlap']
    >>> v = violations(design_discs({**p, "dw": 30}, 4), field_mm=80, work_distance_mm=400)
    >>> sorted(k for k, x in v.items() if x > 0)
    ['beam', 'overlap']
    """
    clr = float(clearance)
    wd = float(work_distance_mm)
    (x0, x1), (y0, y1), (z0, z1) = CHAMBER_INTERIOR_MM
    names = list(discs)
    pts = np.stack([disc_points(discs[n]) for n in names])  # (K, m, 3)
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    out = dict.fromkeys(CONSTRAINTS, 0.0)
    out["chamber"] = float(np.max(np.stack([x - (x1 - clr), (x0 + clr) - x, y - (y1 - clr), (y0 + clr) - y,
                                            z - (z1 - clr), (z0 + clr) - z]).clip(0.0)))
    out["sheet"] = float(np.max(np.minimum(y - (SHEET_Y_MM[0] - clr), z - (SHEET_BOTTOM_MM - clr)).clip(0.0)))
    cheb = np.maximum(np.abs(x), np.abs(y))
    half = 0.5 * float(field_mm) * (1.0 - z / wd)
    in_cone_z = (z >= -clr) & (z <= wd + clr)
    out["beam"] = float(np.max(np.where(in_cone_z, (np.maximum(half, 0.0) + clr) - cheb, 0.0).clip(0.0)))
    above = (z >= wd - clr) & (z <= z1)
    out["column"] = float(np.max(np.where(above, (COLUMN_HALF_WIDTH_MM + clr) - cheb, 0.0).clip(0.0)))
    c = np.array([discs[n].center for n in names])
    r = np.array([discs[n].radius for n in names])
    nrm = np.array([discs[n].normal for n in names])
    fp = field_points(field_mm)
    k = len(names)
    if k > 1:
        dist = np.linalg.norm(c[:, None] - c[None], axis=-1)
        gap = (r[:, None] + r[None] + clr) - dist
        out["overlap"] = float(np.max(np.where(~np.eye(k, dtype=bool), gap, 0.0).clip(0.0)))
        worst = 0.0
        for j in range(k):
            d = _segment_distance(c, fp, c[j])  # (K discs, field points): disc i to segment field -> c_j
            d = np.delete(d, j, axis=0)
            worst = max(worst, float(np.max(((np.delete(r, j) + clr)[:, None] - d).clip(0.0))))
        out["occlusion"] = worst
    facing = np.einsum("kc,fkc->fk", nrm, fp[:, None, :] - c[None])
    out["facing"] = float(np.max((-facing).clip(0.0)))
    return out
