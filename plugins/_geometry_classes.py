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
  near distance): the distance to the first surface, quantised in steps of 1/:data:`STEPS_PER_E`
  of a natural-log unit (12.5 %);
* the normal, quantised in steps of sin(:data:`NORMAL_DEG`);
* the block of :math:`b \\times b` pixels (``block_mm``) holding the pixel.

A class is the pixels of one block with equal quantised normal and probe distances; the integrator
replaces each pixel's events >= 2 by the mean over its class (``bounce_share``). Where the relief
repeats (the corrugated sheet: every point of a flank line along its ridge), a class holds the
points of a line and the average is unbiased but for what varies within the block (the far field,
the beam's incidence: measured below the noise at 4 mm on corrugated_chamber, benchmarks/
RESULTS.md, "Shared by geometry"); where no two points match, every pixel keeps its own value
(no gain, no bias). Quantisation can still join points whose probes agree but whose events >= 2
do not (e.g. a difference no probe direction sees): the bias that is left is measured, never
seen by the render's own error estimate (both halves share the classes).
"""

import hashlib
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ._far_field import NEAR_MM

#: Probe directions per pixel (a power of two: the Hammersley set). 16 matched 32 on
#: corrugated_chamber at 512^2 (bias below the measurement's noise of ~0.5 % of e2 either way).
PROBES = 16
#: Probe distances are quantised in steps of 1/STEPS_PER_E in log(distance) (12.5 %).
STEPS_PER_E = 8
#: Normals are quantised in steps of sin(NORMAL_DEG) along x and y.
NORMAL_DEG = 1.0
#: Shortest probe distance told apart (mm): closer hits count as this distance.
MIN_DISTANCE_MM = 1e-3
#: Odd 64-bit multipliers of the class key's hash (fixed: classes are reproducible).
_MIX = np.random.default_rng(0x6E0C).integers(1, 1 << 62, size=PROBES + 4, dtype=np.int64) * 2 + 1


def probe_directions(count=PROBES):
    """The fixed probe directions in the local frame (count, 3): cosine-weighted Hammersley."""
    bits = int(round(math.log2(count)))
    k = np.arange(count)
    u = (k + 0.5) / count
    v = np.array([int(format(int(x), f"0{bits}b")[::-1], 2) for x in k]) / count + 0.5 / count
    r = np.sqrt(v)
    phi = 2.0 * np.pi * u
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1.0 - v))], axis=1)


def geometry_key(scene, sensor):
    """What the classes depend on: every shape's bounds and mesh vertices, the beam and the film."""
    digest = hashlib.sha1()
    for shape in scene.shapes():
        box = shape.bbox()
        digest.update(repr((shape.id(), list(box.min), list(box.max))).encode())
        if shape.is_mesh():
            digest.update(np.ascontiguousarray(np.array(shape.vertex_positions_buffer())).tobytes())
    size = sensor.film().crop_size()
    return (digest.hexdigest(), float(sensor.field), float(sensor.field_y), float(sensor.wd),
            str(getattr(sensor, "projection", "")), tuple(sensor.aim_offset_mm), int(size[0]), int(size[1]))


def scan_features(scene, sensor):
    """Per pixel (H x W): whether the beam meets a scattering surface there, the quantised normal
    (2 ints) and the quantised probe distances (:data:`PROBES` ints), as int64 arrays."""
    size = sensor.film().crop_size()
    w, h = int(size[0]), int(size[1])
    idx = dr.arange(mi.UInt32, w * h)
    film = mi.Point2f((mi.Float(idx % w) + 0.5) / w, (mi.Float(idx // w) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    valid = si.is_valid() & ~si.shape.is_emitter()
    step = math.sin(math.radians(NORMAL_DEG))
    n = si.sh_frame.n
    keys = [mi.Int32(dr.round(n.x / step)), mi.Int32(dr.round(n.y / step))]
    for d in probe_directions():
        probe = si.spawn_ray(si.to_world(mi.Vector3f(*[float(c) for c in d])))
        probe.maxt = NEAR_MM
        hit = scene.ray_intersect_preliminary(probe, valid)
        t = dr.select(hit.is_valid(), dr.maximum(hit.t, MIN_DISTANCE_MM), NEAR_MM)
        keys.append(mi.Int32(dr.floor(dr.log(t) * STEPS_PER_E)))
    dr.eval(valid, keys)
    valid_np = np.array(valid, dtype=bool).reshape(h, w)
    return valid_np, np.stack([np.array(k, dtype=np.int64).reshape(h, w) for k in keys])


def classes(valid, features, block_px):
    """Class index per pixel (H x W, int64, 0 .. n - 1) and the pixels in each class (n).

    Pixels of one block of ``block_px`` x ``block_px`` with equal ``features`` share a class;
    pixels where ``valid`` is False each have a class of their own.
    """
    h, w = valid.shape
    by = (np.arange(h) // block_px)[:, None]
    bx = (np.arange(w) // block_px)[None, :]
    with np.errstate(over="ignore"):  # the hash wraps around (int64), as intended
        key = by * _MIX[0] + bx * _MIX[1]
        for c in range(features.shape[0]):
            key = key + features[c] * _MIX[2 + c]
    key = key.ravel()
    own = ~valid.ravel()
    # each invalid pixel a class of its own: even keys, the hashes made odd
    key = np.where(own, -2 * (1 + np.arange(key.size, dtype=np.int64)), key | 1)
    _, index, counts = np.unique(key, return_inverse=True, return_counts=True)
    return index.reshape(h, w), counts


class GeometryClasses:
    """The classes of a scene's pixels for one geometry and block size (cached by the integrator).

    Parameters
    ----------
    scene, sensor : the scene and its ``elo_beam`` sensor
    block_mm : float
        Side of the blocks (mm) that bound a class.
    """

    def __init__(self, scene, sensor, block_mm):
        self.key = (geometry_key(scene, sensor), float(block_mm))
        size = sensor.film().crop_size()
        self.block_px = max(1, int(round(block_mm * int(size[0]) / float(sensor.field))))
        valid, features = scan_features(scene, sensor)
        self.index, self.counts = classes(valid, features, self.block_px)
        self.flat = self.index.ravel()

    def share(self, plane):
        """``plane`` (H x W, float32) replaced in place by the mean over each pixel's class."""
        sums = np.bincount(self.flat, weights=plane.ravel(), minlength=self.counts.size)
        plane[...] = (sums / self.counts)[self.index]

    def pixels_per_class(self):
        """Per pixel the number of pixels its value now averages (H x W, float32)."""
        return self.counts[self.index].astype(np.float32)
