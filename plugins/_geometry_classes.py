"""Geometry classes of the scan points: pixels whose surroundings match share their events >= 2.

Where the relief scatters onto itself (a flank onto the facing flank), events >= 2 vary on the
relief's own scale, also along a flank whose normals agree, so the bounce filter's window average
is biased there (:mod:`._relief`). What those events depend on near the surface is the geometry
the electrons leaving the scan point can meet: two scan points with the same normal, the same
surroundings and nearby positions (the walls far away see them alike) have the same expected
events >= 2. This module sorts the pixels into classes of such points, once per geometry:

* the beam's ray at each pixel centre (the scan point, as the ``elo_beam`` sensor aims it);
* :data:`PROBES` fixed directions in the local frame of the normal (a cosine-weighted
  Hammersley set, the same for every pixel), each traced up to :data:`NEAR_MM` (the far field's
  near distance): the distance to the first surface, binned in steps of 1/:data:`STEPS_PER_E`
  of a natural-log unit (a factor 1.65);
* the normal, quantised in steps of sin(:data:`NORMAL_DEG`);
* the block of :math:`b \\times b` pixels (``block_mm``) holding the pixel.

Under a beam profile (fwhm > 0) a pixel's events >= 2 average over the beam's footprint, so the
normal and :data:`FOOTPRINT_PROBES` probes are also taken at four points of it
(:data:`FOOTPRINT_SIGMAS` standard deviations from the grid point along +-x and +-y) and all five
enter the class.

A class is the pixels of one block with equal quantised normal and probe distances; the integrator
replaces each pixel's events >= 2 by its class's (``bounce_share``): for each detector the pixel's
view factor of it (cos / r^2 of the detector's centre from the beam's hit, over a level plane:
:meth:`GeometryClasses.view_factors`) times the class's ratio of events to view factors, times
1 + theta . (x, y), (x, y) the pixel's place in its class and theta the tilt that all classes of
its quantised normal share, fitted by least squares in each render (:meth:`GeometryClasses.tilts`):
the beam's incidence on a flank changes across the field (perspective), and with it what the flank
sends onto the facing one (corrugated_chamber at 1500^2, 64 unshared renders each shared as the
integrator does, RMS per pixel of e2 by detector: 16 mm blocks 1.10-1.36 % without the tilt,
0.36-0.63 % with it; of the total, worst detector, 0.19 % against 0.22 % in the 8 mm blocks
without it of the presets before). A detector
sees the same relief from the block's near side under a larger solid angle, so a plain mean
would tilt every class across its block: corrugated_chamber at 1500^2, 8 mm blocks, 0.97-1.15 % of
e2 per pixel (RMS) plain, 0.58-0.75 % with the view factors; the 1st event of the flat plate
shared so: 0.96 -> 0.03 % (tests/test_geometry_classes.py). Where the relief repeats (the
corrugated sheet: every point of a flank line along its ridge), a class holds the points of a line
and the average is unbiased but for what varies within the block otherwise (the far field, the
beam's incidence); where no two points match, every pixel keeps its own value (no gain, no bias). A class can still join points whose probes agree but whose events >= 2 do
not: a difference between the probe directions, such as how much of the facing flank a point on
the sawtooth plate sees by its distance to the valley's end (16 probes left 7.2 % of e2 per
pixel there, 64 leave 2.8 % in 4 mm blocks and 3.3 % in 8 mm ones: :data:`PROBES`). The bias that is left is measured (``python -m
benchmarks.geometry_share --classes``), never seen by the render's own error estimate (both
halves share the classes). Each pixel's rank in
its class (:meth:`GeometryClasses.ranks`) places its paths in the point set the class's samples
share (:func:`._strata.spread_point`).
"""

import dataclasses
import hashlib
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ._far_field import NEAR_MM
from ._shapes import digest_geometry, shape_key
from ._threads import each_plane

