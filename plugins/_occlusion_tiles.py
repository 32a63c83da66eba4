"""Occlusion analysis of the walls (set-up time): the parts of a chamber's walls, shields and other
few-faced meshes from which no shadow ray to a detector can be blocked.

Events >= 2 start where the continuation paths land: mostly on the chamber's walls, ceiling and
floor, whose shadow rays to the detectors took 42 % of a 1500^2 render of corrugated_chamber
(8 continuation paths per pixel: 4.15 -> 2.43 s without them), and whose view of a detector is
blocked only behind the radiation-protection sheet, a heat shield or another detector. The scan
regions of :mod:`._occlusion` cover the scanned surfaces; this module covers the rest:

* Candidates: every triangle of a mesh that is no detector and has at most :data:`MAX_TILE_FACES`
  faces (Mitsuba merges the chamber's rectangles into one such mesh). Each triangle is cut into
  N x N cells of its barycentric coordinates (b1, b2), N = 2^:data:`TILE_LEVELS` (cells crossing
  b1 + b2 = 1 are clipped to the triangle, those beyond it are empty).
* A block of cells is free for a detector when no blocker cuts the convex hull of the block's
  part of the triangle and the detector's cover (the test of :mod:`._occlusion`: separated by a
  plane of the hull or of the blocker's triangle). Then a segment from any point of the block to
  any point of the detector lies in that hull and meets no blocker. Its own triangle cannot block
  it (a plane meets the segment only at its start) and neither can the detector (a plane it ends
  on). Blockers: every other triangle of the candidate meshes, the covers of other shapes (a
  disk's or rectangle's square), and meshes of more than :data:`BOX_ABOVE_FACES` faces as their
  bounding box (a superset of the mesh: conservative, and 12 triangles instead of 0.12 M).
* Blocks are refined from the whole triangle down to single cells (a quadtree over the cells), all
  blocks of one level and detector at once (numpy).
* Each block is widened by :data:`TILE_MARGIN` in barycentric units inside its triangle: the
  kernel computes (b1, b2) from the hit point in float32 and may pick a neighbouring cell.

A detector whose cover has more than :data:`MAX_DETECTOR_POINTS` corners (a curved or many-faced
detector) or is not planar keeps every shadow ray.

The kernel's test (:meth:`WallTiles.free`) gathers the triangle's origin and dual basis, finds the
cell and reads one flag per detector.
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from ._occlusion import hull_planes_batch
from ._shapes import box_triangles, cover_triangles, is_planar, shape_key

#: Cells per triangle side = 2^TILE_LEVELS. corrugated_chamber's walls: 73-74 % of their cells free
#: at 2 levels (0.04 s), 77-80 % at 3 (0.07-0.09 s), 80-83 % at 4 (0.22 s); shield_chamber 33-36,
#: 39-41, 43-45 % in 0.16, 0.45, 1.7 s, measured before only overlapping pairs were tested (0.37 s
#: at 3 levels since). Where another detector, the radiation sheet or the shield hides a detector
#: the border of the free part is refined; the rest is decided at the first levels.
TILE_LEVELS = 3
#: A render pass uses the walls' cells only when it traces at least this many continuation paths
#: per detector and per square of the candidate triangles' count (:func:`worth_tiling`): the
#: analysis tests blocks of every triangle against every other, so it grows about as the square
#: (0.07 s for the chamber's 30 triangles, 0.35 s with the heat shield's 62, once per geometry and
#: detectors), and it pays back per path. Measured warm, interleaved (benchmarks/RESULTS.md, Far
#: field, "The walls' shadow rays"): 1500^2 `default` (1.2 M paths a pass) melt_chamber 0.92x the
#: time, athene_flat 0.98x; 256^2 `default` (2.6 M) athene_flat 0.94x, melt_chamber 0.83x,
#: shield_chamber 0.98x (0.02 s saved against 0.35 s of analysis at every detector move of a
#: sweep: off). Thresholds: 0.92 M paths for the chamber, 3.9 M with the shield.
PATHS_PER_TILED_FACE_SQUARED = 256
#: Meshes with more faces are not tiled (their shadow rays are cast): the scanned relief is the
#: scan regions' business (:mod:`._occlusion`), and the analysis grows with the faces.
MAX_TILE_FACES = 128
#: Blockers of more faces enter the test as their bounding box (12 triangles).
BOX_ABOVE_FACES = 256
#: Most distinct corners of a detector's cover the test takes (a disk's square has 4).
MAX_DETECTOR_POINTS = 8
#: Cells are widened by this much (barycentric units) for the float32 rounding of the kernel's
#: (b1, b2): about 1e-6 for a 700 mm wall.
TILE_MARGIN = 1e-5
#: Blocks whose hulls are built at a time; their (hull, blocker) pairs are tested 8 x BATCH at a time
#: (scratch of a few MB).
BATCH = 512

def separated_batch(points, tris, own=None):
    """(B,) True where no triangle of ``tris`` (O, 3, 3) can cut the convex hull of ``points``
    (B, P, 3); ``own`` (B,) the index of a triangle that does not count (-1: none). The test of
    :func:`._occlusion._all_separated`, for many hulls at once."""
    planes, valid = hull_planes_batch(points)
    # the facet planes first, the rest of the triples dropped (a hull of 9 points has ~14 facets
    # among its 84 triples)
    order = np.argsort(~valid, axis=1, kind="stable")[:, :max(1, int(valid.sum(axis=1).max()))]
    planes = np.take_along_axis(planes, order[..., None], axis=1)
    valid = np.take_along_axis(valid, order, axis=1)
    tol = 1e-6 * np.maximum(1.0, np.ptp(points, axis=1).max(axis=1))  # (B,)
    lo, hi = points.min(axis=1) - tol[:, None], points.max(axis=1) + tol[:, None]
    near = np.all(tris.max(axis=1)[None] >= lo[:, None], axis=2) & np.all(tris.min(axis=1)[None] <= hi[:, None], axis=2)
    if own is not None:
        near[np.arange(len(points))[own >= 0], own[own >= 0]] = False
    # only the (hull, blocker) pairs whose bounding boxes meet (a quarter of them on shield_chamber)
    pb, po = np.nonzero(near)
    if len(pb) == 0:
        return np.ones(len(points), bool)
    tn = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    tlen = np.linalg.norm(tn, axis=1)
    tok = tlen > 0
    tn = tn / np.where(tok, tlen, 1.0)[:, None]
    toff = np.einsum("ok,ok->o", tn, tris[:, 0])
    sep = np.empty(len(pb), bool)
    for s in range(0, len(pb), 8 * BATCH):
        b, o = pb[s:s + 8 * BATCH], po[s:s + 8 * BATCH]
        pl, t = planes[b], tol[b][:, None, None]
        d = np.einsum("pvk,pfk->pvf", tris[o], pl[..., :3]) + pl[:, None, :, 3]  # (pairs, 3, planes)
        ok = np.any(valid[b] & np.all(d > t, axis=1), axis=1)
        side = np.einsum("pqk,pk->pq", points[b], tn[o]) - toff[o][:, None]  # (pairs, points)
        t = t[:, :, 0]
        ok |= tok[o] & (np.all(side >= -t, axis=1) | np.all(side <= t, axis=1))
        sep[s:s + 8 * BATCH] = ok
    return np.bincount(pb[~sep], minlength=len(points)) == 0


def _block_polygons(tris, i0, j0, size, n, margin):
    """World corners (B, 5, 3) of the blocks [i0, i0 + size) x [j0, j0 + size) of cells of
    triangles ``tris`` (B, 3, 3) in barycentric coordinates, widened by ``margin`` and clipped to
    the triangle (b1, b2 >= 0, b1 + b2 <= 1): a pentagon, repeated corners where it has fewer."""
    u0 = np.maximum(i0 / n - margin, 0.0)
    v0 = np.maximum(j0 / n - margin, 0.0)
    u1 = np.minimum((i0 + size) / n + margin, 1.0)
    v1 = np.minimum((j0 + size) / n + margin, 1.0)
    # the square's corners, those beyond the diagonal moved onto it along the square's edges
    corners = [(u0, v0), (np.minimum(u1, 1.0 - v0), v0),
               (np.minimum(u1, 1.0 - v0), np.maximum(v0, np.minimum(v1, 1.0 - u1))),
               (np.maximum(u0, np.minimum(u1, 1.0 - v1)), np.minimum(v1, 1.0 - u0)),
               (u0, np.minimum(v1, 1.0 - u0))]
    uv = np.stack([np.stack(c, axis=1) for c in corners], axis=1)  # (B, 5, 2)
    uv = np.maximum(uv, 0.0)
    p0 = tris[:, None, 0]
    return p0 + uv[..., :1] * (tris[:, None, 1] - p0) + uv[..., 1:] * (tris[:, None, 2] - p0)


def free_cells(tris, blockers, tri_blocker_index, det_points, levels=TILE_LEVELS, margin=TILE_MARGIN):
    """(T, N, N) bool: the cells of triangles ``tris`` (T, 3, 3) from which nothing of
    ``blockers`` (O, 3, 3) can block a segment to the convex set spanned by ``det_points`` (Q, 3);
    ``tri_blocker_index`` (T,) the index of each triangle among the blockers (-1: not there)."""
    n = 1 << levels
    free = np.zeros((len(tris), n, n), bool)
    # blocks still undecided: (triangle, i0, j0) at the current size
    t = np.arange(len(tris))
    i0 = np.zeros(len(tris), int)
    j0 = np.zeros(len(tris), int)
    size = n
    while len(t):
        ok = np.zeros(len(t), bool)
        for s in range(0, len(t), BATCH):
            sl = slice(s, s + BATCH)
            poly = _block_polygons(tris[t[sl]], i0[sl], j0[sl], size, n, margin)
            pts = np.concatenate([poly, np.broadcast_to(det_points, (len(poly),) + det_points.shape)], axis=1)
            ok[sl] = separated_batch(pts, blockers, tri_blocker_index[t[sl]])
        for a, b, c in zip(t[ok], i0[ok], j0[ok]):
            free[a, b:b + size, c:c + size] = True
        if size == 1:
            break
        half = size // 2
        t, i0, j0 = t[~ok], i0[~ok], j0[~ok]
        t = np.repeat(t, 4)
        i0 = np.repeat(i0, 4) + np.tile([0, half, 0, half], len(i0))
        j0 = np.repeat(j0, 4) + np.tile([0, 0, half, half], len(j0))
        inside = i0 + j0 < n  # the block's lower-left cell lies in the triangle
        t, i0, j0, size = t[inside], i0[inside], j0[inside], half
    # cells beyond the diagonal hold no point of the triangle
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    free &= (i + j < n)[None]
    return free


def candidates(scene, detectors):
    """The meshes whose triangles are tiled: no detector, 1 to :data:`MAX_TILE_FACES` faces."""
    det_keys = {shape_key(det) for _, det in detectors}
    return [sh for sh in scene.shapes() if sh.is_mesh() and shape_key(sh) not in det_keys
            and 0 < sh.face_count() <= MAX_TILE_FACES]


def worth_tiling(scene, detectors, paths):
    """Whether a pass of ``paths`` continuation paths pays for the analysis of the walls
    (:data:`PATHS_PER_TILED_FACE_SQUARED` per detector and square of the candidate triangles)."""
    faces = sum(sh.face_count() for sh in candidates(scene, detectors))
    return faces > 0 and paths >= PATHS_PER_TILED_FACE_SQUARED * faces**2 * len(detectors)


class WallTiles:
    """The free cells of the candidate meshes per detector, as kernel arrays (:meth:`free`)."""

    def __init__(self, scene, detectors, levels=TILE_LEVELS):
        self.levels = levels
        n = 1 << levels
        shapes = {shape_key(sh): sh for sh in scene.shapes()}
        tiled_meshes = candidates(scene, detectors)
        tiled = {shape_key(sh) for sh in tiled_meshes}
        self.meshes, tris, base = [], [], 0
        for sh in tiled_meshes:
            self.meshes.append((dr.opaque(mi.UInt32, shape_key(sh)), dr.opaque(mi.UInt32, base)))
            tris.append(cover_triangles(sh))
            base += sh.face_count()
        self.tris = np.concatenate(tris) if tris else np.zeros((0, 3, 3))
        self.cells = []  # per detector: (T, N, N) bool, or None
        if not len(self.tris):
            self.flags = [None for _ in detectors]
            return
        others = {shape_key(sh): (cover_triangles(sh) if not (sh.is_mesh() and sh.face_count() > BOX_ABOVE_FACES)
                                  else box_triangles(sh))
                  for k, sh in shapes.items() if k not in tiled}
        area = np.linalg.norm(np.cross(self.tris[:, 1] - self.tris[:, 0], self.tris[:, 2] - self.tris[:, 0]), axis=1)
        usable = area > 1e-12 * max(1.0, float(np.ptp(self.tris.reshape(-1, 3), axis=0).max())) ** 2
        self.flags = []
        for _, det in detectors:
            dk = shape_key(det)
            det_points = np.unique(others[dk].reshape(-1, 3), axis=0)
            if not is_planar(det) or len(det_points) > MAX_DETECTOR_POINTS:
                self.cells.append(None)
                self.flags.append(None)
                continue
            # a triangle of no area blocks nothing (the tracer never hits it); as a blocker its
            # corners on a tile's edge would refuse the cells along it
            blockers = np.concatenate([self.tris[usable]] + [tri for k, tri in others.items() if k != dk])
            index = np.arange(int(np.count_nonzero(usable)))
            cells = free_cells(self.tris[usable], blockers, index, det_points, levels)
            full = np.zeros((len(self.tris), n, n), bool)
            full[usable] = cells
            self.cells.append(full)
            self.flags.append(mi.UInt32(full.reshape(-1).astype(np.uint32)) if full.any() else None)
        # the dual basis of each triangle: b1 = (p - p0) . g1, b2 = (p - p0) . g2 in its plane
        p0 = self.tris[:, 0]
        e = np.stack([self.tris[:, 1] - p0, self.tris[:, 2] - p0], axis=1)  # (T, 2, 3)
        gram = np.einsum("tik,tjk->tij", e, e)
        det_g = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] ** 2
        inv = np.stack([np.stack([gram[:, 1, 1], -gram[:, 0, 1]], 1), np.stack([-gram[:, 1, 0], gram[:, 0, 0]], 1)], 1)
        inv = inv / np.where(usable, det_g, 1.0)[:, None, None]
        g = np.einsum("tij,tjk->tik", inv, e)  # (T, 2, 3)

        def f32(a):
            return mi.Float(np.ascontiguousarray(a, np.float32).reshape(-1))

        self._p0, self._g1, self._g2 = f32(p0), f32(g[:, 0]), f32(g[:, 1])

    def any_free(self):
        return any(f is not None for f in self.flags)

    def cell_index(self, si):
        """(lanes on a candidate mesh, their cell's index into a detector's flags)."""
        key = dr.reinterpret_array(mi.UInt32, si.shape)
        on, tri = mi.Bool(False), mi.UInt32(0)
        for mesh_key, base in self.meshes:
            hit = key == mesh_key
            on |= hit
            tri = dr.select(hit, base + si.prim_index, tri)
        three = tri * 3
        p0 = mi.Point3f(*(dr.gather(mi.Float, self._p0, three + c, on) for c in range(3)))
        g1 = mi.Vector3f(*(dr.gather(mi.Float, self._g1, three + c, on) for c in range(3)))
        g2 = mi.Vector3f(*(dr.gather(mi.Float, self._g2, three + c, on) for c in range(3)))
        dp = si.p - p0
        n = 1 << self.levels
        i = dr.clip(mi.Int32(dr.floor(dr.dot(dp, g1) * n)), 0, n - 1)
        j = dr.clip(mi.Int32(dr.floor(dr.dot(dp, g2) * n)), 0, n - 1)
        return on, (tri * n + mi.UInt32(i)) * n + mi.UInt32(j)

    def free(self, si, d, index=None):
        """Lanes at a point of a free cell for detector ``d``, or None where none is free. The cell
        lookup repeats for every detector and shadow ray; Dr.Jit's value numbering merges the
        copies (corrugated_chamber's kernel: 16 413 operations with one lookup or two)."""
        flags = self.flags[d]
        if flags is None:
            return None
        on, cell = self.cell_index(si) if index is None else index
        return on & (dr.gather(mi.UInt32, flags, cell, on) != 0)
