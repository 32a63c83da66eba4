"""Occlusion analysis (set-up time): where shadow rays provably cannot be blocked.

Per detector, the scan region on a surface from which nothing in the scene can block the view of
the detector; shadow rays from there are not cast, any other surface point casts them as usual.
numpy (scipy for hulls of many points), once per geometry; :func:`unblockable` is the kernel's test.

* A horizontal planar surface (flat plate, also inside the chamber): no triangle of any other shape
  (or of the bounding box of a non-mesh shape) cuts the convex hull of the scan region and the
  detector.
* Shallow relief (the melt plate): a mesh that is the graph of a continuous function z = h(x, y)
  over its bounding rectangle (:func:`relief_graph`), with |grad h| <= s on every triangle. A ray
  from a point p of the relief towards the detector rises at tan(elevation) > s; along its path
  h(p + t u) <= h(p) + s t stays below it, so the relief cannot block it, and the other shapes
  cannot when none cuts the hull of the scan region's box (its xy extent x [z_min, z_max]) and
  the detector. The elevation is bounded below by (lowest detector point - z_max) / (largest
  horizontal distance between the box and the detector). Steeper relief (flanks, cliffs,
  overhangs) keeps its shadow rays.
"""

import hashlib
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
    planes, facet = hull_planes_batch(p[None])
    return planes[0][facet[0]] if np.any(facet) else None


def hull_planes_batch(points):
    """Planes (B, F, 4) ``n . x + c`` (<= 0 inside) through every triple of ``points`` (B, P, 3)
    and which of them are facet planes of each hull (B, F): those with every point on their
    inner side. A flat hull (all points on one plane) has none; so has a collinear one."""
    i, j, k = np.array(list(itertools.combinations(range(points.shape[1]), 3))).T
    n = np.cross(points[:, j] - points[:, i], points[:, k] - points[:, i])  # (B, F, 3)
    length = np.linalg.norm(n, axis=2)
    size = np.maximum(1.0, np.ptp(points, axis=1).max(axis=1))[:, None]  # (B, 1)
    eps = 1e-10 * size  # Qhull's own precision for such coordinates is ~1e-13 of the size
    ok = length > eps * size
    n = n / np.where(ok, length, 1.0)[..., None]
    c = -np.einsum("bfk,bfk->bf", n, points[:, i])
    d = np.einsum("bpk,bfk->bpf", points, n) + c[:, None, :]  # (B, P, F): every point from every plane
    below = np.all(d <= eps[:, :, None], axis=1)
    above = np.all(d >= -eps[:, :, None], axis=1)
    flat = np.any(ok & below & above, axis=1)
    sign = np.where(below, 1.0, -1.0)
    facet = ok & (below | above) & ~flat[:, None]
    return np.concatenate([n * sign[..., None], (c * sign)[..., None]], axis=2), facet


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


def _scan_box(sensor, z_low, lo, hi):
    """(xmin, xmax, ymin, ymax) of the beam's hits at heights >= ``z_low`` (a margin for the beam
    profile and rounding), within the xy extent ``lo``-``hi`` of a surface, or None."""
    if not all(hasattr(sensor, a) for a in ("wd", "field", "field_y")) or not sensor.wd > z_low:
        return None
    scale = (sensor.wd - z_low) / sensor.wd if getattr(sensor, "projection", "perspective") == "perspective" else 1.0
    margin = 5.0 * getattr(sensor, "fwhm", 0.0) + 1e-3 * max(sensor.field, sensor.field_y)
    hx, hy = (0.5 * sensor.field + margin) * scale, (0.5 * sensor.field_y + margin) * scale
    box = (max(-hx, lo[0]), min(hx, hi[0]), max(-hy, lo[1]), min(hy, hi[1]))
    if box[0] >= box[1] or box[2] >= box[3]:
        return None
    return box


def _beam_region(shape, sensor):
    """(z0, xmin, xmax, ymin, ymax) of the first-event points on a horizontal plane ``shape``
    (rectangle, disk or planar mesh with normal +-z), or None."""
    if not is_planar(shape):
        return None
    tris = cover_triangles(shape)
    n = np.cross(tris[0, 1] - tris[0, 0], tris[0, 2] - tris[0, 0])
    n /= np.linalg.norm(n)
    if abs(abs(n[2]) - 1.0) > 1e-9:
        return None
    z0 = float(tris[0, 0, 2])
    box = _scan_box(sensor, z0, tris.reshape(-1, 3).min(axis=0), tris.reshape(-1, 3).max(axis=0))
    return None if box is None else (z0,) + box