#: Probe directions per pixel (a power of two: the Hammersley set). Two points whose surroundings
#: differ only between the probes share a class: on the sawtooth plate (valleys ending at the
#: patches' cliffs) the pixels' e2 differs from its class mean by 9.0 % (RMS, of the plate's mean
#: e2, worst detector) with 16 probes, 5.2 % with 32, 2.8 % with 64, 1.7 % with 128 (144 unshared
#: renders at 256²; 16 probes in the finer bins used with them before: 7.2 %). 64 leave a bias of
#: 0.08 of one render's noise in 5 mm means and do not add noise on corrugated_chamber; 128 add
#: 10 % there (benchmarks/RESULTS.md, "64 probes").
PROBES = 64
#: Probe directions at each of the four footprint points under a beam profile.
FOOTPRINT_PROBES = 16
#: Probe distances are binned in steps of 1/STEPS_PER_E in log(distance) (a factor 1.28). Across a
#: flank of the corrugated sheet e2 changes by a factor 4.5 in 13 pixels at 1500², and bins of a
#: factor 1.65 (STEPS_PER_E = 2) joined neighbouring places on it: the classes' bias there (4 mm
#: blocks, from 8 unshared renders, RMS per pixel of e2) 0.93-1.09 % with 2, 0.56-0.63 % with 4,
#: 0.38-0.56 % with 8 (plain means; with the view factors 0.87-0.99 / 0.32-0.46 / 0.19-0.38 %); the
#: classes' effective size, (mean of 1/sqrt(n))^-2, 119 / 99 / 89 pixels (2026-12-06).
STEPS_PER_E = 4
#: Normals are quantised in steps of sin(NORMAL_DEG) along x and y.
NORMAL_DEG = 1.0
#: Shortest probe distance told apart (mm): closer hits count as this distance.
MIN_DISTANCE_MM = 1e-3
#: With a beam profile, the classes also look this many standard deviations of it away from the
#: grid point (along +-x and +-y): inside that radius lie 68 % of a 2-D Gaussian's electrons.
FOOTPRINT_SIGMAS = 1.5
#: Least cosine of a detector's centre over a level plane at the beam's hit in the view factors
#: that scale a class's mean across its block (:meth:`GeometryClasses.view_factors`): a detector
#: at or below the plate's level still gets a positive factor.
MIN_VIEW_COS = 0.05
#: Least pixels, in classes of two or more, of one quantised normal for the classes of that normal
#: to fit a tilt across their blocks (:meth:`GeometryClasses.tilts`).
MIN_TILT_PIXELS = 4096
#: Largest |theta . (x, y)| a tilt may give a pixel: a tilt is a correction to the class's mean.
MAX_TILT = 0.5
#: Seed of the fixed order in which the pixels of a class take their places in its point set.
RANK_SEED = 0x6E0E
#: Pixels classified at a time (bounds the float64 temporaries to about 60 MB).
CHUNK = 1 << 18
#: The probes' offset from the surface along its normal, relative to 1 + max |p| (89 float32
#: roundoffs: 2e-4 mm at 40 mm, far above the origin's float32 rounding, 2e-6 mm; Mitsuba's own
#: spawn_ray offsets by 17x more).
RAY_EPSILON = 89.0 * 2.0 ** -24
#: Most probe directions a point may take (the multipliers below cover them).
MAX_PROBES = 1024
#: Odd 64-bit multipliers of the class key's hash (fixed: classes are reproducible).
_MIX = np.random.default_rng(0x6E0C).integers(1, 1 << 62, size=MAX_PROBES + 4, dtype=np.int64) * 2 + 1
_POINT_MIX = (np.random.default_rng(0x6E0D).integers(1, 1 << 62, size=5, dtype=np.int64) * 2 + 1).astype(np.uint64)


def probe_directions(count=PROBES):
    """The fixed probe directions in the local frame (count, 3): cosine-weighted Hammersley."""
    bits = int(round(math.log2(count)))
    k = np.arange(count)
    u = (k + 0.5) / count
    v = np.array([int(format(int(x), f"0{bits}b")[::-1], 2) for x in k]) / count + 0.5 / count
    r = np.sqrt(v)
    phi = 2.0 * np.pi * u
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1.0 - v))], axis=1)


