"""Detectors of an ELO scene: discovery, geometry, triangulation for the quadrature, surfaces through a disc (set-up time).

A detector is any shape carrying an emitter; its ``id`` is its channel name. For the triangle
quadrature of Appendix A (Eq. A2) a detector is covered by triangles wound counter-clockwise about
its front normal: a disk as an equal-area fan or rings, a rectangle as a grid, a mesh detector as
its own triangles. numpy, run once per render before the kernel is built.
"""

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from elo_mitsuba.constants import DETECTOR_NAMES
from elo_mitsuba.errors import EloInputError
from elo_mitsuba.options import MAX_QUADRATURE_TRIANGLES

from ._shapes import cover_triangles, shape_key


def find_detectors(scene):
    """[(id, shape)] of the detector shapes (those carrying an emitter), in a stable order.

    right, left, back, front first (the paper's order), then other ids alphabetically.
    """
    found = {}
    for shape in scene.shapes():
        if shape.is_emitter():
            name = shape.id()
            if not name:
                raise EloInputError("a detector shape (one with an emitter) has no id; give it id=\"...\"")
            if name in found:
                raise EloInputError(f"two detector shapes share the id {name!r}")
            if "." in name or name.startswith("_") or name == "Y":  # the film's and outputs' own channel names
                raise EloInputError(f"detector id {name!r}: an id names the detector's image channels (<id>, <id>.e2, "
                                    "<id>.err) and may not contain '.', start with '_' or be 'Y'")
            found[name] = shape
    order = [n for n in DETECTOR_NAMES if n in found] + sorted(n for n in found if n not in DETECTOR_NAMES)
    return [(n, found[n]) for n in order]


def _local_disk_triangles(n_tri):
    """Equal-area triangulation of the unit disk (z = 0), counter-clockwise about +z.

    n_tri <= 16: a fan of n_tri sectors; more: rings (inner fan + quads) of M sectors. Every
    ring polygon is enlarged to the area of its circle, so the triangles cover pi exactly.
    """
    rings = 1 if n_tri <= 16 else max(1, int(round(math.sqrt(n_tri / 8.0))))
    m = max(4, int(round(n_tri / (2 * rings - 1))))
    grow = math.sqrt(2.0 * math.pi / (m * math.sin(2.0 * math.pi / m)))
    phi = 2.0 * math.pi * np.arange(m) / m
    ring_pts = [np.stack([np.cos(phi), np.sin(phi), np.zeros(m)], -1) * (math.sqrt((i + 1) / rings) * grow)
                for i in range(rings)]
    centre = np.zeros(3)
    tris = []
    for k in range(m):
        k2 = (k + 1) % m
        tris.append((centre, ring_pts[0][k], ring_pts[0][k2]))
        for i in range(1, rings):
            a, b = ring_pts[i - 1], ring_pts[i]
            tris.append((a[k], b[k], b[k2]))
            tris.append((a[k], b[k2], a[k2]))
    return np.array(tris)


def _local_rectangle_triangles(n_tri):
    """[-1, 1]^2 at z = 0 as an n x n grid of 2 n^2 triangles, counter-clockwise about +z."""
    n = max(1, int(round(math.sqrt(n_tri / 2.0))))
    t = np.linspace(-1.0, 1.0, n + 1)
    tris = []
    for i in range(n):
        for j in range(n):
            p00, p10 = np.array([t[i], t[j], 0.0]), np.array([t[i + 1], t[j], 0.0])
            p01, p11 = np.array([t[i], t[j + 1], 0.0]), np.array([t[i + 1], t[j + 1], 0.0])
            tris += [(p00, p10, p11), (p00, p11, p01)]
    return np.array(tris)


def parse_detector_list(text, names, option):
    """Detector ids of a comma-separated option value (``"*"`` = all, ``""`` = none), checked
    against the scene's ``names``."""
    text = str(text).strip()
    if not text:
        return set()
    if text == "*":
        return set(names)
    ids = {t.strip() for t in text.split(",") if t.strip()}
    unknown = sorted(ids - set(names))
    if unknown:
        raise EloInputError(f"elo: {option}={text!r} names no detector {unknown[0]!r}; detectors: "
                            f"{', '.join(names)} (or '*' for all)")
    return ids


