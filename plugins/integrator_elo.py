"""Integrator ``elo``: electrons traced forward from the gun to every detector (Sec. 2.1.1).

The gun is the sensor (``elo_beam``), so a film pixel is a scan point; surfaces carry the
``elo_bse`` BSDF whose ``eval`` is g_BSE (cosine included, ``wi`` towards where the electron came
from); detectors are the shapes carrying an area emitter (unit radiance). Scattering event n is
path vertex n. At every event the integrator estimates, separately for each detector and with
occlusion, the electrons that reach it directly,

    N_{n,d} / N_0 = throughput * int_{Omega_d} g_BSE dOmega          (Eq. 5, and Eq. 8 for n > 1),

and then continues the path by sampling g_BSE (Eq. 7): the sample weight carries the electrons
that leave in that direction. A continuation ray that hits a detector ends there (the electrons
are absorbed, Eq. 6; they were counted by the direct estimate, so nothing is counted twice); one
that leaves the scene is lost. No bounce ray is traced after the last counted event.

Detector integral of the 1st event (``detector_sampling``):

* ``independent`` (default): ``detector_samples`` uniform points on each detector (Mitsuba's
  area-emitter sampling), each with its own shadow ray;
* ``stratified``: the same number of points, one in each stratum of the unit square (rows x
  columns, unequal strata weighted by their area) mapped onto the detector: unbiased, far less
  noise for the smooth 1st-event integrand;
* ``quadrature``: Appendix A, Eq. A2: the detector as ``quadrature_triangles`` triangles (a disk
  as an equal-area fan/rings, a rectangle as a grid, a mesh detector as its own triangles), each
  weighted by its solid angle from the Van Oosterom-Strackee formula (Eq. A1 with the corrected
  denominator, ERRATA.md item 2) and g_BSE at its centroid. Occlusion: ``quadrature_visibility=
  "sampled"`` (default) casts ONE shadow ray per detector, to a point drawn in a triangle chosen
  with probability proportional to its weight: exact (no noise) wherever the detector is fully
  visible or fully hidden, unbiased in between; ``"triangle"`` casts one ray per triangle
  centroid (deterministic). Its error is deterministic (measured: < 5e-4 with 4 triangles,
  < 4e-4 with 8, < 2e-4 with 24 on the 50 mm discs); with ``fwhm = 0`` one sample per pixel
  gives the converged 1st event.

Events >= 2 sample ``bounce_detector_samples`` points per detector (independent, or stratified
when ``detector_sampling`` is stratified or quadrature). Their budget is set apart from the 1st
event's, without bias: ``bounce_fraction`` f traces the continuation for a fraction f of the
samples (whole blocks of 32 neighbouring lanes, chosen by a randomly shifted golden-ratio
sequence, weight 1/f; skipped blocks really skip the work), ``bounce_samples`` k traces k
continuation paths per sample (splitting, weight 1/k). They can be estimated in space by
``bounce_filter`` (mm): the event >= 2 channels are averaged over a window of about that
half-width, shrunk (halved, three scales at most) wherever the 1st-event surface normals in the
window differ by more than ``bounce_filter_angle`` (deg) or the beam missed, so that flanks,
edges and object borders are not mixed; totals are recomputed. This is biased by the variation
of the events >= 2 inside the window: use it where they vary slowly (walls far away), after
checking the error against a reference (benchmarks/). ``bounce_min`` (paths per pixel) then
tops up, in a second pass of continuation paths only, the pixels left with fewer paths than
that (e.g. at edges where the window had to shrink); both estimates are averaged by path count.

Model only what the scene requires. Scenes whose only scattering surface is one plane
(``rectangle``, ``disk`` or a planar mesh) cannot scatter an electron twice: events >= 2 are
then exactly zero, no bounce ray is traced and ``notes`` says so. Before each render an
occlusion analysis finds, per detector, the scan region on a horizontal planar surface from
which nothing in the scene can block the detector (no triangle of any other shape, or of the
bounding box of a non-mesh shape, can cut the convex hull of that region and the detector):
shadow rays from there are not cast (flat plate, also inside the chamber); any other surface
point casts them as usual.

Outputs (one pass): for each detector ``<id>`` the total over the counted events and, when
``events > 1``, each event alone as ``<id>.e<k>``. Values are N_d/N_0, or detector voltages
U_d = (N_d/N_0) I_b T (Eq. 9 with Eq. 3) with ``units="voltage"``.

XML parameters: ``events`` (int >= 1, default 1; Mitsuba's max_depth = events + 1),
``detector_sampling`` (independent | stratified | quadrature), ``detector_samples`` (int >= 1,
default 1), ``quadrature_triangles`` (int >= 4, default 8), ``quadrature_visibility`` (sampled |
triangle), ``bounce_detector_samples`` (default = detector_samples), ``bounce_samples`` (k >= 1,
default 1), ``bounce_fraction`` (0 < f <= 1, default 1), ``bounce_filter`` (mm >= 0, default 0 =
off), ``bounce_filter_angle`` (deg, default 1), ``bounce_min`` (paths per pixel, default 0 = off),
``units`` ("fraction" or "voltage"), ``beam_current`` (A, default 3e-3), ``transimpedance`` (V/A,
default 1e5). Attributes with the same names can be changed between renders (same kernel where
only values change); ``occlusion_analysis = False`` casts every shadow ray; ``count_rays = True``
stores the rays cast per sample in ``ray_counts`` (benchmarks).

Performance (benchmarks/RESULTS.md): shadow rays dominate; g_BSE is evaluated inline from
per-BSDF tables (no virtual call per direction) when every scattering surface has ``elo_bse``;
the loop over events is unrolled in Python (faster than ``dr.while_loop``); everything runs in
Mitsuba's default single-kernel (symbolic) mode, so memory does not grow with spp.
"""

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from elo_mitsuba.constants import BEAM_CURRENT_A, DETECTOR_NAMES, TRANSIMPEDANCE_V_PER_A
from elo_mitsuba.errors import EloInputError

