"""The far field of events >= 2: a cached wall response used as a control variate (issue 26).

Events >= 2 from a scan point p are the integral over the directions wo the electron leaves p in,

    N_{n,d}/N_0 = int g_BSE(p; wi, wo) F_{n,d}(p, wo) dwo,

where F_{n,d}(p, wo) is what an electron leaving p towards wo adds to detector d at event n (it
meets a wall, a shield, the object again, ... and is counted n - 1 events later). The integrator
estimates it by tracing continuation paths (one wo per path, sampled by g_BSE with the constant
weight S): noisy, because F varies a lot between the walls' parts (which of them see a detector).

Far from the object F changes slowly with p: the walls are hundreds of mm away, the field 80 mm
wide. This module tabulates once per scene geometry a fixed function

    L_{n,d}(node, bin) ~ F_{n,d}(node, wo in bin)

on a coarse grid of :data:`NODES` x :data:`NODES` nodes over the field and :data:`N_U` x
:data:`N_PHI` direction bins of the upper hemisphere (equal solid angle: cos(theta) x azimuth;
looked up bilinearly in both),
traced from the nodes with the integrator's own estimator of the 2nd event, the triangle
quadrature of Appendix A with one shadow ray per triangle (deterministic; averaged over
:data:`JITTER` fixed directions per bin; 0 below the horizon). The integrator then estimates the
2nd event as

    (1/K) sum_k S_k L(node(p), wo_k)   +   (1/m) sum_j S_j [F_j - L(node(p), wo_j)]

with K = s^2 cheap samples of g_BSE (stratified in s x s cells, no ray) and the m traced
continuation paths. Both terms are unbiased for any fixed L (a control variate whose mean is
estimated by its own, cheap samples), so the estimate is unbiased whatever the table holds: a
stale or coarse table costs variance, never bias. Near-field paths (the object scattering onto
itself, flanks that hide part of the hemisphere) are where F departs from L: they stay in the
traced term, per pixel.

The table holds the 2nd event only. Events >= 3 of a far path are traced as they are, without a
variate: one path's later events vary mostly with the directions after its first (which the
table cannot know), so a variate of them lowered their error by < 3 % on athene_flat, while
looking them up cost every cheap sample 16 gathers per channel and the table's build the tracing of
them (benchmarks/RESULTS.md, Far field: events 3 and 4). ``far_roulette`` = q traces them for a
fraction q of the far paths only (whole blocks of lanes, weight 1/q): unbiased, off in the presets
(measured not to pay). The table is keyed by the geometry it depends on (:func:`geometry_key`: every shape's bounds,
mesh vertices and materials, the beam, the events and which detectors collect on both faces) and
rebuilt when the key changes: moving a detector rebuilds it before the next render; re-renders,
the error estimate's halves and quality changes reuse it.
"""

import hashlib
import math

import drjit as dr
import mitsuba as mi
import numpy as np

#: Nodes per side of the grid over the field (looked up bilinearly). The table is rebuilt whenever
#: a detector moves, so its build is part of every point of a detector sweep. Measured on athene_flat
#: and shield_chamber, 128^2, `default` (error = the render's own e2 estimate, worst detector, two
#: seeds): 9 nodes and 2 directions per bin built in 0.45-0.58 s for 0.303 / 0.310 %; 7 and 1 in
#: 0.13-0.14 s for 0.309 / 0.317 %; 5 and 1 with 32 x 64 bins in 0.02 s for 0.386 % (athene_flat).
NODES = 7
#: Direction bins: cos(theta) rows x azimuth columns over the upper hemisphere.
N_U, N_PHI = 64, 128
#: Triangles per detector of the table's quadrature (one shadow ray each).
TABLE_TRIANGLES = 4
#: Directions traced per node and bin when the table is built (fixed offsets in the bin; with 1,
#: the bin's centre): 2 lowered the e2 error by 1 % for twice the build (see NODES).
JITTER = 1
#: On relief under the beam, a direction whose ray meets a surface within this distance (mm) is
#: near field: no control variate there (neither in its mean nor on the traced path), traced per pixel.
NEAR_MM = 60.0
#: Seed of the table's build (its events >= 3 are sampled).
BUILD_SEED = 0x26F4


def geometry_key(scene, sensor, traced, two_sided):
    """Everything the table depends on, as a hashable tuple (compared before every render).

    Parameters
    ----------
    scene : mi.Scene
    sensor : the ``elo_beam`` sensor (field, work distance, projection)
    traced : int
        The last event the table holds (2; with the option ``far_field_later``: every traced one).
    two_sided : list of bool
        Per detector, whether it collects on both faces.
    """
    digest = hashlib.sha1()
    for shape in scene.shapes():
        box = shape.bbox()
        digest.update(repr((shape.id(), shape.is_emitter(), list(box.min), list(box.max),
                            float(np.ravel(shape.surface_area())[0]))).encode())
        if shape.is_mesh():
            digest.update(np.ascontiguousarray(np.array(shape.vertex_positions_buffer())).tobytes())
        bsdf = shape.bsdf()
        for attr in ("material", "lobe_width", "lobe"):
            value = getattr(bsdf, attr, None)
            if value is not None:
                digest.update(repr(getattr(value, "describe", lambda v=value: np.ravel(v).tolist())()).encode())
    beam = (float(sensor.field), float(sensor.field_y), float(sensor.wd), str(getattr(sensor, "projection", "")))
    return (digest.hexdigest(), beam, int(traced), tuple(two_sided), NODES, N_U, N_PHI, JITTER)


