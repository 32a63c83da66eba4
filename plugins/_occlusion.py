"""Occlusion analysis (set-up time): where shadow rays provably cannot be blocked.

Per detector, the scan region on a horizontal planar surface from which nothing in the scene can
block the view of the detector: no triangle of any other shape (or of the bounding box of a
non-mesh shape) can cut the convex hull of that region and the detector. Shadow rays from there
are not cast (flat plate, also inside the chamber); any other surface point casts them as usual.
numpy (scipy for hulls of many points), once per render; :func:`unblockable` is the kernel's test.
"""

import itertools

import drjit as dr
import mitsuba as mi
import numpy as np

from ._shapes import cover_triangles, is_planar, shape_key


#: Up to this many distinct points the hull's facet planes are found by trying every triple of
#: points (the scenes' hulls: a scan region's 4 corners and a disc detector's 4 cover corners);
#: above it by Qhull (scipy.spatial). Why: importing scipy.spatial costs 0.6 s, a third of a new
#: process's scene load, for hulls of 8 points.
BRUTE_FORCE_POINTS = 16


def _hull_planes(points):
    """(F, 4) planes ``n . x + c`` (unit outward ``n``; <= 0 inside) whose set is that of the
    facets of the convex hull of ``points`` (each facet may appear more than once), or None when
    the hull is flat or has fewer than 4 points (as Qhull refuses it)."""
    p = np.unique(np.asarray(points, dtype=float), axis=0)
    if len(p) > BRUTE_FORCE_POINTS:
        from scipy.spatial import ConvexHull, QhullError

        try:
            return ConvexHull(p).equations
        except (QhullError, ValueError):
            return None
    if len(p) < 4:
        return None
    i, j, k = np.array(list(itertools.combinations(range(len(p)), 3))).T
    n = np.cross(p[j] - p[i], p[k] - p[i])
    length = np.linalg.norm(n, axis=1)
    size = max(1.0, float(np.ptp(p, axis=0).max()))
    eps = 1e-10 * size  # Qhull's own precision for such coordinates is ~1e-13 of the size
    keep = length > eps * size
    if not np.any(keep):
        return None  # all points collinear
    n, i = n[keep] / length[keep, None], i[keep]
    c = -np.einsum("fk,fk->f", n, p[i])
    d = p @ n.T + c  # (P, F): signed distances of every point from every candidate plane
    below, above = np.all(d <= eps, axis=0), np.all(d >= -eps, axis=0)
    if np.any(below & above):
        return None  # every point on one plane: a flat hull
    planes = np.concatenate([np.c_[n[below], c[below]], -np.c_[n[above], c[above]]])
    return planes if len(planes) else None


def _all_separated(points, tris, tol):
    """True if no triangle of ``tris`` (T, 3, 3) can intersect the convex hull of ``points``
    (conservative: separating planes are the hull's faces and the triangles' own planes)."""
    eq = _hull_planes(points)  # n . x + c <= 0 inside
    if eq is None:
        return False
    lo, hi = points.min(axis=0) - tol, points.max(axis=0) + tol
    for start in range(0, len(tris), 65536):
        t = tris[start:start + 65536]
        # triangles whose bounding box misses the hull's are separated
        near = np.all(t.max(axis=1) >= lo, axis=1) & np.all(t.min(axis=1) <= hi, axis=1)
        t = t[near]
        if len(t) == 0:
            continue
        d = t @ eq[:, :3].T + eq[:, 3]  # (T, 3, F)
        sep = np.any(np.all(d > tol, axis=1), axis=1)
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        length = np.linalg.norm(n, axis=1)
        ok = length > 0
        side = np.einsum("tpk,tk->tp", points[None, :, :] - t[:, None, 0, :], n / np.where(ok, length, 1.0)[:, None])
        sep |= ok & (np.all(side >= -tol, axis=1) | np.all(side <= tol, axis=1))
        if not np.all(sep):
            return False
    return True


def _beam_region(shape, sensor):
    """(z0, xmin, xmax, ymin, ymax) of the first-event points on a horizontal plane ``shape``
    (rectangle, disk or planar mesh with normal +-z), or None."""
    if not is_planar(shape) or not all(hasattr(sensor, a) for a in ("wd", "field", "field_y")):
        return None
    tris = cover_triangles(shape)
    n = np.cross(tris[0, 1] - tris[0, 0], tris[0, 2] - tris[0, 0])
    n /= np.linalg.norm(n)
    if abs(abs(n[2]) - 1.0) > 1e-9:
        return None
    z0 = float(tris[0, 0, 2])
    if not sensor.wd > z0:
        return None
    scale = (sensor.wd - z0) / sensor.wd if getattr(sensor, "projection", "perspective") == "perspective" else 1.0
    margin = 5.0 * getattr(sensor, "fwhm", 0.0) + 1e-3 * max(sensor.field, sensor.field_y)
    hx, hy = (0.5 * sensor.field + margin) * scale, (0.5 * sensor.field_y + margin) * scale
    lo, hi = tris.reshape(-1, 3).min(axis=0), tris.reshape(-1, 3).max(axis=0)
    box = (max(-hx, lo[0]), min(hx, hi[0]), max(-hy, lo[1]), min(hy, hi[1]))
    if box[0] >= box[1] or box[2] >= box[3]:
        return None
    return (z0,) + box


def unoccluded_regions(scene, sensor, detectors):
    """Per detector: [(shape, (z0, xmin, xmax, ymin, ymax))] of scan regions on horizontal planar
    surfaces from which nothing in the scene can block the view of the detector, so that
    shadow rays from there are not needed (e.g. the flat plate, also inside the chamber)."""
    shapes = {shape_key(sh): sh for sh in scene.shapes()}
    regions = [(k, sh, _beam_region(sh, sensor)) for k, sh in shapes.items() if not sh.is_emitter()]
    regions = [(k, sh, r) for k, sh, r in regions if r is not None]
    covers = {k: cover_triangles(sh) for k, sh in shapes.items()} if regions else {}
    out = []
    for _, det in detectors:
        free = []
        if not is_planar(det):  # a curved detector hides its own far side: its shadow rays are needed
            out.append(free)
            continue
        dk = shape_key(det)
        for k, sh, (z0, x0, x1, y0, y1) in regions:
            pts = np.vstack([[[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0]], covers[dk].reshape(-1, 3)])
            tol = 1e-6 * max(1.0, float(np.ptp(pts, axis=0).max()))
            others = [covers[o] for o in shapes if o not in (k, dk)]
            tris = np.concatenate(others) if others else np.zeros((0, 3, 3))
            if _all_separated(pts, tris, tol):
                free.append((sh, (z0, x0, x1, y0, y1)))
        out.append(free)
    return out


def unblockable_regions(scene, sensor, detectors):
    """:func:`unoccluded_regions` as kernel constants: per detector [(opaque shape id, opaque
    [xmin, xmax, ymin, ymax])]."""
    return [[(dr.opaque(mi.UInt32, shape_key(sh)), [dr.opaque(mi.Float, float(b)) for b in bounds[1:]])
             for sh, bounds in free] for free in unoccluded_regions(scene, sensor, detectors)]


def unblockable(si, regions):
    """Lanes whose surface point lies in one of ``regions`` (one detector's), or None if none."""
    if not regions:
        return None
    shape_id = dr.reinterpret_array(mi.UInt32, si.shape)
    skip = mi.Bool(False)
    for sid, (x0, x1, y0, y1) in regions:
        skip |= (shape_id == sid) & (si.p.x >= x0) & (si.p.x <= x1) & (si.p.y >= y0) & (si.p.y <= y1)
    return skip