UNITS = ("fraction", "voltage")
STRATEGIES = ("independent", "stratified", "quadrature")
VISIBILITY = ("sampled", "triangle")
#: Most triangles of one detector in the quadrature (the loop over them is unrolled).
MAX_QUADRATURE_TRIANGLES = 256
#: Hidden film channels: the 1st-event surface normal that guides ``bounce_filter``.
_GUIDE = ("_elo_nx", "_elo_ny", "_elo_nz")
#: Hidden film channels counting the rays cast per sample (``count_rays = True``, benchmarks).
_COUNTS = ("_elo_intersections", "_elo_shadow_rays")
#: bounce_fraction < 1 selects blocks of 2**_BLOCK_SHIFT consecutive lanes (neighbouring pixels)
_BLOCK_SHIFT = 5
_GOLDEN = 0.6180339887498949


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
            found[name] = shape
    order = [n for n in DETECTOR_NAMES if n in found] + sorted(n for n in found if n not in DETECTOR_NAMES)
    return [(n, found[n]) for n in order]


# ---- geometry helpers (numpy, set-up time only) ------------------------------------------------------
def solid_angle_triangle(p, v1, v2, v3):
    """Van Oosterom-Strackee solid angle (Eq. A1, corrected denominator) of triangles seen from p.

    Positive when p lies on the side opposite to the normal (v2 - v1) x (v3 - v1) (the vertices
    turn clockwise as seen from p), negative on the normal's side. numpy, for set-up and tests;
    the kernel evaluates the same formula (:meth:`EloIntegrator._quadrature`).
    """
    a, b, c = (np.asarray(v, float) - np.asarray(p, float) for v in (v1, v2, v3))
    la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
    num = np.sum(a * np.cross(b, c), axis=-1)
    den = (la * lb * lc + np.sum(a * b, axis=-1) * lc + np.sum(a * c, axis=-1) * lb
           + np.sum(b * c, axis=-1) * la)
    return 2.0 * np.arctan2(num, den)


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
        f"detector {name!r}: detector_sampling=quadrature supports disk, rectangle and mesh "
        "detectors; use stratified for this shape")


def _is_planar(shape):
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


# ---- occlusion analysis (set-up time): which shadow rays cannot hit anything ---------------------------
def _to_world(shape):
    return np.array(mi.traverse(shape)["to_world"].matrix, dtype=float).reshape(-1, 4, 4)[0]