def geometry_key(scene, sensor, keys):
    """What the classes depend on: the placement (:class:`~._shapes.GeometryKey`) of every shape a probe could meet,
    the beam (with its profile: the footprint's points) and the film. Detectors farther than :data:`NEAR_MM` from the field (with a margin of
    half the field for where relief moves the beam's hits) are left out, so that a sweep moving
    them reuses the classes."""
    digest = hashlib.sha1()
    reach = (0.5 * float(sensor.field) + 0.5 * max(float(sensor.field), float(sensor.field_y)) + NEAR_MM,
             0.5 * float(sensor.field_y) + 0.5 * max(float(sensor.field), float(sensor.field_y)) + NEAR_MM)
    for shape in scene.shapes():
        box = shape.bbox()
        lo, hi = np.ravel(box.min), np.ravel(box.max)
        if shape.is_emitter() and (lo[0] > reach[0] or hi[0] < -reach[0] or lo[1] > reach[1] or hi[1] < -reach[1]):
            continue  # a detector out of the probes' reach
        digest_geometry(digest, shape, keys)
    size = sensor.film().crop_size()
    return (digest.hexdigest(), float(sensor.field), float(sensor.field_y), float(sensor.wd),
            float(getattr(sensor, "fwhm", 0.0)), str(getattr(sensor, "projection", "")), tuple(sensor.aim_offset_mm),
            int(size[0]), int(size[1]))


def distance_edges():
    """The edges of the probe distances' bins (mm, float64, increasing): e^(k / STEPS_PER_E) from
    :data:`MIN_DISTANCE_MM` to :data:`NEAR_MM`. Distances below the first edge share a bin, and so
    do those beyond the last one and the probes that meet nothing."""
    k = np.arange(math.ceil(math.log(MIN_DISTANCE_MM) * STEPS_PER_E), math.floor(math.log(NEAR_MM) * STEPS_PER_E) + 1)
    return np.exp(k / STEPS_PER_E)


def _float3(kind, a):
    """``kind`` (mi.Point3f, mi.Vector3f) from the float64 rows ``a`` (N, 3), rounded to float32."""
    return kind(*[mi.Float(np.ascontiguousarray(a[:, c], np.float32)) for c in range(3)])


def _rays(o, d):
    return mi.Ray3f(_float3(mi.Point3f, o), _float3(mi.Vector3f, d))


def _frame(n):
    """Tangents (s, t) of unit normals ``n`` (N, 3), as Mitsuba's coordinate_system (float64)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    s = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return s, t


def _surface_points(scene, hit, si, valid):
    """The hits on the surface (N, 3), float64: on a mesh from the ray tracer's triangle and
    barycentric coordinates (o + t d would miss the surface by the rounding of t, ~1e-5 mm at
    400 mm, enough to start a probe below it); on other shapes Mitsuba's own point."""
    p = np.stack([np.array(c, np.float64) for c in si.p], axis=1)
    keys = np.array(dr.reinterpret_array(mi.UInt32, hit.shape))
    prim = np.array(hit.prim_index, np.int64)
    uv = np.stack([np.array(c, np.float64) for c in hit.prim_uv], axis=1)
    for shape in scene.shapes():
        if not shape.is_mesh():
            continue
        on = valid & (keys == shape_key(shape))
        if not on.any():
            continue
        vertices = np.array(shape.vertex_positions_buffer(), np.float64).reshape(-1, 3)
        faces = np.array(shape.faces_buffer(), np.int64).reshape(-1, 3)[prim[on]]
        b1, b2 = uv[on, 0:1], uv[on, 1:2]
        p[on] = vertices[faces[:, 0]] * (1.0 - b1 - b2) + vertices[faces[:, 1]] * b1 + vertices[faces[:, 2]] * b2
    return p