#: Faces per block of :func:`relief_graph`'s per-triangle arithmetic (bounded scratch memory).
GRAPH_BLOCK = 1 << 20
#: Most faces of a mesh whose vertices are not shared (one per triangle corner) that
#: :func:`relief_graph` merges by their coordinates first; above it such a mesh keeps its shadow
#: rays (the merge sorts every corner: seconds for millions of triangles).
MERGE_MAX_FACES = 1 << 20


def relief_graph(vertices, faces):
    """(xmin, xmax, ymin, ymax, zmin, zmax, slope) of a triangle mesh (``vertices`` V x 3,
    ``faces`` F x 3) that is the graph of a continuous function z = h(x, y) over its bounding
    rectangle, ``slope`` the largest |grad h| of its triangles; None for any other mesh.

    The test: every triangle faces the same way along z (none vertical or degenerate); every edge
    is shared by two triangles in opposite directions or is a boundary edge on one side of the
    rectangle (vertices of equal coordinates are one where the mesh does not share them); and the
    triangles' projected areas sum to the rectangle's. Then the projection is one-to-one inside
    the rectangle (a local homeomorphism whose boundary runs once round it) and covers it, so h is
    single-valued and, being piecewise linear, Lipschitz with constant ``slope`` along any segment.
    A vertex that no face uses but lies outside the faces' rectangle makes the areas disagree: None.
    """
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    f = np.asarray(faces).reshape(-1, 3)
    if len(f) == 0 or not np.all(np.isfinite(v)) or not np.issubdtype(f.dtype, np.integer):
        return None
    up = down = 0
    area = slope = 0.0
    for s in range(0, len(f), GRAPH_BLOCK):
        t = f[s:s + GRAPH_BLOCK]
        p0 = v[t[:, 0]]
        e1, e2 = v[t[:, 1]] - p0, v[t[:, 2]] - p0
        nz = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        up += int(np.count_nonzero(nz > 0))
        down += int(np.count_nonzero(nz < 0))
        nx = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]
        ny = e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]
        area += 0.5 * float(np.sum(np.abs(nz)))
        with np.errstate(divide="ignore", invalid="ignore"):
            slope = max(slope, float(np.max(np.hypot(nx, ny) / np.abs(nz))))
    if not (up == len(f) or down == len(f)):
        return None
    lo, hi = v.min(axis=0), v.max(axis=0)
    rect = (hi[0] - lo[0]) * (hi[1] - lo[1])
    if not rect > 0 or abs(area - rect) > 1e-9 * rect:
        return None
    sides = _edges_on_sides(f, v, lo, hi)
    if sides is None and len(f) <= MERGE_MAX_FACES:
        pos, vid = np.unique(v, axis=0, return_inverse=True)  # vertices of equal coordinates are one
        if len(pos) < len(v):
            sides = _edges_on_sides(vid.reshape(-1)[f], pos, lo, hi)
    if not sides:
        return None
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), float(lo[2]), float(hi[2]), slope