def detector_triangles(shape, n_tri, name="detector"):
    """World-space triangles (T, 3, 3) covering a detector, counter-clockwise about its front
    normal (the side its one-sided emitter collects on)."""
    stype = shape.shape_type()
    if stype in (mi.ShapeType.Disk, mi.ShapeType.Rectangle):
        params = mi.traverse(shape)
        m = np.array(params["to_world"].matrix, dtype=float).reshape(-1, 4, 4)[0]
        local = _local_disk_triangles(n_tri) if stype == mi.ShapeType.Disk else _local_rectangle_triangles(n_tri)
        world = local @ m[:3, :3].T + m[:3, 3]
        if np.linalg.det(m[:3, :3]) < 0:  # a mirroring transform flips the winding
            world = world[:, ::-1]
        return world
    if stype == mi.ShapeType.Mesh:
        n_faces = int(shape.face_count())
        if n_faces > MAX_QUADRATURE_TRIANGLES:
            raise EloInputError(
                f"detector {name!r}: a mesh of {n_faces} triangles is too fine for "
                f"detector_sampling=quadrature (at most {MAX_QUADRATURE_TRIANGLES}); use stratified")
        v = np.array(shape.vertex_positions_buffer(), dtype=float).reshape(-1, 3)
        f = np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
        return v[f]
    raise EloInputError(
        f"detector {name!r}: detector_sampling=quadrature (what every quality preset uses) supports disk, "
        "rectangle and mesh detectors; render this shape with quality 'scene' (--quality scene) and "
        "detector_sampling='stratified' in the scene's <integrator>")


def quadrature_geometry(detectors, n_tri):
    """Per detector: (vertices as opaque Point3f, [((i, j, k), opaque 2 A n)]) of its triangles.

    Shared vertices are subtracted from the scattering point and normed once in the kernel. The
    edge cross products (q2 - q1) x (q3 - q1) are taken in float64 here: Eq. A1's numerator is
    v1 . (v2 x v3) = v1 . ((q2 - q1) x (q3 - q1)), without the float32 cancellation of v2 x v3
    for small or distant triangles.
    """
    out = []
    for name, shape in detectors:
        tris = detector_triangles(shape, n_tri, name)
        if not np.all(np.isfinite(tris)):
            raise EloInputError(f"detector {name!r}: non-finite geometry")
        area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
        if not np.sum(area) > 0:
            raise EloInputError(f"detector {name!r} has zero area")
        verts, index = np.unique(tris.reshape(-1, 3), axis=0, return_inverse=True)
        index = index.reshape(-1, 3)
        normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        out.append(([dr.opaque(mi.Point3f, [float(x) for x in v]) for v in verts],
                    [(tuple(int(i) for i in t), dr.opaque(mi.Vector3f, [float(x) for x in n]))
                     for t, n in zip(index, normals)]))
    return out


def detector_geometry(shape, to_world=None) -> dict:
    """Centre, unit front normal, equivalent radius and area of a detector (mm, mm^2).

    Exact from ``to_world`` for a disk, rectangle, sphere ... (a unit shape placed by its
    transform); a mesh, or a shape without a transform, from samples of its surface."""
    if shape.is_mesh() or to_world is None:
        return _sampled_geometry(shape)
    return _placed_geometry(to_world, shape)