def _cover_triangles(shape):
    """Triangles covering ``shape`` (a superset of its surface): a mesh's own, the square around
    a disk or rectangle, else the 12 triangles of its bounding box."""
    stype = shape.shape_type()
    if stype == mi.ShapeType.Mesh:
        v = np.array(shape.vertex_positions_buffer(), dtype=float).reshape(-1, 3)
        f = np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
        return v[f]
    if stype in (mi.ShapeType.Disk, mi.ShapeType.Rectangle):
        m = _to_world(shape)
        sq = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) @ m[:3, :3].T + m[:3, 3]
        return np.array([[sq[0], sq[1], sq[2]], [sq[0], sq[2], sq[3]]])
    bb = shape.bbox()
    lo, hi = np.array(bb.min, float).ravel(), np.array(bb.max, float).ravel()
    c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
             (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    return c[np.array(faces)]


def _all_separated(points, tris, tol):
    """True if no triangle of ``tris`` (T, 3, 3) can intersect the convex hull of ``points``
    (conservative: separating planes are the hull's faces and the triangles' own planes)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(points)
    except (QhullError, ValueError):
        return False
    eq = hull.equations  # n . x + c <= 0 inside
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
    if not _is_planar(shape) or not all(hasattr(sensor, a) for a in ("wd", "field", "field_y")):
        return None
    tris = _cover_triangles(shape)
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


def _shape_key(shape):
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])


def unoccluded_regions(scene, sensor, detectors):
    """Per detector: [(shape, (z0, xmin, xmax, ymin, ymax))] of scan regions on horizontal planar
    surfaces from which nothing in the scene can block the view of the detector, so that
    shadow rays from there are not needed (e.g. the flat plate, also inside the chamber)."""
    shapes = {_shape_key(sh): sh for sh in scene.shapes()}
    regions = [(k, sh, _beam_region(sh, sensor)) for k, sh in shapes.items() if not sh.is_emitter()]
    regions = [(k, sh, r) for k, sh, r in regions if r is not None]
    covers = {k: _cover_triangles(sh) for k, sh in shapes.items()} if regions else {}
    out = []
    for _, det in detectors:
        free = []
        dk = _shape_key(det)
        for k, sh, (z0, x0, x1, y0, y1) in regions:
            pts = np.vstack([[[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0]], covers[dk].reshape(-1, 3)])
            tol = 1e-6 * max(1.0, float(np.ptp(pts, axis=0).max()))
            others = [covers[o] for o in shapes if o not in (k, dk)]
            tris = np.concatenate(others) if others else np.zeros((0, 3, 3))
            if _all_separated(pts, tris, tol):
                free.append((sh, (z0, x0, x1, y0, y1)))
        out.append(free)
    return out

def _interpolation(n_fine, n_coarse, tile):
    """(index of the window at or before each pixel, (n_fine, n_coarse) matrix of the linear
    interpolation from window centres (tile centres) to pixel centres, clamped at the edges)."""
    c = (np.arange(n_fine) + 0.5) / tile - 0.5
    i0 = np.clip(np.floor(c).astype(np.int64), 0, n_coarse - 1)
    i1 = np.minimum(i0 + 1, n_coarse - 1)
    f = np.clip(c - i0, 0.0, 1.0)
    a = np.zeros((n_fine, n_coarse), np.float32)
    rows = np.arange(n_fine)
    np.add.at(a, (rows, i0), 1.0 - f)
    np.add.at(a, (rows, i1), f)
    return i0, a


def _eval_directions(bsdf, ctx, si, wos, active):
    """g_BSE for several local directions in ONE dispatch; identical work (angle of incidence,
    table lookup) is shared by Dr.Jit's common-subexpression elimination."""
    return [bsdf.eval(ctx, si, wo, active)[0] for wo in wos]


class EloIntegrator(mi.SamplingIntegrator):
    def __init__(self, props):
        mi.SamplingIntegrator.__init__(self, props)
        self.events = int(props.get("events", 1))
        if self.events < 1:
            raise EloInputError(f"elo: events={self.events}; must be >= 1 (1 = first event only)")
        self.detector_sampling = str(props.get("detector_sampling", "independent"))
        if self.detector_sampling not in STRATEGIES:
            raise EloInputError(f"elo: detector_sampling={self.detector_sampling!r}; allowed: {', '.join(STRATEGIES)}")
        self.detector_samples = int(props.get("detector_samples", 1))
        if self.detector_samples < 1:
            raise EloInputError(f"elo: detector_samples={self.detector_samples}; must be >= 1")
        self.bounce_detector_samples = int(props.get("bounce_detector_samples", self.detector_samples))
        if self.bounce_detector_samples < 1:
            raise EloInputError(f"elo: bounce_detector_samples={self.bounce_detector_samples}; must be >= 1")
        self.quadrature_triangles = int(props.get("quadrature_triangles", 8))
        if not 4 <= self.quadrature_triangles <= MAX_QUADRATURE_TRIANGLES:
            raise EloInputError(f"elo: quadrature_triangles={self.quadrature_triangles}; must be in "
                                f"[4, {MAX_QUADRATURE_TRIANGLES}]")
        self.quadrature_visibility = str(props.get("quadrature_visibility", "sampled"))
        if self.quadrature_visibility not in VISIBILITY:
            raise EloInputError(f"elo: quadrature_visibility={self.quadrature_visibility!r}; allowed: {', '.join(VISIBILITY)}")
        self.bounce_samples = int(props.get("bounce_samples", 1))
        if self.bounce_samples < 1:
            raise EloInputError(f"elo: bounce_samples={self.bounce_samples}; must be >= 1")
        self.bounce_fraction = float(props.get("bounce_fraction", 1.0))
        if not (0.0 < self.bounce_fraction <= 1.0):
            raise EloInputError(f"elo: bounce_fraction={self.bounce_fraction!r}; must be in (0, 1]")
        self.bounce_min = float(props.get("bounce_min", 0.0))
        if not (math.isfinite(self.bounce_min) and 0.0 <= self.bounce_min <= 4096):
            raise EloInputError(f"elo: bounce_min={self.bounce_min!r}; must be in [0, 4096] (0 = off)")
        self.bounce_filter = float(props.get("bounce_filter", 0.0))
        if not (math.isfinite(self.bounce_filter) and self.bounce_filter >= 0):
            raise EloInputError(f"elo: bounce_filter={self.bounce_filter!r} mm; must be >= 0 (0 = off)")
        self.bounce_filter_angle = float(props.get("bounce_filter_angle", 1.0))
        if not (0.0 < self.bounce_filter_angle < 90.0):
            raise EloInputError(f"elo: bounce_filter_angle={self.bounce_filter_angle!r} deg; must be in (0, 90)")
        self.units = str(props.get("units", "fraction"))
        if self.units not in UNITS:
            raise EloInputError(f"elo: units={self.units!r}; allowed: {', '.join(UNITS)}")
        self.beam_current = float(props.get("beam_current", BEAM_CURRENT_A))
        self.transimpedance = float(props.get("transimpedance", TRANSIMPEDANCE_V_PER_A))
        for name, value in (("beam_current", self.beam_current), ("transimpedance", self.transimpedance)):
            if not (value > 0 and math.isfinite(value)):
                raise EloInputError(f"elo: {name}={value!r}; must be > 0")
        self.detectors = []  # [(id, shape)], resolved from the scene at render time
        self.bounce_possible = True  # False: the scene cannot scatter an electron twice
        self.notes = []  # what the integrator decided to skip, and why
        self._quad = []  # per detector: (vertices [opaque Point3f], [((i, j, k), opaque 2 A n)])
        self._tables = None  # inline g_BSE: per-BSDF material tables (None: use dispatch)
        self._free = []  # per detector: [(shape id, bounds)] where no shadow ray is needed
        #: skip shadow rays that provably cannot be blocked (set False to cast them all)
        self.occlusion_analysis = True
        self._block_offset = dr.opaque(mi.Float, 0.5)  # per-render random shift of the block pattern
        self._in_render = False
        self._pass2 = None  # (pixel mask, spp) while the top-up pass of bounce_min renders
        #: benchmarks: count the rays cast (hidden channels) and store the per-sample means in
        #: ``ray_counts`` = {"intersections": ..., "shadow_rays": ...} after each render
        self.count_rays = False
        self.ray_counts = None

    # ---- set-up ---------------------------------------------------------------------------------
    def prepare_scene(self, scene, sensor=None):
        """Find the detectors of ``scene`` and prepare what the options need; called by
        :meth:`render` (and the Python API) before every render, so moved detectors are seen."""
        detectors = find_detectors(scene)
        if not detectors:
            raise EloInputError(
                "the scene has no detector: mark a shape as detector with <emitter type=\"area\"/> "
                "and give it an id (its channel name)"
            )
        self.detectors = detectors
        self._check_options()
        scatterers = [s for s in scene.shapes() if not s.is_emitter()]
        self.bounce_possible = not (len(scatterers) <= 1 and all(_is_planar(s) for s in scatterers))
        self.notes = []
        if self.events > 1 and not self.bounce_possible:
            self.notes.append(
                "events >= 2 are exactly zero: the only scattering surface is one plane (no chamber, "
                "nothing to scatter an electron twice); no bounce was traced")
        self._quad = []
        if self.detector_sampling == "quadrature":
            for name, shape in detectors:
                tris = detector_triangles(shape, self.quadrature_triangles, name)
                if not np.all(np.isfinite(tris)):
                    raise EloInputError(f"detector {name!r}: non-finite geometry")
                area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
                if not np.sum(area) > 0:
                    raise EloInputError(f"detector {name!r} has zero area")
                # shared vertices: each is subtracted from the scattering point and normed once
                verts, index = np.unique(tris.reshape(-1, 3), axis=0, return_inverse=True)
                index = index.reshape(-1, 3)
                # (q2 - q1) x (q3 - q1) in float64: Eq. A1's numerator is v1 . (v2 x v3) =
                # v1 . ((q2 - q1) x (q3 - q1)), without the float32 cancellation of v2 x v3 for
                # small or distant triangles
                normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
                self._quad.append(([dr.opaque(mi.Point3f, [float(x) for x in v]) for v in verts],
                                   [(tuple(int(i) for i in t), dr.opaque(mi.Vector3f, [float(x) for x in n]))
                                    for t, n in zip(index, normals)]))
        self._tables = self._material_tables(scatterers)
        self._free = [[] for _ in detectors]
        if self.occlusion_analysis:
            sensor = sensor if sensor is not None else (scene.sensors()[0] if scene.sensors() else None)
            if sensor is not None:
                for d, free in enumerate(unoccluded_regions(scene, sensor, detectors)):
                    self._free[d] = [(dr.opaque(mi.UInt32, _shape_key(sh)),
                                      [dr.opaque(mi.Float, float(b)) for b in bounds[1:]]) for sh, bounds in free]

    def _check_options(self):
        if self.events < 1:
            raise EloInputError(f"elo: events={self.events}; must be >= 1 (1 = first event only)")
        if self.detector_sampling not in STRATEGIES:
            raise EloInputError(f"elo: detector_sampling={self.detector_sampling!r}; allowed: {', '.join(STRATEGIES)}")
        for name in ("detector_samples", "bounce_detector_samples", "bounce_samples"):
            if int(getattr(self, name)) < 1:
                raise EloInputError(f"elo: {name}={getattr(self, name)}; must be >= 1")
        if not 4 <= self.quadrature_triangles <= MAX_QUADRATURE_TRIANGLES:
            raise EloInputError(f"elo: quadrature_triangles={self.quadrature_triangles}; must be in "
                                f"[4, {MAX_QUADRATURE_TRIANGLES}]")
        if not (0.0 < self.bounce_fraction <= 1.0):
            raise EloInputError(f"elo: bounce_fraction={self.bounce_fraction!r}; must be in (0, 1]")
        if not (math.isfinite(self.bounce_filter) and self.bounce_filter >= 0):
            raise EloInputError(f"elo: bounce_filter={self.bounce_filter!r} mm; must be >= 0 (0 = off)")
        if not (0.0 < self.bounce_filter_angle < 90.0):
            raise EloInputError(f"elo: bounce_filter_angle={self.bounce_filter_angle!r} deg; must be in (0, 90)")
        if not (math.isfinite(self.bounce_min) and 0.0 <= self.bounce_min <= 4096):
            raise EloInputError(f"elo: bounce_min={self.bounce_min!r}; must be in [0, 4096] (0 = off)")
        if self.quadrature_visibility not in VISIBILITY:
            raise EloInputError(f"elo: quadrature_visibility={self.quadrature_visibility!r}; allowed: {', '.join(VISIBILITY)}")

    @staticmethod
    def _material_tables(scatterers):
        """g_BSE of every scattering surface from per-BSDF tables, without a virtual call: the
        BSDF id of a surface interaction indexes (eta0, 1/lobe_width, W(theta) table) of its
        ``elo_bse``. None (use ``bsdf.eval`` by dispatch) if a scatterer has another BSDF."""
        bsdfs = {}
        for shape in scatterers:
            bsdf = shape.bsdf()
            if not all(hasattr(bsdf, a) for a in ("eta0", "lobe_table", "lobe_width")):
                return None
            bid = int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(bsdf))[0])
            bsdfs[bid] = bsdf
        if not bsdfs:
            return None
        table_size = len(next(iter(bsdfs.values())).lobe_table)
        slot_of = np.zeros(max(bsdfs) + 1, np.uint32)  # slot 0: not a scatterer, g = 0
        eta0 = np.zeros(len(bsdfs) + 1, np.float32)
        inv_width = np.zeros(len(bsdfs) + 1, np.float32)
        lobe = np.zeros((len(bsdfs) + 1) * table_size, np.float32)
        for slot, (bid, bsdf) in enumerate(sorted(bsdfs.items()), start=1):
            table = np.array(bsdf.lobe_table, dtype=np.float32)
            if len(table) != table_size:
                return None
            slot_of[bid] = slot
            eta0[slot] = float(np.array(bsdf.eta0).ravel()[0])
            inv_width[slot] = 1.0 / float(np.array(bsdf.lobe_width).ravel()[0])
            lobe[slot * table_size:(slot + 1) * table_size] = table
        return {"size": table_size, "slot_of": mi.UInt32(slot_of), "eta0": mi.Float(eta0),
                "inv_width": mi.Float(inv_width), "lobe": mi.Float(lobe)}

    def _g_setup(self, si, wi_world, alive):
        """Per scattering point: what g_BSE shares between directions (same formulas as
        elo_bse's ``_terms``, in world coordinates)."""
        t = self._tables
        size = t["size"]
        bid = dr.reinterpret_array(mi.UInt32, si.bsdf())
        slot = dr.gather(mi.UInt32, t["slot_of"], bid, alive & (bid < dr.width(t["slot_of"])))
        eta0 = dr.gather(mi.Float, t["eta0"], slot, alive)
        inv_width = dr.gather(mi.Float, t["inv_width"], slot, alive)
        n = si.sh_frame.n
        cos_t = dr.dot(n, wi_world)
        theta_deg = dr.acos(dr.clip(cos_t, 0.0, 1.0)) * (180.0 / dr.pi)
        k = theta_deg * inv_width
        pos = theta_deg * ((size - 1) / 90.0)
        i0 = mi.UInt32(dr.clip(dr.floor(pos), 0, size - 2))
        frac = pos - mi.Float(i0)
        base = slot * size + i0
        w0 = dr.gather(mi.Float, t["lobe"], base, alive)
        w1 = dr.gather(mi.Float, t["lobe"], base + 1, alive)
        weight = dr.fma(frac, w1 - w0, w0)
        mirror = n * (2.0 * cos_t) - wi_world  # mirror direction of p_E = -wi about n
        return (eta0 * (1.0 / dr.pi), weight, k, n, mirror, alive & (cos_t > 0))

    @staticmethod
    def _g(setup, d):
        diffuse, weight, k, n, mirror, ok = setup
        cos_a = dr.dot(n, d)
        cos_b = dr.dot(mirror, d)
        lobe = dr.select(cos_b > 0, dr.power(dr.maximum(cos_b, 1e-30), k), 0.0)
        g = dr.fma(diffuse, cos_a, weight * lobe)
        return dr.select(ok & (cos_a > 0), g, 0.0)

    def _g_many(self, si, bsdf, ctx, ray, alive, dirs_world):
        """g_BSE (cosine included) for world directions; inline tables or one dispatch."""
        if self._tables is not None:
            setup = self._g_setup(si, -ray.d, alive)
            return [self._g(setup, d) for d in dirs_world]
        return dr.dispatch(bsdf, _eval_directions, ctx, si, [si.to_local(d) for d in dirs_world], active=alive)

    def traced_events(self):
        """Events actually traced (1 when the scene cannot scatter twice)."""
        return self.events if self.bounce_possible else 1

    def channel_names(self):
        names = []
        for name, _ in self.detectors:
            names.append(name)
            if self.events > 1:
                names += [f"{name}.e{k}" for k in range(1, self.events + 1)]
        return names

    def _guided(self):
        return self.bounce_filter > 0 and self.traced_events() > 1

    def _hidden(self):
        return (list(_GUIDE) if self._guided() else []) + (list(_COUNTS) if self.count_rays else [])

    def aov_names(self):
        return self.channel_names() + self._hidden()

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if self._in_render:
            # the base class's render dispatches back to this override once: render plainly
            return mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)
        self._in_render = True
        try:
            return self._render(scene, sensor, seed, spp, develop, evaluate)
        finally:
            self._in_render = False

    def _render(self, scene, sensor, seed, spp, develop, evaluate):
        sensor_obj = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        self.prepare_scene(scene, sensor_obj)
        # the block selection of bounce_fraction: a fresh uniform shift per seed (unbiased)
        seed_value = int(np.array(seed, dtype=np.uint64).ravel()[0]) if not isinstance(seed, int) else seed
        self._block_offset = dr.opaque(mi.Float, float(np.random.default_rng([seed_value, 7]).random()))
        image = mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)
        if not develop:
            return image
        n_public = 1 + len(self.channel_names())
        col = {name: i for i, name in enumerate(["Y"] + self.aov_names())}
        if self.count_rays:
            self.ray_counts = {"intersections": float(np.mean(np.array(image[..., col[_COUNTS[0]]]))),
                               "shadow_rays": float(np.mean(np.array(image[..., col[_COUNTS[1]]])))}
        if self.traced_events() > 1 and (self.bounce_filter > 0 or self.bounce_min > 0):
            n_spp = int(spp) if int(spp) > 0 else int(sensor_obj.sampler().sample_count())
            rate = self.bounce_fraction * self.bounce_samples * n_spp  # paths per pixel, expected
            paths = np.full(tuple(image.shape[:2]), rate, np.float32)
            if self.bounce_filter > 0:
                self._filter_bounces(image, col, sensor_obj, paths)
            if self.bounce_min > 0:
                self._top_up(image, col, scene, sensor, seed_value, paths)
            self._totals(image, col)
        if image.shape[2] > n_public:  # drop the hidden channels
            image = image[..., :n_public]
        return image

    def _top_up(self, image, col, scene, sensor, seed, paths):
        """bounce_min: pixels whose events >= 2 rest on fewer continuation paths than that (e.g.
        where the filter must stop at edges) get a second pass of bounce paths only; the two
        estimates are averaged with their path counts as weights."""
        need = paths < self.bounce_min
        if not np.any(need):
            return
        missing = float(np.max(self.bounce_min - paths[need]))
        k = max(1, min(8, math.ceil(missing)))
        spp2 = max(1, math.ceil(missing / k))
        saved = (self.bounce_samples, self.bounce_fraction, self.bounce_filter, self.count_rays)
        self._pass2 = (mi.Bool(need.ravel()), dr.opaque(mi.UInt32, spp2))
        # same film channels as the main pass (hidden ones included) so the columns agree
        self.bounce_samples, self.bounce_fraction = k, 1.0
        try:
            extra = mi.SamplingIntegrator.render(self, scene, sensor, seed + 0x5EED, spp2, True, True)
        finally:
            self._pass2 = None
            self.bounce_samples, self.bounce_fraction, self.bounce_filter, self.count_rays = saved
        n2 = float(k * spp2)
        w1 = np.where(need, paths / (paths + n2), 1.0).astype(np.float32)
        for d, _ in self.detectors:
            for e in range(2, self.events + 1):
                c = col[f"{d}.e{e}"]
                mixed = np.array(image[..., c]) * w1 + np.array(extra[..., c]) * (1.0 - w1)
                image[..., c] = mi.Float(mixed.ravel())
        paths[need] += n2

    def _totals(self, image, col):
        """Each detector's total and the film's sum channel from the event channels (in place)."""
        totals = []
        for d, _ in self.detectors:
            total = image[..., col[f"{d}.e1"]]
            for e in range(2, self.events + 1):
                total = total + image[..., col[f"{d}.e{e}"]]
            totals.append(total)
        y = totals[0]
        for total in totals[1:]:
            y = y + total
        dr.eval(y, *totals)  # read everything first: the writes below then need no copy
        for (d, _), total in zip(self.detectors, totals):
            image[..., col[d]] = total.array
        image[..., 0] = y.array

    # ---- the estimator --------------------------------------------------------------------------
    def sample(self, scene, sampler, ray, medium=None, active=True):
        ctx = mi.BSDFContext()
        n_det = len(self.detectors)
        traced = self.traced_events()
        counting = self.count_rays
        self._n_shadow = mi.Float(0.0) if counting else None

        # ---- 1st event: where the beam hits
        alive = mi.Bool(active)
        si = scene.ray_intersect(ray, alive)
        n_isect = dr.select(alive, 1.0, 0.0) if counting else None
        # electrons scatter only on surfaces that are not detectors (detectors absorb)
        alive &= si.is_valid() & ~si.shape.is_emitter()
        bsdf = si.bsdf(ray)
        if self._pass2 is not None:  # top-up pass of bounce_min: events >= 2 only
            first = [mi.Float(0.0) for _ in range(n_det)]
        elif self.detector_sampling == "quadrature":
            first = self._quadrature(scene, sampler, si, bsdf, ctx, ray, alive)
        else:
            first = self._sampled(scene, sampler, si, bsdf, ctx, ray, alive, self.detector_samples,
                                  self.detector_sampling != "independent")
        per_event = [[first[d]] for d in range(n_det)]
        si_first, alive_first = si, mi.Bool(alive)

        # ---- events 2 .. traced: continue by sampling g_BSE (Eq. 7)
        if traced > 1:
            outer_shadow = self._n_shadow

            k_paths = self.bounce_samples

            def bounces(si, ray, alive, sampler):
                self._n_shadow = mi.Float(0.0) if counting else None
                # k continuation paths from the same 1st event (splitting), each weighted 1/k
                later, n_hit = self._bounces(scene, sampler, si, ray, bsdf_of(si, ray), ctx, alive, traced)
                for _ in range(k_paths - 1):
                    more, more_hit = self._bounces(scene, sampler, si, ray, bsdf_of(si, ray), ctx, alive, traced)
                    later = [[a + b for a, b in zip(x, y)] for x, y in zip(later, more)]
                    n_hit = n_hit + more_hit
                if k_paths > 1:
                    later = [[a * (1.0 / k_paths) for a in x] for x in later]
                extra = [n_hit, self._n_shadow] if counting else []
                return tuple(x for per_det in later for x in per_det) + tuple(extra)

            def bsdf_of(si_, ray_):
                return si_.bsdf(ray_)

            n_out = n_det * (traced - 1) + (2 if counting else 0)
            if self._pass2 is not None:
                # only the pixels in the mask (Mitsuba orders lanes pixel by pixel, spp each)
                mask, spp2 = self._pass2
                pixel = dr.arange(mi.UInt32, dr.width(alive)) // spp2
                chosen = dr.gather(mi.Bool, mask, pixel, alive)
                out = dr.if_stmt((si, ray, alive, sampler), alive & chosen, bounces,
                                 lambda *args: tuple(mi.Float(0.0) for _ in range(n_out)))
            elif self.bounce_fraction < 1.0:
                # whole blocks of lanes (neighbouring pixels) trace the bounce or skip it, so that
                # the skipped work is really not done; each block with probability f, weight 1/f
                lane = dr.arange(mi.UInt32, dr.width(alive))
                u = mi.Float(lane >> _BLOCK_SHIFT) * _GOLDEN + self._block_offset
                fraction = dr.opaque(mi.Float, self.bounce_fraction)
                keep = (u - dr.floor(u)) < fraction
                out = dr.if_stmt((si, ray, alive, sampler), alive & keep, bounces,
                                 lambda *args: tuple(mi.Float(0.0) for _ in range(n_out)))
                inv = 1.0 / fraction
                out = tuple(x * inv for x in out[: n_det * (traced - 1)]) + tuple(out[n_det * (traced - 1):])
            else:
                out = bounces(si, ray, alive, sampler)
            for d in range(n_det):
                per_event[d] += list(out[d * (traced - 1):(d + 1) * (traced - 1)])
            if counting:
                n_isect = n_isect + out[-2]
                self._n_shadow = outer_shadow + out[-1]

        # ---- channels
        scale = self.beam_current * self.transimpedance if self.units == "voltage" else 1.0
        aovs = []
        total_all = mi.Float(0.0)
        for d in range(n_det):
            events = [e * scale for e in per_event[d]]
            events += [mi.Float(0.0)] * (self.events - len(events))  # not traced: exactly zero
            total = events[0]
            for e in events[1:]:
                total = total + e  # not +=: Dr.Jit's in-place add would alias events[0]
            total_all = total_all + total
            aovs.append(total)
            if self.events > 1:
                aovs += events
        if self._guided():
            if self._pass2 is not None:
                aovs += [mi.Float(0.0)] * 3
            else:
                n = dr.select(alive_first, si_first.sh_frame.n, mi.Vector3f(0.0))
                aovs += [n.x, n.y, n.z]
        if counting:
            aovs += [n_isect, self._n_shadow]
            self._n_shadow = None
        return mi.Spectrum(total_all), mi.Bool(True), aovs

    def _bounces(self, scene, sampler, si, ray, bsdf, ctx, alive, traced):
        """Events 2 .. traced for the paths alive after the 1st: per detector a list of their
        direct contributions, and the number of bounce rays cast (for count_rays)."""
        n_det = len(self.detectors)
        later = [[] for _ in range(n_det)]
        alive = mi.Bool(alive)  # a copy: the &= below must not change the caller's mask
        throughput = mi.Float(1.0)
        n_hit = mi.Float(0.0)
        stratify = self.detector_sampling != "independent"
        for event in range(1, traced):
            bs, weight = bsdf.sample(ctx, si, sampler.next_1d(alive), sampler.next_2d(alive), alive)
            throughput = throughput * weight[0]
            alive &= throughput > 0
            ray = si.spawn_ray(si.to_world(bs.wo))
            si = scene.ray_intersect(ray, alive)
            n_hit = n_hit + dr.select(alive, 1.0, 0.0)
            alive &= si.is_valid() & ~si.shape.is_emitter()
            bsdf = si.bsdf(ray)
            counting = self.count_rays

            def direct_fn(si, ray, alive, sampler, bsdf=bsdf):
                outer = self._n_shadow
                self._n_shadow = mi.Float(0.0) if counting else None
                out = self._sampled(scene, sampler, si, bsdf, ctx, ray, alive, self.bounce_detector_samples,
                                    stratify)
                extra = [self._n_shadow] if counting else []
                self._n_shadow = outer
                return tuple(out) + tuple(extra)

            # paths that left the scene (most, without a chamber) skip the detector estimate:
            # whole SIMD packets of escaped paths do no work at all
            out = dr.if_stmt((si, ray, alive, sampler), alive, direct_fn,
                             lambda *args: tuple(mi.Float(0.0) for _ in range(n_det + (1 if counting else 0))))
            if counting:
                self._n_shadow = self._n_shadow + out[-1]
            for d in range(n_det):
                later[d].append(throughput * out[d])
        return later, n_hit

    def _ray_test(self, scene, ray, active):
        if self.count_rays:
            self._n_shadow = self._n_shadow + dr.select(active, 1.0, 0.0)
        return scene.ray_test(ray, active)

    def _unblockable(self, si, d):
        """Lanes whose point lies in a region from which detector d cannot be occluded."""
        if not self._free[d]:
            return None
        shape_id = dr.reinterpret_array(mi.UInt32, si.shape)
        skip = mi.Bool(False)
        for sid, (x0, x1, y0, y1) in self._free[d]:
            skip |= (shape_id == sid) & (si.p.x >= x0) & (si.p.x <= x1) & (si.p.y >= y0) & (si.p.y <= y1)
        return skip

    def _visible(self, scene, si, target, test, d):
        """test & not occluded on the way from si to target (a point on detector d)."""
        skip = self._unblockable(si, d)
        cast = test if skip is None else test & ~skip
        return test & ~self._ray_test(scene, si.spawn_ray_to(target), cast)

    def _sampled(self, scene, sampler, si, bsdf, ctx, ray, alive, n_pts, stratify):
        """Per detector: sum over n_pts sampled points of g_BSE / pdf, with occlusion."""
        if stratify:
            rows = max(1, int(math.isqrt(n_pts)))
            cols = [n_pts // rows + (1 if r < n_pts % rows else 0) for r in range(rows)]
            cells = [(r, c, cols[r]) for r in range(rows) for c in range(cols[r])]
        wos, weights = [], []
        for d, (_, shape) in enumerate(self.detectors):
            emitter = shape.emitter()
            for i in range(n_pts):
                u = sampler.next_2d(alive)
                w = 1.0 / n_pts
                if stratify:
                    r, c, nc = cells[i]
                    u = mi.Point2f((c + u.x) / nc, (r + u.y) / rows)
                    w = 1.0 / (rows * nc)
                ds, em_weight = emitter.sample_direction(si, u, alive)
                # em_weight = 1/pdf (unit radiance), 0 at the detector's back face
                test = alive & (ds.pdf > 0)
                visible = self._visible(scene, si, ds.p, test, d)
                wos.append(ds.d)
                weights.append(dr.select(visible, em_weight[0] * w, 0.0))
        g = self._g_many(si, bsdf, ctx, ray, alive, wos)
        out = []
        k = 0
        for _ in self.detectors:
            acc = mi.Float(0.0)
            for _ in range(n_pts):
                acc = dr.fma(g[k], weights[k], acc)
                k += 1
            out.append(acc)
        return out

    def _quadrature(self, scene, sampler, si, bsdf, ctx, ray, alive):
        """Appendix A (Eq. A2): sum over detector triangles of Omega_p (Eq. A1, corrected) times
        g_BSE at the centroid direction; occlusion by one sampled ray or one per triangle."""
        p = si.p
        omegas, dirs, per_det = [], [], []
        for verts, tris in self._quad:
            v = [q - p for q in verts]
            lengths = [dr.norm(x) for x in v]
            dots = {}

            def dot(i, j):
                key = (min(i, j), max(i, j))
                if key not in dots:
                    dots[key] = dr.dot(v[i], v[j])
                return dots[key]

            per_det.append(len(tris))
            for (i, j, k), twice_area_normal in tris:
                num = dr.dot(v[i], twice_area_normal)
                den = (lengths[i] * lengths[j] * lengths[k] + dot(i, j) * lengths[k]
                       + dot(i, k) * lengths[j] + dot(j, k) * lengths[i])
                # counter-clockwise about the front normal: num < 0 seen from the front
                omegas.append(dr.maximum(2.0 * dr.atan2(-num, den), 0.0))
                dirs.append(dr.normalize(v[i] + v[j] + v[k]))
        g = self._g_many(si, bsdf, ctx, ray, alive, dirs)
        out = []
        base = 0
        for d, ((verts, tris), n_tri) in enumerate(zip(self._quad, per_det)):
            ws = [omegas[base + j] * g[base + j] for j in range(n_tri)]
            if self.quadrature_visibility == "triangle":
                acc = mi.Float(0.0)
                for j, ((a, b, c), _) in enumerate(tris):
                    test = alive & (ws[j] > 0)
                    centroid = (verts[a] + verts[b] + verts[c]) * (1.0 / 3.0)
                    acc = acc + dr.select(self._visible(scene, si, centroid, test, d), ws[j], 0.0)
                out.append(acc)
                base += n_tri
                continue
            total = ws[0]
            for w in ws[1:]:
                total = total + w
            # pick triangle j with probability w_j / total, a uniform point in it, one ray
            u = sampler.next_1d(alive) * total
            bary = mi.warp.square_to_uniform_triangle(sampler.next_2d(alive))
            target = mi.Point3f(0.0)
            cum = mi.Float(0.0)
            for j, ((a, b, c), _) in enumerate(tris):
                point = verts[a] * (1.0 - bary.x - bary.y) + verts[b] * bary.x + verts[c] * bary.y
                nxt = cum + ws[j]
                pick = (u >= cum) & (u < nxt) if j + 1 < n_tri else (u >= cum)
                target = dr.select(pick, point, target)
                cum = nxt
            test = alive & (total > 0)
            out.append(dr.select(self._visible(scene, si, target, test, d), total, 0.0))
            base += n_tri
        return out

    # ---- events >= 2 estimated in space ----------------------------------------------------------
    def _filter_bounces(self, image, col, sensor, paths=None):
        """Replace the event >= 2 channels of the developed film ``image`` (TensorXf, H x W x C,
        in place) by their normal-guided window average (see the module docstring).

        Multi-scale and cheap: a sum pyramid of tiles of 2^j pixels (one pass over the image);
        the window of a tile is the 3 x 3 tiles around it (2^j about the filter half-width at the
        top level); it counts as homogeneous if the mean of its unit normals (zero where the beam
        missed) is longer than cos(bounce_filter_angle). Pixels whose surrounding windows are all
        homogeneous take the bilinear interpolation of the window means; the others go on to
        tiles half as large (three scales at most); what is left keeps its own value. ``paths``
        (H, W) is multiplied by the number of pixels each value now averages."""
        h, w = int(image.shape[0]), int(image.shape[1])
        field = getattr(sensor, "field", None)
        if not field:
            return
        radius = self.bounce_filter / (field / w)  # window half-width in pixels
        if radius < 1.0:
            return
        top = max(0, int(round(math.log2((2.0 * radius + 1.0) / 3.0))))
        bounce_cols = [col[f"{d}.e{k}"] for d, _ in self.detectors for k in range(2, self.events + 1)]
        n_later = len(bounce_cols)
        size = 1 << top
        hp, wp = -(-h // size) * size, -(-w // size) * size
        data = np.zeros((hp, wp, 4 + n_later), np.float32)  # normal, pixel count, events >= 2
        for i, g in enumerate(_GUIDE):
            data[:h, :w, i] = np.array(image[..., col[g]])
        data[:h, :w, 3] = 1.0
        later = np.empty((n_later, h, w), np.float32)
        for i, c in enumerate(bounce_cols):
            later[i] = np.array(image[..., c])
            data[:h, :w, 4 + i] = later[i]
        normal = data[:h, :w, :3]
        # pixels whose beam hit a scattering surface (their film normal is a unit vector)
        undecided = np.einsum("ijk,ijk->ij", normal, normal) > 0.25
        pyramid = [data]
        for _ in range(top):
            x = pyramid[-1]
            pyramid.append(x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2])
        cos2 = math.cos(math.radians(self.bounce_filter_angle)) ** 2
        for level in range(top, max(top - 3, 0) - 1, -1):  # three scales at most
            if not np.any(undecided):
                break
            tiles = pyramid[level]
            nt, ns = tiles.shape[:2]
            pad = np.pad(tiles, ((1, 1), (1, 1), (0, 0)))
            win = sum(pad[i:i + nt, j:j + ns] for i in range(3) for j in range(3))
            count = np.maximum(win[..., 3:4], 1.0)
            n_mean = win[..., :3] / count
            # homogeneous: every pixel of the window valid (|n| = 1) and the normals agree
            homogeneous = np.einsum("ijk,ijk->ij", n_mean, n_mean) > cos2
            hh = np.pad(homogeneous, ((0, 1), (0, 1)), mode="edge")
            ok = hh[:-1, :-1] & hh[1:, :-1] & hh[:-1, 1:] & hh[1:, 1:]
            tile = 1 << level
            iy, ay = _interpolation(h, nt, tile)
            ix, ax = _interpolation(w, ns, tile)
            take = undecided & ok[iy][:, ix]
            if not np.any(take):
                continue
            means = np.ascontiguousarray((win[..., 4:] / count).transpose(2, 0, 1))
            for c in range(n_later):
                smooth = ay @ means[c] @ ax.T  # window centres -> pixel centres
                np.copyto(later[c], smooth, where=take)
            if paths is not None:  # continuation paths behind each pixel's value now
                np.copyto(paths, paths * win[..., 3][iy][:, ix], where=take)
            undecided &= ~take
        for i, c in enumerate(bounce_cols):
            image[..., c] = mi.Float(later[i].ravel())

    def to_string(self):
        names = ", ".join(n for n, _ in self.detectors) or "(resolved at render time)"
        return (f"EloIntegrator[events={self.events}, detector_sampling={self.detector_sampling}, "
                f"detector_samples={self.detector_samples}, units={self.units}, detectors={names}]")


PLUGIN_CLASS = EloIntegrator