def scan_features(scene, sensor):
    """Per pixel (H x W): whether the beam meets a scattering surface there, a 64-bit hash of
    its quantised normal (2 ints) and probe distances (:data:`PROBES` ints), equal for equal
    features, the beam's hit at the grid point (H x W x 3, float32, mm; meaningless where it
    meets no scattering surface) and a 64-bit hash of the quantised normal at the grid point alone.

    The rays are built on the host in float64 from the beam's centre rays and the distances come
    from the ray tracer as they are, so that the classes do not depend on the instruction set
    Dr.Jit compiles for: a last-bit change of a beam direction moves its hit by 4e-5 mm at 400 mm
    work distance, enough to move some probe distances across a quantisation step (10 of 2304
    pixels of corrugated_sheet at 48² changed class between AVX-512 and AVX2 kernels when the rays
    were built in the kernel). The normal alone comes from the kernel (it is quantised coarsely).
    """
    size = sensor.film().crop_size()
    w, h = int(size[0]), int(size[1])
    valid = np.ones(w * h, bool)
    key = np.zeros(w * h, np.uint64)
    normal = np.zeros(w * h, np.uint64)
    points = np.zeros((w * h, 3), np.float32)
    for k, offset in enumerate(footprint_offsets(sensor)):
        o, d = sensor.centre_rays(offset)
        for a in range(0, w * h, CHUNK):  # float64 temporaries of CHUNK pixels at a time
            ok, part, p, n = _chunk_features(scene, o[a:a + CHUNK], d[a:a + CHUNK],
                                             PROBES if k == 0 else FOOTPRINT_PROBES)
            valid[a:a + CHUNK] &= ok
            if k == 0:
                points[a:a + CHUNK] = p
                normal[a:a + CHUNK] = n
            with np.errstate(over="ignore"):  # the hash wraps around (uint64), as intended
                key[a:a + CHUNK] += part * _POINT_MIX[k]
    return (valid.reshape(h, w), key.view(np.int64).reshape(h, w), points.reshape(h, w, 3),
            normal.view(np.int64).reshape(h, w))


def footprint_offsets(sensor):
    """Where on the build plane (mm, about the pixel's grid point) the classes look: the grid
    point; with a beam profile (fwhm > 0) also :data:`FOOTPRINT_SIGMAS` standard deviations of it
    along +-x and +-y, so that pixels share only where their footprints' surroundings match."""
    sigma = float(np.ravel(getattr(sensor, "sigma", 0.0))[0]) if getattr(sensor, "fwhm", 0.0) > 0 else 0.0
    if not sigma > 0:
        return [(0.0, 0.0)]
    r = FOOTPRINT_SIGMAS * sigma
    return [(0.0, 0.0), (r, 0.0), (-r, 0.0), (0.0, r), (0.0, -r)]


