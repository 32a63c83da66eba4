"""What the beam meets: relief under it (scattering surfaces it hits that are not one plane), and
detectors in its path (:func:`detectors_in_beam`).

Such a surface can scatter electrons onto itself over distances of its own relief (flank to
flank), so events >= 2 vary on that scale, also along a flank whose normals agree: the bounce
filter's window average is biased there (:mod:`._bounce_filter`). Surfaces the beam does not hit
(chamber walls, merged by Mitsuba into one mesh of many planes) add events >= 2 that vary over
tens of mm and do not count as relief.
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from ._shapes import cover_triangles, is_planar, shape_key, to_world_matrix

#: Beam rays per side of the coarse grid over the field (plus a margin of 3 beam sigmas).
GRID = 65


def relief_under_beam(scene, sensor, surfaces, probe=None, planar=is_planar):
    """Ids (or ``"a shape"``) of the ``surfaces`` that the beam of ``sensor`` hits on a
    :data:`GRID` x :data:`GRID` grid over its field and that are not one plane.

    Parameters
    ----------
    scene : mi.Scene
    sensor : the ``elo_beam`` sensor (``field``, ``field_y``, ``wd``, ``projection``, ``sigma``)
    surfaces : list of mi.Shape
        The scattering surfaces (objects, walls, backscattering detector plates).
    probe : callable, optional
        Returns :func:`beam_probe`'s hits (shared with other users of the same probe).
    planar : callable, optional
        :func:`~._shapes.is_planar`, or a memo of it (:meth:`~._shapes.GeometryKey.planar`).
    """
    candidates = [s for s in surfaces if not planar(s)]
    if not candidates:
        return []
    si = probe() if probe is not None else beam_probe(scene, sensor)
    hit_ids = set()
    for shape in candidates:  # few shapes: one comparison each, vectorised over the grid
        mask = si.is_valid() & (dr.reinterpret_array(mi.UInt32, si.shape) == shape_key(shape))
        if bool(dr.any(mask)):
            hit_ids.add(id(shape))
    return [s.id() or "a shape" for s in candidates if id(s) in hit_ids]


#: A hit counts as on a surface's back when the beam arrives at least this far behind its plane
#: (cosine of the angle to the geometric normal): grazing hits on near-vertical facets of a
#: consistently wound mesh round either way.
BACK_COS = -1e-2


def surfaces_seen_from_behind(surfaces, sensor, probe):
    """[(name, share)] of the scattering ``surfaces`` whose back the beam of ``sensor`` meets, with
    the share of the scan field where it does (:func:`beam_probe`'s grid, its margin left out):
    triangles wound clockwise seen from the gun (a mesh oriented inconsistently, a surface upside
    down). g_BSE scatters nothing back through a surface's underside, so those pixels are dark."""
    if not surfaces or not all(hasattr(sensor, k) for k in ("wd", "field", "field_y")):
        return []
    si = probe()
    behind = np.asarray(si.is_valid() & (dr.dot(si.n, si.to_world(si.wi)) < BACK_COS), dtype=bool)
    if not behind.any():
        return []
    inside = _in_field(sensor)
    keys = np.asarray(dr.reinterpret_array(mi.UInt32, si.shape))
    found = []
    for shape in surfaces:
        share = float(np.count_nonzero(behind & inside & (keys == shape_key(shape)))) / max(1, np.count_nonzero(inside))
        if share > 0:
            found.append((shape.id() or "a surface without an id", share))
    return found


#: Directions per probe point of :func:`surfaces_met_from_behind`, cosine-weighted about the normal
#: where the beam lands: a Hammersley set shifted by a random offset per point, drawn with
#: :data:`LEAVING_SEED` (the same rays in every run).
LEAVING_DIRECTIONS = 16
LEAVING_SEED = 20261206
#: :func:`surfaces_met_from_behind` names a surface whose back takes at least this share of the
#: electrons leaving the field and at least :data:`BACK_MAJORITY` of those reaching the surface (a
#: slab of two faces with open edges lets a few electrons in between: they are not named). The
#: radiation sheet's open 2 mm lower edge took 0.10-0.17 % of the probe's rays (by scene) and 1.0 %
#: of back.e2 at (10, 10) mm; no plane of a closed shipped scene is met from behind at all.
BACK_SHARE_OF_ALL = 3e-4
BACK_MAJORITY = 0.5
#: At most this many planes named per shape (the ones whose back takes the most).
MAX_PLANES = 3


def surfaces_met_from_behind(scene, surfaces, sensor, probe) -> list[dict]:
    """The planes of the scattering ``surfaces`` whose back the electrons leaving the scan field
    meet: a wall or shield that faces away from the field (a rectangle turned outward by its
    look-at, a mesh wound inside out). g_BSE sends nothing back from a surface's back, so such a
    plane absorbs what it should scatter, and events >= 2 come out too small with no other sign
    (a wall of the chamber turned outward took 16 % of the 2nd event of the detector beside it).

    Rays leave :func:`beam_probe`'s hits (``probe()``, the beam of ``sensor``) in :data:`LEAVING_DIRECTIONS`
    cosine-weighted directions about the normal there. Hits are grouped by shape and plane (the
    geometric normal to 1e-3 and its offset to 1 mm: Mitsuba merges the walls of a chamber into
    one mesh, so a shape alone would not say which wall). A shape met mostly from behind is named
    once, as a whole (a sphere, a cylinder's mesh); else at most :data:`MAX_PLANES` of its planes.
    Returns one dict per plane or shape named: ``name`` (the shape's id, "" for none), ``normal``
    (None for a curved surface), ``point`` (the mean of the hits on its back, mm),
    ``share`` (of all the probe's rays that end on its back) and ``own`` (of those reaching
    the plane); a plane is named when ``share`` >= :data:`BACK_SHARE_OF_ALL` and ``own`` >=
    :data:`BACK_MAJORITY`.
    """
    if not surfaces or not all(hasattr(sensor, k) for k in ("wd", "field", "field_y")):  # no beam: no probe
        return []
    si = probe()
    valid = np.flatnonzero(np.asarray(si.is_valid(), dtype=bool))
    if valid.size == 0:
        return []
    k = LEAVING_DIRECTIONS
    u = (np.arange(k) + 0.5) / k
    v = np.array([int(f"{i:b}"[::-1], 2) / 2.0 ** len(f"{i:b}") if i else 0.0 for i in range(k)])  # radical inverse
    # one Hammersley set per point, each shifted (Cranley-Patterson) by a fixed-seed offset: a set
    # shared by all points aliases with thin targets (a 2 mm edge 320 mm away came out at 0.13 %
    # or 0.47 % for a true 0.3 %, by the set); shifted sets estimate the shares without bias
    shift = np.random.default_rng(LEAVING_SEED).random((valid.size, 1, 2))
    uv = (np.stack([np.broadcast_to(u, (valid.size, k)), np.broadcast_to(v, (valid.size, k))], axis=-1) + shift) % 1.0
    at = dr.gather(type(si), si, mi.UInt32(np.repeat(valid, k).astype(np.uint32)))
    local = mi.warp.square_to_cosine_hemisphere(mi.Point2f(mi.Float(uv[..., 0].ravel().astype(np.float32)),
                                                            mi.Float(uv[..., 1].ravel().astype(np.float32))))
    ray = at.spawn_ray(mi.Frame3f(at.n).to_world(local))
    hit = scene.ray_intersect(ray)
    reached = np.asarray(hit.is_valid(), dtype=bool)
    n = np.asarray(hit.n, dtype=np.float64).reshape(3, -1).T if reached.any() else np.zeros((reached.size, 3))
    p = np.asarray(hit.p, dtype=np.float64).reshape(3, -1).T if reached.any() else np.zeros((reached.size, 3))
    d = np.asarray(ray.d, dtype=np.float64).reshape(3, -1).T
    back = reached & (np.sum(n * d, axis=1) > -BACK_COS)
    keys = np.asarray(dr.reinterpret_array(mi.UInt32, hit.shape))
    found = []
    for shape in surfaces:
        mine = reached & (keys == shape_key(shape))
        behind = back[mine]
        if np.count_nonzero(behind) < BACK_SHARE_OF_ALL * reached.size:
            continue
        # planes: normal to 1e-3, offset to 1 mm
        plane = np.c_[np.round(n[mine] * 1e3), np.round(np.sum(n[mine] * p[mine], axis=1))].astype(np.int64)
        groups, which = np.unique(plane, axis=0, return_inverse=True)
        which = which.ravel()
        per_plane = np.bincount(which[behind], minlength=len(groups))

        def entry(where, normal):
            count = np.count_nonzero(behind & where)
            return {"name": shape.id(), "normal": normal, "point": p[mine][behind & where].mean(axis=0).round(1).tolist(),
                    "share": count / reached.size, "own": count / np.count_nonzero(where)}

        if np.count_nonzero(behind) >= BACK_MAJORITY * behind.size:  # the shape as a whole: named once
            top = int(np.argmax(per_plane))
            flat = per_plane[top] >= 0.9 * np.count_nonzero(behind)  # one plane, or curved (a sphere, a mesh)
            found.append(entry(np.ones(behind.size, bool), (groups[top, :3] / 1e3).tolist() if flat else None))
            continue
        # shapes Mitsuba merged (a chamber's walls are one mesh): the planes whose back takes the most
        for g in np.argsort(-per_plane)[:MAX_PLANES]:
            in_g = which == g
            if per_plane[g] >= BACK_SHARE_OF_ALL * reached.size and per_plane[g] >= BACK_MAJORITY * np.count_nonzero(in_g):
                found.append(entry(in_g, (groups[g, :3] / 1e3).tolist()))
    return found


#: Where a probe ray misses, it is cast again this fraction of the probe's pitch aside: a ray aimed
#: exactly at a mesh's vertex or edge can slip through the crack between its triangles (the melt
#: plate's vertices lie on the probe's grid: 3 % of its rays missed a plate that covers the field).
MISS_NUDGE = 1e-3


#: Two surfaces overlap where the beam's hit on one lies within this distance (mm) of the other's
#: plane, inside it, the planes parallel to :data:`COPLANAR_COS`: float32 hits 100 mm from the
#: origin are good to about 1e-5 mm, and nothing an electron image resolves is 1 um thick.
COPLANAR_MM = 1e-3
COPLANAR_COS = 1.0 - 1e-4
#: Point-triangle pairs per block of the overlap test.
_OVERLAP_BLOCK = 1 << 20


def _on_triangles(points, normals, tris, pi, ti):
    """For the pairs (points[pi], tris[ti]): the point lies within :data:`COPLANAR_MM` of the
    triangle's plane, its normal parallel to it, and strictly inside (an edge shared by two
    surfaces does not count)."""
    t = tris[ti]
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    n = np.cross(e1, e2)
    area2 = np.linalg.norm(n, axis=1)
    n = n / np.where(area2 > 0, area2, 1.0)[:, None]
    d = points[pi] - t[:, 0]
    ok = ((area2 > 0) & (np.abs(np.sum(d * n, 1)) <= COPLANAR_MM)
          & (np.abs(np.sum(normals[pi] * n, 1)) >= COPLANAR_COS))
    d00, d01, d11 = np.sum(e1 * e1, 1), np.sum(e1 * e2, 1), np.sum(e2 * e2, 1)
    d20, d21 = np.sum(d * e1, 1), np.sum(d * e2, 1)
    den = np.where(ok, d00 * d11 - d01 * d01, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    eps = 1e-5
    return ok & (v > eps) & (w > eps) & (1.0 - v - w > eps)


def _inside_cover(points, normals, tris):
    """Which ``points`` (k, 3) with normals (k, 3) lie in the plane of one of ``tris`` (m, 3, 3),
    parallel to it and strictly inside. Each point meets the triangles whose bounding sphere holds
    it: a k-d tree of the centres per octave of the spheres' radii, so a few large triangles do not
    widen the search for the many small ones (the melt plate's 0.12 M triangles in 0.1 s)."""
    from scipy.spatial import cKDTree

    found = np.zeros(len(points), bool)
    if len(tris) == 0:
        return found
    centre = tris.mean(axis=1)
    radius = np.max(np.linalg.norm(tris - centre[:, None], axis=2), axis=1) + COPLANAR_MM
    octave = np.floor(np.log2(radius / radius.min())).astype(np.int64)
    for o in np.unique(octave):
        members = np.flatnonzero(octave == o)
        near = cKDTree(centre[members]).query_ball_point(points, r=float(radius[members].max()))
        counts = np.fromiter((len(x) for x in near), np.int64, len(near))
        if not counts.sum():
            continue
        pi = np.repeat(np.arange(len(points)), counts)
        ti = members[np.concatenate(near).astype(np.int64)]
        for lo in range(0, len(pi), _OVERLAP_BLOCK):
            a, b = pi[lo:lo + _OVERLAP_BLOCK], ti[lo:lo + _OVERLAP_BLOCK]
            found[a[_on_triangles(points, normals, tris, a, b)]] = True
    return found


def surfaces_overlapping(surfaces, sensor, probe) -> list[dict]:
    """The pairs of ``surfaces`` that lie in one plane where the beam of ``sensor`` meets them: one
    dict per pair, ``names`` (the surface the beam met, the other; each its id and material),
    ``share`` (of the scan field: :func:`beam_probe`'s grid, its margin left out) and ``point``
    (the mean of those hits, mm). The ray tracer returns either of two surfaces at the same depth,
    point by point, so those pixels mix their materials (a floor frame moved onto the plate took
    8 % off its 1st event without a sign). Rectangles and meshes are tested with their triangles
    (:func:`~._shapes.cover_triangles`), disks with their radius; other shapes are not planar."""
    if len(surfaces) < 2 or not all(hasattr(sensor, k) for k in ("wd", "field", "field_y")):
        return []
    si = probe()
    hit = np.asarray(si.is_valid(), dtype=bool) & _in_field(sensor)
    if not hit.any():
        return []
    keys = np.asarray(dr.reinterpret_array(mi.UInt32, si.shape))
    p = np.asarray(si.p, dtype=np.float64).reshape(3, -1).T
    n = np.asarray(si.n, dtype=np.float64).reshape(3, -1).T
    inside = max(1, int(np.count_nonzero(_in_field(sensor))))
    owner = {shape_key(s): s for s in surfaces}
    found = []
    for other in surfaces:
        stype = other.shape_type()
        if stype not in (mi.ShapeType.Mesh, mi.ShapeType.Rectangle, mi.ShapeType.Disk):
            continue
        box = other.bbox()
        lo, hi = np.ravel(box.min) - COPLANAR_MM, np.ravel(box.max) + COPLANAR_MM
        near = hit & (keys != shape_key(other)) & np.all((p >= lo) & (p <= hi), axis=1)
        if not near.any():
            continue
        idx = np.flatnonzero(near)
        if stype == mi.ShapeType.Disk:  # its square cover would reach beyond the rim
            m = to_world_matrix(other)
            inv = np.linalg.inv(m)
            local = p[idx] @ inv[:3, :3].T + inv[:3, 3]
            normal = np.cross(m[:3, 0], m[:3, 1])
            normal = normal / np.linalg.norm(normal)
            dist = np.abs((p[idx] - m[:3, 3]) @ normal)
            over = ((dist <= COPLANAR_MM) & (np.abs(n[idx] @ normal) >= COPLANAR_COS)
                    & (np.sum(local[:, :2] ** 2, axis=1) < 1.0 - 1e-5))
        else:
            over = _inside_cover(p[idx], n[idx], cover_triangles(other))
        for key in np.unique(keys[idx[over]]):
            mine = idx[over][keys[idx[over]] == key]
            found.append({"names": (_describe(owner.get(key)), _describe(other)), "share": mine.size / inside,
                          "point": p[mine].mean(axis=0).round(1).tolist()})
    return found


def _describe(shape):
    """'plate' (Ti-6Al-4V), or a surface without an id (316L: Mitsuba merges the shapes that share a BSDF)."""
    material = getattr(getattr(shape.bsdf(), "material", None), "name", None) if shape is not None else None
    what = repr(shape.id()) if shape is not None and shape.id() else "a surface without an id"
    return f"{what} ({material})" if material else what


def field_missed(scene, sensor, probe) -> float:
    """The share of the scan field where the beam of ``sensor`` meets no surface at all
    (:func:`beam_probe`'s grid, its margin left out): a field wider than the scene's surfaces.
    Those pixels are 0."""
    if not all(hasattr(sensor, k) for k in ("wd", "field", "field_y")):
        return 0.0
    x, y = probe_points(sensor)
    inside = _in_field(sensor)
    missed = ~np.asarray(probe().is_valid(), dtype=bool) & inside
    if missed.any():
        pitch = float(sensor.field) / (GRID - 1)
        again = beam_probe(scene, sensor, points=(x[missed] + np.float32(MISS_NUDGE * pitch),
                                                  y[missed] + np.float32(0.7 * MISS_NUDGE * pitch)))
        missed[missed] = ~np.asarray(again.is_valid(), dtype=bool)
    return float(np.count_nonzero(missed)) / max(1, np.count_nonzero(inside))


def may_meet_beam(shape, sensor) -> bool:
    """Whether ``shape``'s bounding box meets the beam's cone (or prism) under the gun of the
    ``elo_beam`` ``sensor``: a detector that does not cannot change what the beam probe meets
    (another sensor: no beam, False)."""
    if not all(hasattr(sensor, k) for k in ("wd", "field", "field_y")):
        return False
    wd, fx, fy = float(sensor.wd), 0.5 * float(sensor.field), 0.5 * float(sensor.field_y)
    box = shape.bbox()
    low = max(float(box.min.z), 0.0)
    if low >= wd:
        return False
    shrink = 1.0 if getattr(sensor, "projection", "perspective") == "orthographic" else 1.0 - low / wd
    return (float(box.min.x) <= fx * shrink and float(box.max.x) >= -fx * shrink
            and float(box.min.y) <= fy * shrink and float(box.max.y) >= -fy * shrink)


def detectors_in_beam(detectors, sensor, probe):
    """[(name, share)] of the ``detectors`` ([(name, shape)]) that the beam of ``sensor`` meets
    before any surface, with the share of the scan field where it does (:func:`beam_probe`'s grid,
    its margin left out). There the beam ends on the detector: no electron reaches the plate."""
    if not all(hasattr(sensor, k) for k in ("wd", "field", "field_y")):  # not the elo_beam sensor: no beam
        return []
    detectors = [(name, shape) for name, shape in detectors if may_meet_beam(shape, sensor)]
    if not detectors:
        return []
    si = probe()
    inside = _in_field(sensor)
    found = []
    for name, shape in detectors:
        mask = si.is_valid() & (dr.reinterpret_array(mi.UInt32, si.shape) == shape_key(shape))
        share = float(np.count_nonzero(np.asarray(mask, dtype=bool) & inside)) / max(1, np.count_nonzero(inside))
        if share > 0:
            found.append((name, share))
    return found


def probe_points(sensor, grid=GRID):
    """The aim points (x, y) of :func:`beam_probe`, flat float32 arrays: a ``grid`` x ``grid``
    grid over the field plus a margin of 3 beam sigmas."""
    margin = 3.0 * float(np.ravel(getattr(sensor, "sigma", 0.0))[0])
    u = np.linspace(-0.5, 0.5, grid)
    x, y = np.meshgrid(u * (float(sensor.field) + 2 * margin), u * (float(sensor.field_y) + 2 * margin))
    return x.ravel().astype(np.float32), y.ravel().astype(np.float32)


def _in_field(sensor):
    """Which of :func:`probe_points`' points lie in the scan field (not in the beam's margin)."""
    x, y = probe_points(sensor)
    return (np.abs(x) <= 0.5 * float(sensor.field)) & (np.abs(y) <= 0.5 * float(sensor.field_y))


def beam_probe(scene, sensor, grid=GRID, points=None):
    """Where the beam of ``sensor`` meets the scene on a ``grid`` x ``grid`` grid over its field
    (plus a margin of 3 beam sigmas), or at the aim ``points`` (x, y) given: the surface
    interactions (a Dr.Jit array of them)."""
    x, y = probe_points(sensor, grid) if points is None else points
    wd = float(sensor.wd)
    if getattr(sensor, "projection", "perspective") == "orthographic":
        o = mi.Point3f(mi.Float(x), mi.Float(y), wd)
        d = mi.Vector3f(0.0, 0.0, -1.0)
    else:
        o = mi.Point3f(0.0, 0.0, wd)
        d = dr.normalize(mi.Vector3f(mi.Float(x), mi.Float(y), -wd))
    return scene.ray_intersect(mi.Ray3f(o, d))
