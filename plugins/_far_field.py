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

from ._shapes import digest_geometry

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


def geometry_key(scene, sensor, traced, two_sided, keys):
    """Everything the table depends on, as a hashable tuple (compared before every render).

    Parameters
    ----------
    scene : mi.Scene
    sensor : the ``elo_beam`` sensor (field, work distance, projection)
    traced : int
        The last event the table holds (2; with the option ``far_field_later``: every traced one).
    two_sided : list of bool
        Per detector, whether it collects on both faces.
    keys : GeometryKey
        Where the scene's shapes are (:class:`~._shapes.GeometryKey`, called on ``scene``).
    """
    digest = hashlib.sha1()
    for shape in scene.shapes():
        digest_geometry(digest, shape, keys)
        digest.update(repr((shape.is_emitter(), float(np.ravel(shape.surface_area())[0]))).encode())
    digest.update(repr(scattering_key(scene)).encode())
    beam = (float(sensor.field), float(sensor.field_y), float(sensor.wd), str(getattr(sensor, "projection", "")))
    return (digest.hexdigest(), beam, int(traced), tuple(two_sided), NODES, N_U, N_PHI, JITTER)


def scattering_key(scene) -> tuple:
    """Per shape what its BSDF scatters by (an ``elo_bse``'s material, lobe width and lobe; empty
    for others): the part of the keys of what depends on the scattering law."""
    out = []
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        values = [getattr(bsdf, attr, None) for attr in ("material", "lobe_width", "lobe")]
        out.append(tuple(repr(getattr(v, "describe", lambda v=v: np.ravel(v).tolist())()) for v in values
                         if v is not None))
    return tuple(out)


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
        fu = dr.clip(wo.z * N_U - 0.5, 0.0, N_U - 1.0)
        iu = dr.minimum(dr.floor(fu), N_U - 2.0)
        tu = fu - iu
        fp = (dr.atan2(wo.y, wo.x) + math.pi) * (N_PHI / (2.0 * math.pi)) - 0.5  # [-0.5, N_PHI - 0.5]
        ip = dr.floor(fp)
        tp = fp - ip
        ip0 = mi.UInt32(dr.select(ip < 0, ip + N_PHI, ip))
        ip1 = mi.UInt32(dr.select(ip + 1 >= N_PHI, ip + 1 - N_PHI, ip + 1))
        corners = []
        for node, wn in self.node_corners(p):
            for u_i, wu in ((mi.UInt32(iu), 1 - tu), (mi.UInt32(iu) + 1, tu)):
                for p_i, wp in ((ip0, 1 - tp), (ip1, tp)):
                    corners.append(((node * (N_U * N_PHI) + u_i * N_PHI + p_i) * self.n_channels, wn * wu * wp))
        return weighted_gathers(self.values, corners, self.n_channels, up)

    def node_corners(self, p):
        """The four nodes around ``p`` (world; clamped to the grid) and their bilinear weights."""
        fx = dr.clip((p.x - self._x0) / self._dx, 0.0, NODES - 1.0)
        fy = dr.clip((p.y - self._y0) / self._dy, 0.0, NODES - 1.0)
        ix = dr.minimum(dr.floor(fx), NODES - 2.0)
        iy = dr.minimum(dr.floor(fy), NODES - 2.0)
        tx, ty = fx - ix, fy - iy
        n0 = mi.UInt32(iy) * NODES + mi.UInt32(ix)
        return ((n0, (1 - tx) * (1 - ty)), (n0 + 1, tx * (1 - ty)), (n0 + NODES, (1 - tx) * ty),
                (n0 + NODES + 1, tx * ty))


def weighted_gathers(values, corners, n_channels, active):
    """Per channel, the sum over ``corners`` ((base index, weight)) of weight x values[base + channel]."""
    out = []
    for c in range(n_channels):
        acc = mi.Float(0.0)
        for base, w in corners:
            acc = dr.fma(w, dr.gather(mi.Float, values, base + c, active), acc)
        out.append(acc)
    return out


# ---- the variate's mean, tabulated (option ``far_table``) --------------------------------------
#: Polar step (deg) of the normal nodes of the tabulated mean on relief (from world +z); a scene
#: whose beam meets one plane gets a table for that plane's normal alone. Measured on melt_chamber
#: against 32 x 1024 g_BSE samples at 200 beam hits (z RMS of the difference, worst detector):
#: 5 deg 1.17, 10 deg 1.41 (mean +0.06 % of M against +0.04 %).
MEAN_DTHETA_DEG = 5.0
#: Azimuth nodes of the tabulated mean's normals on relief: 12 and 24 gave the same agreement
#: there (z RMS 1.18 and 1.17) and the build 0.28 against 0.45 s.
MEAN_N_PHI = 12
#: A beam hit whose normal lies within this angle (rad) of a planar scene's normal uses its table.
PLANE_TOL = 1e-3