def _edges_on_sides(f, v, lo, hi):
    """True if every edge of faces ``f`` runs once each way (two triangles, one orientation) or is a
    boundary edge on one side of the rectangle ``lo``-``hi``; False if an edge runs twice the same
    way; None if a boundary edge lies elsewhere (a hole, or vertices the mesh does not share).
    Edges are keyed a (V + 1) + b, built and looked up in blocks of faces (a 4.5 M-triangle mesh:
    0.1 GB of keys, not a gigabyte of temporaries)."""
    n = len(v) + 1

    def keys(block, reverse=False):
        a = block.astype(np.int64)
        b = a[:, [1, 2, 0]]
        return (b * n + a).reshape(-1) if reverse else (a * n + b).reshape(-1)

    directed = np.empty(3 * len(f), np.int64)
    for s in range(0, len(f), GRAPH_BLOCK):
        directed[3 * s:3 * (s + len(f[s:s + GRAPH_BLOCK]))] = keys(f[s:s + GRAPH_BLOCK])
    directed.sort()
    if np.any(directed[1:] == directed[:-1]):
        return False
    lone = []
    for s in range(0, len(f), GRAPH_BLOCK):
        reverse = keys(f[s:s + GRAPH_BLOCK], reverse=True)
        at = np.minimum(np.searchsorted(directed, reverse), len(directed) - 1)
        lone.append(reverse[directed[at] != reverse])  # no twin: a boundary edge (b, a)
    lone = np.concatenate(lone)
    pa, pb = v[lone % n, :2], v[lone // n, :2]
    tol = 1e-9 * max(1.0, float(np.max(hi - lo)))
    on_side = np.zeros(len(pa), bool)
    for axis, value in ((0, lo[0]), (0, hi[0]), (1, lo[1]), (1, hi[1])):
        on_side |= (np.abs(pa[:, axis] - value) <= tol) & (np.abs(pb[:, axis] - value) <= tol)
    return True if np.all(on_side) else None


#: relief_graph of the meshes seen lately, by their vertices and faces: a detector sweep repeats the
#: analysis at every point, and the test of a 0.12 M-triangle plate takes about 0.08 s
_GRAPHS = {}


def _relief_region(shape, sensor):
    """(zmin, zmax, slope, xmin, xmax, ymin, ymax) of the scanned part of a relief mesh that is a
    graph over its rectangle (:func:`relief_graph`), or None."""
    if shape.shape_type() != mi.ShapeType.Mesh or is_planar(shape):
        return None
    v = np.array(shape.vertex_positions_buffer(), dtype=np.float32)
    f = np.array(shape.faces_buffer(), dtype=np.uint32)
    digest = hashlib.blake2b(v, digest_size=16)
    digest.update(f)
    key = digest.digest()
    if key not in _GRAPHS:
        if len(_GRAPHS) >= 16:
            _GRAPHS.pop(next(iter(_GRAPHS)))
        _GRAPHS[key] = relief_graph(v, f)
    graph = _GRAPHS[key]
    if graph is None:
        return None
    x0, x1, y0, y1, z0, z1, slope = graph
    box = _scan_box(sensor, z0, (x0, y0), (x1, y1))
    return None if box is None else (z0, z1, slope) + box


def _rises_above(slope, box, z_top, cover):
    """True where every ray from the box (xy extent ``box``, heights <= ``z_top``) to a point of
    the detector's ``cover`` (triangles) rises more steeply than ``slope``."""
    x0, x1, y0, y1 = box
    pts = cover.reshape(-1, 3)
    rise = float(pts[:, 2].min()) - z_top
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    run = float(np.max(np.linalg.norm(pts[None, :, :2] - corners[:, None, :], axis=-1)))
    return rise > 0 and rise > slope * run * (1.0 + 1e-9)


def unoccluded_regions(scene, sensor, detectors):
    """Per detector: [(shape, (z, xmin, xmax, ymin, ymax))] of scan regions on horizontal planar
    surfaces and on shallow relief from which nothing in the scene can block the view of the
    detector, so that shadow rays from there are not needed (e.g. the flat plate, also inside the
    chamber; the melt plate)."""
    shapes = {shape_key(sh): sh for sh in scene.shapes()}
    planes = [(k, sh, _beam_region(sh, sensor)) for k, sh in shapes.items() if not sh.is_emitter()]
    planes = [(k, sh, r) for k, sh, r in planes if r is not None]
    reliefs = [(k, sh, _relief_region(sh, sensor)) for k, sh in shapes.items() if not sh.is_emitter()]
    reliefs = [(k, sh, r) for k, sh, r in reliefs if r is not None]
    covers = {k: cover_triangles(sh) for k, sh in shapes.items()} if planes or reliefs else {}
    out = []
    for _, det in detectors:
        free = []
        if not is_planar(det):  # a curved detector hides its own far side: its shadow rays are needed
            out.append(free)
            continue
        dk = shape_key(det)
        for k, sh, (z0, x0, x1, y0, y1) in planes:
            pts = np.vstack([[[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0]], covers[dk].reshape(-1, 3)])
            if _separated_from_others(pts, covers, (k, dk)):
                free.append((sh, (z0, x0, x1, y0, y1)))
        for k, sh, (z0, z1, slope, x0, x1, y0, y1) in reliefs:
            if not _rises_above(slope, (x0, x1, y0, y1), z1, covers[dk]):
                continue
            box = [[x, y, z] for z in (z0, z1) for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
            pts = np.vstack([box, covers[dk].reshape(-1, 3)])
            if _separated_from_others(pts, covers, (k, dk)):
                free.append((sh, (z0, x0, x1, y0, y1)))
        out.append(free)
    return out


def _separated_from_others(pts, covers, own):
    """:func:`_all_separated` for the hull of ``pts`` and the triangles of every shape but ``own``."""
    tol = 1e-6 * max(1.0, float(np.ptp(pts, axis=0).max()))
    others = [covers[o] for o in covers if o not in own]
    tris = np.concatenate(others) if others else np.zeros((0, 3, 3))
    return _all_separated(pts, tris, tol)


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