def _chunk_features(scene, o, d, probes):
    """:func:`scan_features` for the beam rays (o, d) (N, 3) and ``probes`` directions: (valid, hash,
    hit point, hash of the quantised normal alone) per ray."""
    ray = _rays(o, d)
    hit = scene.ray_intersect_preliminary(ray)
    si = hit.compute_surface_interaction(ray)
    hit_valid = si.is_valid() & ~si.shape.is_emitter()
    # one kernel for everything read back (each read alone would trace the rays again)
    dr.eval(hit_valid, si.sh_frame.n, si.p, hit.shape, hit.prim_index, hit.prim_uv)
    valid = np.array(hit_valid, dtype=bool)
    n = np.stack([np.array(c, np.float64) for c in si.sh_frame.n], axis=1)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    n[~valid] = (0.0, 0.0, 1.0)
    p = _surface_points(scene, hit, si, valid)
    step = math.sin(math.radians(NORMAL_DEG))
    mix = _MIX.astype(np.uint64)
    with np.errstate(over="ignore"):  # the hash wraps around (uint64), as intended
        key = np.round(n[:, 0] / step).astype(np.int64).astype(np.uint64) * mix[2]
        key += np.round(n[:, 1] / step).astype(np.int64).astype(np.uint64) * mix[3]
        normal = key.copy()
        # leave the surface along the normal, by an offset scaled by |p| (as Mitsuba's spawn_ray)
        origin = p + n * (RAY_EPSILON * (1.0 + np.max(np.abs(p), axis=1)))[:, None]
        o = _float3(mi.Point3f, origin)
        # the frame in float32 columns: numpy's float32 products and sums round alike on every CPU
        s, t = _frame(n)
        columns = [[np.ascontiguousarray(v[:, c], np.float32) for c in range(3)] for v in (s, t, n)]
        active = mi.Bool(valid)
        edges = distance_edges()
        for c, (dx, dy, dz) in enumerate(probe_directions(probes).astype(np.float32)):
            direction = mi.Vector3f(*[mi.Float(columns[0][a] * dx + columns[1][a] * dy + columns[2][a] * dz)
                                      for a in range(3)])
            ray = mi.Ray3f(o, direction)
            ray.maxt = NEAR_MM
            t_probe = np.array(scene.ray_intersect_preliminary(ray, active).t, np.float64)  # inf: nothing met
            # the bin by exact comparison with float64 edges (numpy's log may round differently per CPU)
            q = np.searchsorted(edges, t_probe, side="right").astype(np.uint64)
            key += q * mix[4 + c]
    return valid, key, p, normal