def bin_directions():
    """The centres of the table's direction bins (world, lane = iu * N_PHI + ip) and each bin's
    solid angle (equal: cos(theta) x azimuth)."""
    iu, ip = np.divmod(np.arange(N_U * N_PHI), N_PHI)
    u = (iu + 0.5) / N_U
    phi = (ip + 0.5) / N_PHI * 2.0 * np.pi - np.pi
    s = np.sqrt(1.0 - u * u)
    return np.stack([s * np.cos(phi), s * np.sin(phi), u], axis=1), 2.0 * np.pi / (N_U * N_PHI)


class MeanTable:
    """The control variate's mean M(p, n) = int g_BSE(n; wi(p), wo) L(p, wo) dwo per channel,
    tabulated on the far-field table's nodes x a grid of normals for ONE ``elo_bse`` (``bsdf_key``).

    Beam hits on another BSDF, or with a normal outside the grid, are not ``covered``: they get
    neither the mean nor the variate on their traced paths (unbiased, no variance reduction)."""

    def __init__(self, key, values, far, pole, n_theta, n_phi, dtheta, bsdf_key):
        self.key = key
        self.values = values
        self.n_channels = far.n_channels
        self._far = far
        self.frame = mi.Frame3f(mi.Vector3f(*[float(c) for c in pole]))
        self.pole = tuple(float(c) for c in pole)
        self.n_theta, self.n_phi, self.dtheta = int(n_theta), int(n_phi), float(dtheta)
        self.theta_max = (self.n_theta - 1) * self.dtheta if self.n_theta > 1 else PLANE_TOL
        self.bsdf_key = dr.opaque(mi.UInt32, bsdf_key)

    def lookup(self, p, n, bsdf_key, active):
        """(M per channel, covered): bilinear in the node grid and in (theta, phi) of the normal
        about the pole (azimuth periodic); 0 where not covered."""
        local = self.frame.to_local(n)
        # atan2, not acos: well conditioned at the pole, where a planar scene's normals lie
        theta = dr.atan2(dr.sqrt(dr.fma(local.x, local.x, local.y * local.y)), local.z)
        covered = active & (bsdf_key == self.bsdf_key) & (theta <= self.theta_max)
        if self.n_theta > 1:
            ft = dr.clip(theta / self.dtheta, 0.0, self.n_theta - 1.0)
            it = dr.minimum(dr.floor(ft), self.n_theta - 2.0)
            tt = ft - it
            fp = (dr.atan2(local.y, local.x) + math.pi) * (self.n_phi / (2.0 * math.pi))  # node j at -pi + j 2pi/n
            ip = dr.minimum(dr.floor(fp), self.n_phi - 1.0)
            tp = fp - ip
            ip0 = mi.UInt32(ip)
            ip1 = mi.UInt32(dr.select(ip + 1 >= self.n_phi, 0.0, ip + 1))
            normal = [(mi.UInt32(it) * self.n_phi + ip0, (1 - tt) * (1 - tp)), (mi.UInt32(it) * self.n_phi + ip1, (1 - tt) * tp),
                      ((mi.UInt32(it) + 1) * self.n_phi + ip0, tt * (1 - tp)), ((mi.UInt32(it) + 1) * self.n_phi + ip1, tt * tp)]
        else:
            normal = [(mi.UInt32(0), mi.Float(1.0))]
        per_node = self.n_theta * self.n_phi
        corners = [((node * per_node + j) * self.n_channels, wn * wj)
                   for node, wn in self._far.node_corners(p) for j, wj in normal]
        return weighted_gathers(self.values, corners, self.n_channels, covered), covered


def mean_grid(normals):
    """(pole, n_theta, n_phi, dtheta in rad) for the beam hits' ``normals`` (k x 3, world): one
    node at their normal when they all lie within :data:`PLANE_TOL` of it, else a grid about +z
    from 0 to two steps beyond their largest tilt (at most 90 deg)."""
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    mean = normals.mean(axis=0) if len(normals) else np.array([0.0, 0.0, 1.0])
    mean = mean / max(np.linalg.norm(mean), 1e-30)
    if len(normals) == 0 or np.all(normals @ mean >= math.cos(PLANE_TOL)):
        return tuple(mean), 1, 1, 0.0
    step = math.radians(MEAN_DTHETA_DEG)
    tilt = float(np.max(np.arccos(np.clip(normals[:, 2], -1.0, 1.0))))
    n_theta = min(int(math.ceil(tilt / step)) + 2, int(round(90.0 / MEAN_DTHETA_DEG))) + 1
    return (0.0, 0.0, 1.0), n_theta, MEAN_N_PHI, step


