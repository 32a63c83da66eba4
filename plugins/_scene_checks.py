"""What a scene must be for the ``elo`` integrator, checked on the host before any kernel is built:
detectors that count electrons, surfaces that scatter by g_BSE or absorb, meshes with triangles
that name their vertices, detector discs clear of every surface; and the notes on what renders but
may not be what the user meant (a mesh smoothed by its vertex normals). Each mesh is checked once
and each geometry's discs once (:class:`SceneChecks` keeps the caches); a render's set-up runs
:meth:`SceneChecks.refuse` every time, so that moved detectors are checked too.
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from elo_mitsuba.errors import EloInputError

from ._detectors import surfaces_through_detectors
from .bsdf_elo_bse import is_elo_bse


#: Shape types that are not an instance (Mitsuba's Python API has no type for it).
_PLAIN = (mi.ShapeType.Mesh, mi.ShapeType.Rectangle, mi.ShapeType.Disk, mi.ShapeType.Sphere, mi.ShapeType.Cylinder)


class SceneChecks:
    """The checks of one integrator, with what they cache between renders."""

    def __init__(self):
        self._smoothed = {}  # the checked shapes (their GeometryKey entries) -> whether normals smooth them
        self._cut, self._cut_key = [], None  # surfaces_through_detectors of the last geometry, and its key
        self._triangles = {}  # the scene's triangles for surfaces_through_detectors, by shape

    def refuse(self, scene, detectors, keys, geometry) -> list[str]:
        """Raise :class:`EloInputError` on what no render may use; return the notes on the meshes.
        ``keys`` (:class:`~._shapes.GeometryKey`) and ``geometry`` (its key of ``scene``): where the
        shapes are, the keys of what is checked once (a mesh given new vertices is checked again)."""
        for emitter in scene.emitters():
            check_emitter(emitter)
        for name, shape in detectors:
            check_collector(name, shape)
            # a plate backscatters by g_BSE (copper) or keeps what arrives, nothing else; Mitsuba's
            # default for an emitter without a BSDF is a diffuse one of reflectance 0, an absorber
            check_scatterer(shape, detector=True)
        scatterers = [s for s in scene.shapes() if not s.is_emitter()]
        for shape in scatterers:
            if shape.shape_type() not in _PLAIN and str(shape).startswith("Instance["):  # its group is out of reach
                raise EloInputError(
                    f"surface {shape.id() or '(no id)'!r} is an instance of a shapegroup, whose shapes the renderer "
                    "cannot check or tabulate (their BSDFs, their triangles, where they cut a detector); write each "
                    "shape of the group out as a <shape> of its own")
            check_scatterer(shape)
            if keys.entry(shape) not in self._smoothed:  # once per placement (area, indices: device reductions)
                check_mesh(shape)
        # segments along the discs against the (checked) meshes, once per geometry
        if self._cut_key != geometry:
            self._cut, self._cut_key = surfaces_through_detectors(scene, detectors, cache=self._triangles), geometry
        for name, through in self._cut[:1]:
            raise EloInputError(f"detector {name!r} is cut by {through}: it passes through the disc (a detector "
                                "moved through a wall or a shield?); move it clear of the scene's surfaces")
        notes = []
        for shape in scatterers:
            key = keys.entry(shape)
            if key not in self._smoothed:  # once per placement: a mesh's buffers are copied to the host
                self._smoothed[key] = smoothed(shape)
            if self._smoothed[key]:
                notes.append(
                    f"mesh {shape.id() or '(no id)'!r} has vertex normals: g_BSE sees them interpolated across its "
                    "triangles, a surface smoothed over its edges (a sharp relief loses its slopes); for facets add "
                    "<boolean name=\"face_normals\" value=\"true\"/> to its <shape>")
        return notes


def check_emitter(emitter):
    """An emitter marks a detector only on a shape (an area emitter); any other (point, constant,
    directional, ...) would be a setting that is not applied: the beam is the only source of
    electrons and nothing else collects them."""
    if emitter.get_shape() is None:
        kind = str(emitter).split("[", 1)[0].strip() or type(emitter).__name__
        raise EloInputError(f"emitter {emitter.id() or '(no id)'!r} ({kind}) is not on a shape, and the renderer does not use it: "
                            "the beam is the only source of electrons, and a detector is a shape marked with "
                            "<emitter type=\"area\"/>; remove it")


def check_collector(name, shape):
    """A detector counts the electrons that reach it (N_d/N_0): the radiance of the area emitter
    that marks it is not read, so a radiance other than 1 would be a setting that is not applied."""
    radiance = mi.traverse(shape.emitter()).get("radiance.value")
    value = float(np.ravel(np.array(radiance, dtype=float))[0]) if radiance is not None else 1.0
    if value != 1.0:
        raise EloInputError(f"detector {name!r} has an emitter radiance of {value:g}, which the renderer does not use "
                            "(a detector counts electrons: N_d/N_0); remove it, or scale the images (--units "
                            "voltage for volts)")


def check_scatterer(shape, detector: bool = False):
    """A surface electrons meet must carry ``elo_bse`` (g_BSE), or absorb them (a BSDF of zero
    reflectance): any other BSDF would scatter by a law that is not the electrons'. On a
    ``detector`` it would be a setting that is not applied (a detector's plate keeps what arrives,
    or backscatters by its own ``elo_bse``; a diffuse reflectance of 0.5 was ignored)."""
    bsdf = shape.bsdf()
    if bsdf is None or is_elo_bse(bsdf):
        return
    values = [np.abs(np.array(v, dtype=float)).max() for k, v in mi.traverse(bsdf).items()
              if "reflectance" in k or "specular" in k]
    if values and max(values) == 0.0:
        return  # an absorber: electrons that arrive end there
    kind = str(bsdf).split("[")[0].strip() or "another BSDF"
    if detector:
        raise EloInputError(
            f"detector {shape.id()!r} has a {kind} BSDF that reflects, which the renderer does not apply: a "
            "detector keeps every electron that reaches it (the paper's model); give it no BSDF or "
            "<bsdf type=\"diffuse\"><float name=\"reflectance\" value=\"0\"/></bsdf>, or <bsdf type=\"elo_bse\"> "
            "for a plate that backscatters (-D plates=copper)")
    raise EloInputError(
        f"surface {shape.id() or '(no id)'!r} has a {kind} BSDF, which does not describe electron "
        "backscatter; give it <bsdf type=\"elo_bse\"> (with its material), or make it an absorber: "
        "<bsdf type=\"diffuse\"><float name=\"reflectance\" value=\"0\"/></bsdf>")


def smoothed(shape, degrees: float = 1.0) -> bool:
    """Whether a mesh's vertex normals depart from its triangles' own by more than ``degrees``
    somewhere (a flat shape turned into a mesh has them too, all equal to its face normal).
    Checked in blocks of triangles, stopping at the first that departs: a smooth mesh of millions
    of triangles answers at once."""
    if not (shape.is_mesh() and shape.has_vertex_normals()):
        return False
    v = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
    vn = np.array(shape.vertex_normals_buffer(), dtype=np.float64).reshape(-1, 3)
    faces = np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
    limit = np.cos(np.radians(degrees))
    for at in range(0, len(faces), _BLOCK):
        f = faces[at:at + _BLOCK]
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        cosines = np.einsum("fk,fjk->fj", fn, vn[f]) / np.maximum(np.linalg.norm(vn[f], axis=2), 1e-300)
        if np.any(cosines < limit):
            return True
    return False


#: Triangles per block of :func:`smoothed`.
_BLOCK = 1 << 16


def check_mesh(shape):
    """A mesh an electron can meet has triangles whose indices name its vertices (an empty PLY, or
    one whose faces point past its vertex list, failed deep in the set-up with an IndexError)."""
    name = shape.id() or "(no id)"
    if shape.is_mesh():  # the indices first: the area of a triangle naming a missing vertex reads past the
        # vertex buffer (its value, and so the message, changed from run to run)
        if shape.vertex_count() == 0 or shape.face_count() == 0:
            raise EloInputError(f"mesh {name!r} has {shape.vertex_count()} vertices and {shape.face_count()} "
                                "triangles; a surface needs triangles")
        top = int(dr.max(shape.faces_buffer())[0] if dr.width(shape.faces_buffer()) else 0)
        if top >= shape.vertex_count():
            raise EloInputError(f"mesh {name!r}: a triangle names vertex {top}, but the mesh has "
                                f"{shape.vertex_count()} (indices 0 to n-1): the file is damaged")
    area = float(np.ravel(np.array(shape.surface_area(), dtype=float))[0])
    if not (area > 0 and np.isfinite(area)):  # a scale of 0 (or beyond float32): no surface to meet
        raise EloInputError(f"surface {name!r} has an area of {area:g} mm^2 (a scale of 0, or beyond float32?)")