def surfaces_through_detectors(scene, detectors, segments: int = 16, cache=None):
    """[(detector, what)] of the scene's surfaces that pass through a detector disc: segments along
    the disc's rim polygon and its diameters (``segments`` points on the rim), just in front of its
    face, that cross a surface (a detector moved through a chamber wall): a mesh's or rectangle's
    triangles near the disc, a sphere, cylinder or disk exactly, in its own frame. On the host: no
    kernel, so a re-render after a move compiles nothing. ``cache`` (a dict): each mesh's triangles,
    kept by shape with its vertex buffer (held: Dr.Jit gives a freed array's index to new ones),
    vertex count and bounds (a merged mesh's bbox() is empty, so its bounds come from its
    triangles)."""

    cache = {} if cache is None else cache
    others, boxes = [], []
    for sh in scene.shapes():
        kind = sh.shape_type()
        if sh.is_emitter() or kind not in (mi.ShapeType.Mesh, mi.ShapeType.Rectangle) + tuple(_LOCAL_TESTS):
            continue
        if kind in _LOCAL_TESTS:  # the exact surface, in its own frame: the affine map keeps segments segments
            to_world = np.array(mi.traverse(sh)["to_world"].matrix, dtype=float).reshape(-1, 4, 4)[0]
            box = sh.bbox()
            entry = ((_LOCAL_TESTS[kind], np.linalg.inv(to_world)), np.array(box.min, float).ravel(),
                     np.array(box.max, float).ravel())
        else:
            # a mesh's triangles are kept (a rectangle's two are read again: its bounds do not tell
            # a plate tilted +10 deg from one tilted -10 deg)
            # the vertex buffer is held with them, so that no new buffer takes its variable index
            buffer = sh.vertex_positions_buffer() if sh.is_mesh() else None
            stamp = (sh.vertex_count(), tuple(sh.bbox().min), tuple(sh.bbox().max)) if sh.is_mesh() else None
            held = cache.get(shape_key(sh)) if sh.is_mesh() else None
            entry = held[2] if held is not None and held[0].index == buffer.index and held[1] == stamp else None
            if entry is None:
                tris = cover_triangles(sh)
                entry = (tris, tris.reshape(-1, 3).min(axis=0), tris.reshape(-1, 3).max(axis=0))
                if sh.is_mesh():
                    cache[shape_key(sh)] = (buffer, stamp, entry)
        others.append((sh, entry[0]))
        boxes.append(entry[1:])
    found = []
    for name, shape in detectors:
        if shape.shape_type() != mi.ShapeType.Disk:
            continue
        g = _placed_geometry(mi.traverse(shape)["to_world"], shape)
        c, n, r = np.array(g["center"]), np.array(g["normal"]), float(g["radius"])
        if not (r > 0 and np.all(np.isfinite(n))):
            continue
        a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        phi = 2.0 * np.pi * np.arange(segments) / segments
        rim = c + 1e-4 * r * n + 0.999 * r * (np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b)
        i = np.r_[np.arange(segments), np.arange(segments // 2)]
        j = np.r_[(np.arange(segments) + 1) % segments, np.arange(segments // 2) + segments // 2]
        p0, p1 = rim[i], rim[j]
        lo, hi = c - r, c + r
        for (sh, tris), (blo, bhi) in zip(others, boxes):
            if np.any(bhi < lo) or np.any(blo > hi):
                continue
            if isinstance(tris, tuple):
                test, to_local = tris
                crossed = test(p0 @ to_local[:3, :3].T + to_local[:3, 3], p1 @ to_local[:3, :3].T + to_local[:3, 3])
            else:
                near = np.all(tris.max(axis=1) >= lo, axis=1) & np.all(tris.min(axis=1) <= hi, axis=1)
                crossed = np.any(near) and _segments_cross(p0, p1, tris[near])
            if crossed:
                found.append((name, repr(sh.id()) if sh.id() else
                              "a surface of the scene (without an id: Mitsuba merges shapes of one material)"))
                break
    return found


def _roots_in_segment(a, b, c):
    """Per segment, the roots t in [0, 1] of a t^2 + b t + c = 0 (NaN where none): two columns."""
    disc = b * b - 4.0 * a * c
    ok = (disc >= 0) & (a > 0)
    q = np.sqrt(np.where(ok, disc, 0.0))
    t = np.stack([(-b - q), (-b + q)], axis=1) / np.where(ok, 2.0 * a, 1.0)[:, None]
    return np.where(ok[:, None] & (t >= 0.0) & (t <= 1.0), t, np.nan)


def _crosses_unit_sphere(p0, p1) -> bool:
    """Whether a segment meets Mitsuba's ``sphere`` in its own frame (radius 1 about the origin)."""
    d = p1 - p0
    t = _roots_in_segment(np.sum(d * d, 1), 2.0 * np.sum(p0 * d, 1), np.sum(p0 * p0, 1) - 1.0)
    return bool(np.any(np.isfinite(t)))


def _crosses_unit_cylinder(p0, p1) -> bool:
    """... Mitsuba's ``cylinder`` (an open tube of radius 1 about z, from z = 0 to 1)."""
    d = p1 - p0
    t = _roots_in_segment(d[:, 0] ** 2 + d[:, 1] ** 2, 2.0 * (p0[:, 0] * d[:, 0] + p0[:, 1] * d[:, 1]),
                          p0[:, 0] ** 2 + p0[:, 1] ** 2 - 1.0)
    z = p0[:, 2:3] + t * d[:, 2:3]
    return bool(np.any(np.isfinite(t) & (z >= 0.0) & (z <= 1.0)))


def _crosses_unit_disk(p0, p1) -> bool:
    """... Mitsuba's ``disk`` (radius 1 about the origin in z = 0)."""
    d = p1 - p0
    with np.errstate(divide="ignore", invalid="ignore"):  # a segment parallel to the disk: no crossing
        t = -p0[:, 2] / d[:, 2]
        x, y = p0[:, 0] + t * d[:, 0], p0[:, 1] + t * d[:, 1]
    return bool(np.any(np.isfinite(t) & (t >= 0.0) & (t <= 1.0) & (x * x + y * y <= 1.0)))


#: The surfaces tested exactly, in their own frame, rather than by covering triangles.
_LOCAL_TESTS = {mi.ShapeType.Sphere: _crosses_unit_sphere, mi.ShapeType.Cylinder: _crosses_unit_cylinder,
                mi.ShapeType.Disk: _crosses_unit_disk}


def _segments_cross(p0, p1, tris) -> bool:
    """Whether any segment p0[k] -> p1[k] crosses any triangle (Moeller-Trumbore, all pairs)."""
    d = (p1 - p0)[:, None, :]
    e1, e2 = (tris[:, 1] - tris[:, 0])[None], (tris[:, 2] - tris[:, 0])[None]
    h = np.cross(d, e2)
    det = np.einsum("stk,stk->st", e1, h)
    ok = np.abs(det) > 1e-12 * np.linalg.norm(e1, axis=-1) * np.linalg.norm(e2, axis=-1) * np.linalg.norm(d, axis=-1)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    sv = p0[:, None, :] - tris[None, :, 0]
    u = np.einsum("stk,stk->st", sv, h) * inv
    q = np.cross(sv, e1)
    v = np.einsum("stk,stk->st", d, q) * inv
    t = np.einsum("stk,stk->st", e2, q) * inv
    return bool(np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)))


def _placed_geometry(to_world, shape) -> dict:
    """Centre, front normal and equivalent radius of a unit shape placed by ``to_world``."""
    m = np.array(to_world.matrix, dtype=float).reshape(4, 4) if hasattr(to_world, "matrix") else None
    m = m.squeeze() if m is not None else np.eye(4)
    centre = m[:3, 3]
    area = float(shape.surface_area()[0])
    if abs(np.linalg.det(m[:3, :3])) < 1e-300:  # a zero scale: no normal; the caller names the detector
        return {"center": [round(float(x), 6) for x in centre], "normal": [math.nan] * 3, "radius": 0.0,
                "area_mm2": 0.0}
    normal = np.linalg.inv(m[:3, :3]).T @ np.array([0.0, 0.0, 1.0])
    normal /= np.linalg.norm(normal)
    return {
        "center": [round(float(x), 6) for x in centre],
        "normal": [round(float(x), 6) for x in normal],
        "radius": round(math.sqrt(area / math.pi), 6),
        "area_mm2": round(area, 6),
    }


def _sampled_geometry(shape, n_samples: int = 4096) -> dict:
    """Area-weighted centroid, mean unit normal and equivalent radius of a shape (mm)."""
    u = (np.arange(n_samples) + 0.5) / n_samples
    v = np.modf(np.arange(n_samples) * 0.6180339887498949)[0]
    ps = shape.sample_position(0.0, mi.Point2f(mi.Float(u.astype(np.float32)), mi.Float(v.astype(np.float32))))
    p = np.array([np.asarray(ps.p.x), np.asarray(ps.p.y), np.asarray(ps.p.z)]).T
    n = np.array([np.asarray(ps.n.x), np.asarray(ps.n.y), np.asarray(ps.n.z)]).T
    normal = n.mean(axis=0)
    normal /= np.linalg.norm(normal)
    area = float(shape.surface_area()[0])
    return {
        "center": [round(float(x), 6) for x in p.mean(axis=0)],
        "normal": [round(float(x), 6) for x in normal],
        "radius": round(math.sqrt(area / math.pi), 6),
        "area_mm2": round(area, 6),
    }