def build_mean(far, bsdf, bsdf_key, sensor, normals, key):
    """The :class:`MeanTable` of ``far`` for ``bsdf`` at the beam hits' ``normals``: at each node,
    the midpoint rule over the table's direction bins of g_BSE(n; wi(node), wo) x L(node, wo).
    Converged: 4 x 4 points per bin (L bilinear between them) changed the mean at 64 beam hits on
    the corrugated sheet's 45 deg flanks by < 0.02 %, though a flank's tangent plane cuts bins
    where g_BSE drops to 0."""
    from .bsdf_elo_bse import normal_setup, world_eval

    pole, n_theta, n_phi, dtheta = mean_grid(normals)
    frame = mi.Frame3f(mi.Vector3f(*[float(c) for c in pole]))  # the lookup's frame: the same axes
    it, ip = np.divmod(np.arange(n_theta * n_phi), n_phi)
    theta, phi = it * dtheta, ip * (2.0 * np.pi / n_phi) - np.pi
    local = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    basis = np.array([np.array(a, dtype=np.float64).ravel() for a in (frame.s, frame.t, frame.n)])  # rows: axes
    nodes_n = local @ basis
    wo, d_omega = bin_directions()
    n_norm, n_bins = len(nodes_n), len(wo)
    j, b = np.divmod(np.arange(n_norm * n_bins), n_bins)
    n_dr = _vector(nodes_n[j])
    wo_dr = _vector(wo[b])
    gx = np.linspace(-0.5, 0.5, NODES)
    xs, ys = np.meshgrid(gx * float(sensor.field), gx * float(sensor.field_y), indexing="xy")
    orthographic = getattr(sensor, "projection", "perspective") == "orthographic"
    values = np.zeros((NODES * NODES, n_norm, far.n_channels))
    for m, (x, y) in enumerate(zip(xs.ravel(), ys.ravel())):
        wi = np.array([0.0, 0.0, 1.0]) if orthographic else np.array([-x, -y, float(sensor.wd)])
        wi = wi / np.linalg.norm(wi)
        # opaque: one kernel for every node (a literal direction would compile one per node)
        wi_dr = mi.Vector3f(*[dr.opaque(mi.Float, float(c)) for c in wi])
        g = np.array(world_eval(normal_setup(bsdf, n_dr, wi_dr), wo_dr)).reshape(n_norm, n_bins)
        values[m] = (g @ far.host[m]) * d_omega  # float32 (BLAS): sums of 8192 terms, ~1e-6 relative
    return MeanTable(key, mi.Float(values.astype(np.float32).ravel()), far, pole, n_theta, n_phi, dtheta, bsdf_key)


def _vector(a):
    return mi.Vector3f(*[mi.Float(np.ascontiguousarray(a[:, c], dtype=np.float32)) for c in range(3)])


def near_share(scene, sensor, directions=16):
    """The share of the 2nd event's electrons (weighted by g_BSE's sampling weight S) that meet a
    surface within :data:`NEAR_MM` of where the beam hit, over the beam probe's grid
    (:func:`._relief.beam_probe`): what the far field's variate cannot help with. 0 when the beam
    meets nothing that scatters. Deterministic (a fixed sampler seed)."""
    from ._relief import beam_probe

    si = beam_probe(scene, sensor)
    alive = si.is_valid() & ~si.shape.is_emitter()
    n = dr.width(alive)
    idx = dr.arange(mi.UInt32, n * directions)
    lane = idx // directions
    si = dr.gather(type(si), si, lane)
    alive = dr.gather(mi.Bool, alive, lane)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(BUILD_SEED, n * directions)
    bsdf = si.bsdf()
    bs, w = bsdf.sample(mi.BSDFContext(), si, sampler.next_1d(alive), sampler.next_2d(alive), alive)
    weight = dr.select(alive, w[0], 0.0)
    ray = si.spawn_ray(si.to_world(bs.wo))
    ray.maxt = NEAR_MM
    near = scene.ray_test(ray, alive & (weight > 0))
    total = float(dr.sum(weight)[0]) if dr.width(weight) else 0.0
    return float(dr.sum(dr.select(near, weight, 0.0))[0]) / total if total > 0 else 0.0
