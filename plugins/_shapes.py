"""Host-side facts about a scene's shapes (set-up time): identity, planarity, covering triangles,
and where they are (:class:`GeometryKey`, the key of every cache of the set-up). numpy; the
detectors' quadrature (:mod:`._detectors`), the scene checks (:mod:`._scene_checks`), the occlusion
analysis (:mod:`._occlusion`), the relief probes (:mod:`._relief`), the far-field table and the
geometry classes all ask these questions of the same shapes.
"""

import drjit as dr
import mitsuba as mi
import numpy as np


def shape_key(shape):
    """The id by which a kernel tells ``shape`` from the others: its pointer as a UInt32 (the
    value of ``SurfaceInteraction3f.shape`` reinterpreted), stable while the scene is loaded."""
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])


def is_planar(shape):
    """True for a rectangle, a disk, or a mesh whose vertices all lie in one plane."""
    stype = shape.shape_type()
    if stype in (mi.ShapeType.Disk, mi.ShapeType.Rectangle):
        return True
    if stype != mi.ShapeType.Mesh:
        return False
    v = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
    if len(v) < 4:
        return True
    extent = max(float(np.ptp(v, axis=0).max()), 1e-30)
    a = v[0]
    b = v[np.argmax(np.sum((v - a) ** 2, axis=1))]
    n = np.cross(b - a, v - a)
    c = v[np.argmax(np.sum(n * n, axis=1))]
    normal = np.cross(b - a, c - a)
    length = np.linalg.norm(normal)
    if not length > 0:
        return True  # all vertices on one line
    return bool(np.max(np.abs((v - a) @ (normal / length))) <= 1e-7 * extent)


def to_world_matrix(shape):
    """The 4 x 4 to_world matrix of a rectangle or disk (numpy, float64)."""
    return np.array(mi.traverse(shape)["to_world"].matrix, dtype=float).reshape(-1, 4, 4)[0]


def cover_triangles(shape):
    """Triangles covering ``shape`` (a superset of its surface): a mesh's own, the square around
    a disk or rectangle, else the 12 triangles of its bounding box."""
    stype = shape.shape_type()
    if stype == mi.ShapeType.Mesh:
        v = np.array(shape.vertex_positions_buffer(), dtype=float).reshape(-1, 3)
        f = np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
        return v[f]
    if stype in (mi.ShapeType.Disk, mi.ShapeType.Rectangle):
        m = to_world_matrix(shape)
        sq = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) @ m[:3, :3].T + m[:3, 3]
        return np.array([[sq[0], sq[1], sq[2]], [sq[0], sq[2], sq[3]]])
    return box_triangles(shape)


def bbox_centre(shape):
    """The centre of ``shape``'s bounding box (mm, float64, 3)."""
    bb = shape.bbox()
    return 0.5 * (np.array(bb.min, float).ravel() + np.array(bb.max, float).ravel())


def box_triangles(shape):
    """The 12 triangles of ``shape``'s bounding box."""
    bb = shape.bbox()
    lo, hi = np.array(bb.min, float).ravel(), np.array(bb.max, float).ravel()
    c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
             (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    return c[np.array(faces)]


def digest_geometry(digest, shape, keys):
    """Feed ``shape``'s id and placement (``keys``: a :class:`GeometryKey` of its scene) to
    ``digest`` (hashlib): the geometry part of the keys of the far-field table and the geometry
    classes, compared at every render (hashing a mesh's vertices instead took 63 ms of a 1.06 s
    re-render at 256² with a height-map mesh of 2.25 M vertices)."""
    digest.update(repr((shape.id(), keys.entry(shape))).encode())


class GeometryKey:
    """A key of where the scene's shapes are, cheap enough to read at every render: per shape its
    kernel id, its bounds, and for a shape placed by a transform its ``to_world`` (read through a
    parameter handle kept per shape: bounds alone do not tell a plate tilted +10 deg from one tilted
    -10 deg), for a mesh its vertex count and the generation of its vertex buffer (counted up at
    every new buffer, which ``params.update()`` makes). The buffer last read is held: Dr.Jit reuses
    the variable index of a freed array, so a new buffer could take an old one's index, and keys
    read by index matched the placement of vertices since replaced (the corrugated sheet bent,
    tilted flat and bent again was taken for the flat one). What it cannot see: a mesh's vertices
    changed in place in their buffer (a scatter into it) without a change of the mesh's bounds.
    """

    def __init__(self):
        # shape key -> (shape, mi.traverse(shape)), whose entries read the current values; the shape
        # is held so that no other shape can take its address (the key) while the handle lives
        self._handles, self._scene = {}, None
        self._planar = {}  # a shape's entry -> is_planar (a mesh's vertices are copied to the host)
        self._entries = {}  # shape key -> entry, as of the last keying (the set-up asks several times)
        self._buffers = {}  # mesh's shape key -> (its vertex buffer as last read, held; its generation)

    def __call__(self, scene) -> tuple:
        if self._scene != id(scene):
            self._handles, self._planar, self._buffers, self._scene = {}, {}, {}, id(scene)
        self._entries = {shape_key(sh): self._read(sh) for sh in scene.shapes()}
        return (id(scene),) + tuple(self._entries.values())

    def entry(self, sh) -> tuple:
        """The key's part of one shape, as of the last keying of its scene (call the key first)."""
        k = shape_key(sh)
        return self._entries[k] if k in self._entries else self._read(sh)

    def _read(self, sh) -> tuple:
        k = shape_key(sh)
        box = sh.bbox()
        entry = (k, int(sh.shape_type()), tuple(box.min), tuple(box.max))
        if sh.is_mesh():
            buffer, held = sh.vertex_positions_buffer(), self._buffers.get(k)
            if held is None or held[0].index != buffer.index:  # the held buffer's index is not reused
                self._buffers[k] = (buffer, 0 if held is None else held[1] + 1)
            return entry + (sh.vertex_count(), sh.face_count(), self._buffers[k][1])
        if k not in self._handles:
            self._handles[k] = (sh, mi.traverse(sh))
        to_world = self._handles[k][1].get("to_world")
        return entry if to_world is None else entry + (np.array(to_world.matrix, dtype=float).tobytes(),)

    def planar(self, sh) -> bool:
        """:func:`is_planar`, once per shape and placement (a mesh of a million vertices took 0.11 s
        at every set-up)."""
        entry = self.entry(sh)
        if entry not in self._planar:
            self._planar[entry] = is_planar(sh)
        return self._planar[entry]