def classes(valid, features, block_px):
    """Class index per pixel (H x W, int64, 0 .. n - 1) and the pixels in each class (n).

    Pixels of one block of ``block_px`` x ``block_px`` with equal ``features`` (an int64 hash per
    pixel, H x W, or one int64 plane per feature, F x H x W) share a class; pixels where ``valid``
    is False each have a class of their own.
    """
    h, w = valid.shape
    by = (np.arange(h) // block_px)[:, None]
    bx = (np.arange(w) // block_px)[None, :]
    with np.errstate(over="ignore"):  # the hash wraps around (int64), as intended
        key = by * _MIX[0] + bx * _MIX[1]
        planes = features[None] if features.ndim == 2 else features
        for c in range(planes.shape[0]):
            key = key + planes[c] * _MIX[2 + c]
    key = key.ravel()
    own = ~valid.ravel()
    # each invalid pixel a class of its own: even keys, the hashes made odd
    key = np.where(own, -2 * (1 + np.arange(key.size, dtype=np.int64)), key | 1)
    _, index, counts = np.unique(key, return_inverse=True, return_counts=True)
    return index.reshape(h, w), counts


@dataclasses.dataclass(frozen=True)
class ViewMoments:
    """Per class: ``sum`` of a detector's view factors, their ``centre`` (x, y, mm, about the
    class's plain centre) and the ``first`` and ``second`` moments of view^2, (x, y) and (x^2, xy,
    y^2), about that centre."""

    sum: np.ndarray
    centre: np.ndarray
    first: np.ndarray
    second: np.ndarray


class GeometryClasses:
    """The classes of a scene's pixels for one geometry and block size (cached by the integrator).

    Parameters
    ----------
    scene, sensor : the scene and its ``elo_beam`` sensor
    block_mm : float
        Side of the blocks (mm) that bound a class.
    key : hashable
        What they were made for (:func:`geometry_key` and the block), kept to compare.
    like : GeometryClasses, optional
        Classes of the same geometry, beam and film in another block size: their
        :func:`scan_features` and view factors are taken over (the scan is the costly part, 4-7 s
        at 1500^2; sorting into other blocks takes about a second).
    """

    def __init__(self, scene, sensor, block_mm, key, like=None):
        self.key = key
        size = sensor.film().crop_size()
        self.block_px = max(1, int(round(block_mm * int(size[0]) / float(sensor.field))))
        self.features = scan_features(scene, sensor) if like is None else like.features
        valid, features, self._points, normal = self.features
        self._valid = valid
        self.index, self.counts = classes(valid, features, self.block_px)
        self.flat = self.index.ravel()
        self._ranks = None
        self._views = (None, None) if like is None else like._views
        self._moments = {}  # per view factor plane (its buffer): its sums per class (_view_moments)
        self._dr_views = {}  # ... and the plane as a Dr.Jit array (_view_array)
        self._dr_pixels = None  # per pixel its class and place in it, as Dr.Jit arrays (_pixel_arrays)
        # each pixel's place in its class: its hit less the class's mean hit (x, y, mm); 0 in a
        # class of one pixel, and where the beam meets no scattering surface
        xy = np.where(valid.reshape(-1, 1), self._points[..., :2].reshape(-1, 2).astype(np.float64), 0.0)
        centre = np.stack([np.bincount(self.flat, weights=xy[:, a], minlength=self.counts.size)
                           for a in (0, 1)], axis=1) / self.counts[:, None]
        self._ox, self._oy = (np.ascontiguousarray(xy[:, a] - centre[self.flat, a]) for a in (0, 1))
        # the class's quantised normal (the grid point's, part of every class key), as a group number
        first = np.full(self.counts.size, -1, np.int64)
        first[self.flat[::-1]] = np.arange(self.flat.size - 1, -1, -1)
        _, group = np.unique(normal.ravel()[first], return_inverse=True)
        shared = np.bincount(group, weights=np.where(self.counts > 1, self.counts, 0))
        self._class_group = group
        self._tilted = shared >= MIN_TILT_PIXELS  # groups whose tilt is fitted
        self._reach = np.zeros(self._tilted.size)  # per group the farthest pixel from its class's centre (mm)
        np.maximum.at(self._reach, group[self.flat], np.hypot(self._ox, self._oy))

    def view_factors(self, centres):
        """Per detector centre (mm) the pixels' view factors of it (D x H x W, float64): the solid
        angle a small detector at the centre subtends from a level plane at the beam's hit, per unit
        area, max(cos, :data:`MIN_VIEW_COS`) / r^2; 1 where the beam meets no scattering surface
        (those pixels are classes of their own). Cached for the last centres."""
        key = tuple(tuple(round(float(x), 9) for x in c) for c in centres)
        if self._views[0] != key:
            out = np.ones((len(key),) + self._valid.shape)
            p = self._points.astype(np.float64)[self._valid]
            for d, c in enumerate(key):
                v = np.asarray(c) - p
                r2 = np.maximum(np.einsum("ij,ij->i", v, v), 1e-12)  # finite even at the centre itself
                out[d][self._valid] = np.maximum(v[:, 2] / np.sqrt(r2), MIN_VIEW_COS) / r2
            self._views = (key, out)
            self._moments, self._dr_views = {}, {}
        return self._views[1]

    def share(self, plane, view=None):
        """``plane`` (H x W, float32) replaced in place by the mean over each pixel's class; with
        ``view`` (H x W, a detector's :meth:`view_factors`) by its pixel's view factor times the
        class's ratio of plane to view factor (sum over sum), so that what a detector sees of a
        class varies across the block as its solid angle does (the detector's near side sees more
        from the same relief), and times 1 + theta . (x, y), (x, y) the pixel's place in its class
        (mm, about the class's centre weighted by the view factors, so that the tilt leaves the
        class's sum as it is): the tilt across the block that the classes of one quantised normal
        share (:meth:`tilts`), as the beam's incidence on a flank changes across the field."""
        self._apply(plane, self._tables(plane, view), view)

    def _tables(self, plane, view):
        """Per class what :meth:`share` writes, (a, b, c) of v (a + b x + c y) (float64; b and c
        None without a tilt, v = 1 without a view): numpy's passes, which let go of the GIL."""
        x = plane.reshape(-1)  # float32: bincount and the products below work in float64
        sums = np.bincount(self.flat, weights=x, minlength=self.counts.size)
        if view is None:
            return sums / self.counts, None, None
        v = view.reshape(-1)
        moments = self._view_moments(view)
        norms = moments.sum
        ratio = sums / np.where(norms != 0, norms, 1.0)
        theta = self.tilts(x, v, sums, moments)
        if theta is None:
            return ratio, None, None
        tx, ty = theta[self._class_group, 0], theta[self._class_group, 1]
        return ratio * (1.0 - tx * moments.centre[:, 0] - ty * moments.centre[:, 1]), ratio * tx, ratio * ty

    def _apply(self, plane, tables, view):
        """``plane`` = v (a + b x + c y) per pixel from its class's ``tables`` (:meth:`_tables`), in
        one Dr.Jit kernel over the pixels (float64 arithmetic on the float32 offsets and view
        factors): three gathers of small tables and a few products, where numpy made a pass over
        the pixels for each."""
        f64 = mi.Float64
        flat, ox, oy = self._pixel_arrays()
        a, b, c = tables
        out = dr.gather(f64, f64(a), flat)
        if b is not None:
            out = out + dr.gather(f64, f64(b), flat) * f64(ox) + dr.gather(f64, f64(c), flat) * f64(oy)
        if view is not None:
            out = out * f64(self._view_array(view))
        plane.reshape(-1)[...] = np.asarray(mi.Float(out))

    def _pixel_arrays(self):
        """Per pixel its class and its place in the class (x, y; float32), as Dr.Jit arrays (made once)."""
        if self._dr_pixels is None:
            self._dr_pixels = (mi.UInt32(self.flat.astype(np.uint32)), mi.Float(self._ox.astype(np.float32)),
                               mi.Float(self._oy.astype(np.float32)))
        return self._dr_pixels

    def _view_array(self, view):
        """A view factor plane as a Dr.Jit float32 array, kept as its moments are (:meth:`_view_moments`)."""
        key = self._view_key(view)
        if key not in self._dr_views:
            self._dr_views[key] = mi.Float(np.ascontiguousarray(view, np.float32).reshape(-1))
        return self._dr_views[key]

    def share_all(self, jobs):
        """:meth:`share` of each (plane, view) in ``jobs`` (planes that are not the same array):
        the classes' sums on threads (:func:`._threads.each_plane`: numpy lets go of the GIL in its
        passes over the pixels), then each plane's pixels in one Dr.Jit kernel on this thread; each
        plane's result is the same as alone (corrugated_chamber at 1500^2, a render's 8 shares:
        0.44 s on one thread, 0.25 s on two, 0.18 s with the pixels in Dr.Jit)."""
        jobs = list(jobs)
        for _, view in jobs:  # the views' moments once, before the threads read them
            if view is not None:
                self._view_moments(view)
        tables = [None] * len(jobs)

        def fill(i):
            tables[i] = self._tables(*jobs[i])

        each_plane(fill, range(len(jobs)))
        for (plane, view), t in zip(jobs, tables):
            self._apply(plane, t, view)

    def tilts(self, x, v, sums, moments):
        """The tilt theta (groups x 2, per mm) of :meth:`share` per quantised normal, or None where
        no normal has :data:`MIN_TILT_PIXELS` pixels in classes of two or more: the least-squares
        fit of x = v R (1 + theta . (x, y)) over the pixels of that normal's classes (x the plane,
        flat, float64; v the view factors; ``sums`` the classes' sums of x; R the class's ratio of
        those to the view factors'; ``moments`` :meth:`_view_moments` of v), scaled down where it
        would exceed :data:`MAX_TILT` at a pixel. With (x, y) about the view-weighted centre the
        ratio R is the class's value whatever theta is, so the fit is exact where the model is."""
        if not self._tilted.any():
            return None
        n, groups = self.counts.size, self._tilted.size
        r = np.where(moments.sum != 0, sums / np.where(moments.sum != 0, moments.sum, 1.0), 0.0)
        xv = x * v
        b = np.stack([np.bincount(self.flat, weights=xv * o, minlength=n) for o in (self._ox, self._oy)], axis=1)
        b -= moments.centre * np.bincount(self.flat, weights=xv, minlength=n)[:, None]  # sum of v x (x, y) per class
        b -= r[:, None] * moments.first  # ... less R v^2 (x, y): the sum of v (x - v R) (x, y)

        def by_group(w):
            return np.bincount(self._class_group, weights=w, minlength=groups)

        a11, a12, a22 = (by_group(r * r * moments.second[:, k]) for k in range(3))
        b1, b2 = by_group(r * b[:, 0]), by_group(r * b[:, 1])
        det = a11 * a22 - a12 * a12
        ok = self._tilted & (det > 1e-12 * np.maximum(a11 * a22, 1e-300))
        safe = np.where(ok, det, 1.0)
        theta = np.where(ok[:, None], np.stack([(a22 * b1 - a12 * b2) / safe, (a11 * b2 - a12 * b1) / safe], axis=1), 0.0)
        # |theta . (x, y)| <= |theta| times twice the group's farthest pixel from its class's centre
        theta *= np.minimum(1.0, MAX_TILT / np.maximum(2.0 * np.linalg.norm(theta, axis=1) * self._reach, 1e-300))[:, None]
        return theta

    def _view_moments(self, view):
        """Per class the sum of ``view``, its view-weighted centre (x, y) (about the plain centre)
        and the sums of view^2 (x, y) and view^2 (x^2, xy, y^2) about that centre ((x, y) the
        pixels' places in the class), kept per view plane (its buffer, shape and a sample of its values) until
        :meth:`view_factors` is called with other centres."""
        key = self._view_key(view)
        if key not in self._moments:
            n, v = self.counts.size, view.ravel().astype(np.float64)

            def sums(w):
                return np.bincount(self.flat, weights=w, minlength=n)

            total = sums(v)
            safe = np.where(total != 0, total, 1.0)
            centre = np.stack([sums(v * o) / safe for o in (self._ox, self._oy)], axis=1)
            dx, dy = (o - centre[self.flat, a] for a, o in enumerate((self._ox, self._oy)))
            v2 = v * v
            first = np.stack([sums(v2 * dx), sums(v2 * dy)], axis=1)
            second = np.stack([sums(v2 * dx * dx), sums(v2 * dx * dy), sums(v2 * dy * dy)], axis=1)
            self._moments[key] = ViewMoments(total, centre, first, second)
        return self._moments[key]

    @staticmethod
    def _view_key(view):
        return view.__array_interface__["data"][0], view.shape, float(view.ravel()[::4099].sum())

    def ranks(self):
        """Per pixel (flat, row-major) its class, its rank in the class (0 .. n - 1, in a fixed
        scrambled order) and its class's size n, as Dr.Jit UInt32 arrays (made once): where a
        pixel's paths lie in the point set its class spreads over all its samples
        (:func:`._strata.spread_point`). Scrambled, not row-major: the point set's neighbouring
        points sample neighbouring directions, and in row-major ranks a pixel's place in its class
        would decide which, so that within one render the pixels' values would run across the
        block with the directions they drew, and the tilt that :meth:`share` fits would follow
        them (corrugated_chamber 1500^2, `default`: total noise 0.32 -> 0.54 %)."""
        if self._ranks is not None:
            return self._ranks
        scramble = np.random.default_rng(RANK_SEED).permutation(self.flat.size)
        order = np.argsort((self.flat.astype(np.int64) << 32) | scramble)  # by class, then scrambled
        starts = np.cumsum(self.counts) - self.counts
        rank = np.empty(self.flat.size, np.int64)
        rank[order] = np.arange(self.flat.size) - starts[self.flat[order]]
        self._ranks = (self._pixel_arrays()[0],) + tuple(mi.UInt32(a.astype(np.uint32))
                                                        for a in (rank, self.counts[self.flat]))
        return self._ranks

    def pixels_per_class(self):
        """Per pixel the number of pixels its value now averages (H x W, float32)."""
        return self.counts[self.index].astype(np.float32)