def build_rays(scene, sensor):
    """Origins and directions of the table's build, lane = (node, bin, jitter), and the nodes' x, y.

    The nodes lie on the field's grid at the height of the highest point the beam meets there
    (plus 1 um), so that their rays start above the object.
    """
    g = np.linspace(-0.5, 0.5, NODES)
    nx = (g * float(sensor.field)).astype(np.float32)
    ny = (g * float(sensor.field_y)).astype(np.float32)
    xs, ys = np.meshgrid(nx, ny, indexing="xy")  # node = iy * NODES + ix
    probe = scene.ray_intersect(mi.Ray3f(mi.Point3f(mi.Float(xs.ravel()), mi.Float(ys.ravel()), 1e4),
                                         mi.Vector3f(0.0, 0.0, -1.0)))
    z = np.where(np.array(probe.is_valid()), np.array(probe.p.z), 0.0)
    z0 = float(np.max(z)) + 1e-3 if z.size else 1e-3
    n_bins = N_U * N_PHI
    lanes = NODES * NODES * n_bins * JITTER
    lane = np.arange(lanes)
    node, rest = lane // (n_bins * JITTER), lane % (n_bins * JITTER)
    b = rest // JITTER
    iu, ip = b // N_PHI, b % N_PHI
    j = rest % JITTER  # fixed offsets in the bin (no random numbers: the table is the same bit for bit
    # wherever its rays and quadrature round alike)
    u = (iu + (j + 0.5) / JITTER) / N_U
    phi = (ip + np.mod(0.5 + j * 0.6180339887498949, 1.0)) / N_PHI * 2.0 * np.pi - np.pi
    s = np.sqrt(np.maximum(0.0, 1.0 - u * u))
    d = mi.Vector3f(mi.Float((s * np.cos(phi)).astype(np.float32)), mi.Float((s * np.sin(phi)).astype(np.float32)),
                    mi.Float(u.astype(np.float32)))
    o = mi.Point3f(mi.Float(xs.ravel()[node]), mi.Float(ys.ravel()[node]), mi.Float(np.full(lanes, z0, np.float32)))
    return o, d, (nx, ny)


def reduce_table(responses):
    """The table from per-lane responses (one Dr.Jit Float per channel, lanes as :func:`build_rays`):
    the mean over the jittered directions, laid out [node, bin, channel] in one Float."""
    n_bins = N_U * N_PHI
    cols = [np.array(r, dtype=np.float64).reshape(NODES * NODES, n_bins, JITTER).mean(axis=2) for r in responses]
    return mi.Float(np.stack(cols, axis=-1).astype(np.float32).ravel())


class FarFieldTable:
    """A built table: ``values`` [node, bin, channel] (channel = detector x the events it holds: the 2nd),
    the grid's node coordinates and the key it was built for."""

    def __init__(self, key, values, nodes_xy, n_channels):
        self.key = key
        self.values = values
        self.n_channels = n_channels
        nx, ny = nodes_xy
        self._x0, self._y0 = float(nx[0]), float(ny[0])
        self._dx = float(nx[1] - nx[0]) if NODES > 1 else 1.0
        self._dy = float(ny[1] - ny[0]) if NODES > 1 else 1.0
        self.host = np.array(values).reshape(NODES * NODES, N_U * N_PHI, n_channels)

    def lookup(self, p, wo, active):
        """L per channel at ``p`` (world) for the world direction ``wo``: bilinear between the
        nodes and between the direction bins' centres (azimuth periodic), so that L is continuous
        in p and wo (a last-bit change of a direction moves it by as little); 0 below the horizon."""
        up = active & (wo.z > 0)
        fx = dr.clip((p.x - self._x0) / self._dx, 0.0, NODES - 1.0)
        fy = dr.clip((p.y - self._y0) / self._dy, 0.0, NODES - 1.0)
        ix = dr.minimum(dr.floor(fx), NODES - 2.0)
        iy = dr.minimum(dr.floor(fy), NODES - 2.0)
        tx, ty = fx - ix, fy - iy
        fu = dr.clip(wo.z * N_U - 0.5, 0.0, N_U - 1.0)
        iu = dr.minimum(dr.floor(fu), N_U - 2.0)
        tu = fu - iu
        fp = (dr.atan2(wo.y, wo.x) + math.pi) * (N_PHI / (2.0 * math.pi)) - 0.5  # [-0.5, N_PHI - 0.5]
        ip = dr.floor(fp)
        tp = fp - ip
        ip0 = mi.UInt32(dr.select(ip < 0, ip + N_PHI, ip))
        ip1 = mi.UInt32(dr.select(ip + 1 >= N_PHI, ip + 1 - N_PHI, ip + 1))
        n0 = mi.UInt32(iy) * NODES + mi.UInt32(ix)
        corners = []
        for node, wn in ((n0, (1 - tx) * (1 - ty)), (n0 + 1, tx * (1 - ty)), (n0 + NODES, (1 - tx) * ty),
                         (n0 + NODES + 1, tx * ty)):
            for u_i, wu in ((mi.UInt32(iu), 1 - tu), (mi.UInt32(iu) + 1, tu)):
                for p_i, wp in ((ip0, 1 - tp), (ip1, tp)):
                    corners.append(((node * (N_U * N_PHI) + u_i * N_PHI + p_i) * self.n_channels, wn * wu * wp))
        out = []
        for c in range(self.n_channels):
            acc = mi.Float(0.0)
            for base, w in corners:
                acc = dr.fma(w, dr.gather(mi.Float, self.values, base + c, up), acc)
            out.append(acc)
        return out
