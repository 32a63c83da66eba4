"""The 1st scattering event of a surface facet onto disc detectors, vectorised over pixels.

N_1,d / N_0 = int_disc g_BSE(n_S, p_E, d) |cos psi| / r^2 dA     (Eq. 5 written over the disc)

with g_BSE of Eq. 13 (exact lobe normalisation C(theta), :mod:`elo_mitsuba.physics.scattering`),
for every pixel's landing point, beam direction and facet normal at once. This is the model that
the model-based gradient (:mod:`.model_gradient`) and the detector calibration
(:mod:`.calibration`) invert: what the renderer computes for the 1st event of a pixel that sees
one flat facet (no shadowing by neighbours, no beam blur, no later events).

The disc integral uses a product rule: Gauss-Legendre in s = (r/R)^2 (area-uniform) and the
midpoint rule in the azimuth (spectrally accurate for a periodic integrand). The integrand is
smooth over a detector that subtends a few degrees, so few nodes suffice. Measured against the
64 x 256-node reference of :func:`~elo_mitsuba.analysis.first_event.disc_integral` on ATHENE's
discs (random facets, slopes up to 0.8; tests/test_model_gradient.py): (1, 4) nodes 2e-5
relative, (2, 6) 5e-7 (float32 round-off). :data:`DEFAULT_NODES` = (1, 4): its error is far
below the images' noise, and a 1500 x 1500 model gradient costs 2.8x less than with (2, 6).

Both faces of a disc collect (the integrator's default), so |cos psi| is used: a surface point in
front of or behind the plate is counted alike.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Mapping

import numpy as np

from ..constants import LOBE_WIDTH_DEG
from ..physics import get_material
from ..physics.scattering import lobe_weight_table
from .jit_arrays import floats

#: Nodes of the disc rule (in s = (r/R)^2, in the azimuth).
DEFAULT_NODES = (1, 4)
#: Largest cosine of incidence the model uses (see FacetModel._setup).
COS_MAX = 1.0 - 1e-6


@lru_cache(maxsize=16)
def unit_disc_rule(n_s: int, n_phi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes (u, v) on the unit disc and weights summing to pi (area of the unit disc)."""
    x, w = np.polynomial.legendre.leggauss(int(n_s))
    s = 0.5 * (x + 1.0)
    ws = 0.5 * w
    r = np.sqrt(s)
    phi = (np.arange(int(n_phi)) + 0.5) * 2.0 * np.pi / int(n_phi)
    rr, pp = np.meshgrid(r, phi, indexing="ij")
    # dA = r dr dphi = 1/2 ds dphi
    weights = np.broadcast_to(ws[:, None] * 0.5 * (2.0 * np.pi / int(n_phi)), rr.shape)
    return (rr * np.cos(pp)).ravel(), (rr * np.sin(pp)).ravel(), np.array(weights).ravel()


def check_nodes(nodes) -> tuple[int, int]:
    """``nodes`` as the rule's (radial, angular) node counts, each a whole number in [1, 64].

    >>> check_nodes((2, 6))
    (2, 6)
    >>> check_nodes(0)
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: nodes=0; must be two whole numbers (radial, angular), e.g. (1, 4)
    """
    from ..arguments import shown, whole_number
    from ..errors import EloInputError

    try:
        pair = tuple(nodes)
    except TypeError:
        pair = ()
    if len(pair) != 2:
        raise EloInputError(f"nodes={shown(nodes)}; must be two whole numbers (radial, angular), e.g. {DEFAULT_NODES}")
    return whole_number("nodes (radial)", pair[0], 1, 64), whole_number("nodes (angular)", pair[1], 1, 64)


def disc_nodes_world(disc, nodes=DEFAULT_NODES) -> tuple[np.ndarray, np.ndarray]:
    """World positions (J, 3) and area weights (J,) of the rule's nodes on one disc."""
    n = np.asarray(disc.normal, float)
    a = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.99 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    u, v, w = unit_disc_rule(*nodes)
    r = disc.radius
    pts = np.asarray(disc.center, float) + r * (u[:, None] * a + v[:, None] * b)
    return pts, w * r * r


@lru_cache(maxsize=16)
def _lobe_table(material: str, lobe_width_deg: float, size: int) -> np.ndarray:
    """W(theta) of the ``elo_bse`` plugin's table, by material (computing C(theta) costs 50 ms)."""
    desc = material[material.index("(") + 1:-1] if "(" in material else material
    _, table = lobe_weight_table(get_material(desc), lobe_width_deg, n=size)
    return table.astype(np.float32)


class FacetModel:
    """1st-event signals of all detectors, in Dr.Jit, for any landing points, beams and normals.

    g_BSE is evaluated by the renderer's own code (``world_eval`` of the ``elo_bse`` plugin, from
    the same W(theta) table), the disc integral by the rule of :func:`unit_disc_rule`. The nodes
    are data (gathered in a symbolic loop over the rule), not constants of the kernel: one small
    kernel serves every detector geometry, resolution and start value (the calibration moves the
    discs at every step without recompiling; Dr.Jit caches it on disk between runs).

    Parameters
    ----------
    detectors : mapping of str to Disc
        The detectors, in the order of the outputs.
    material : str or Material
        Surface material (eta0, eta(theta) of Eqs. 10-12).
    nodes : (int, int)
        Disc rule (see :func:`unit_disc_rule`).
    lobe_width_deg : float
        Lobe width of Eq. 13.
    """

    def __init__(self, detectors: Mapping, material, *, nodes=DEFAULT_NODES, lobe_width_deg: float = LOBE_WIDTH_DEG):
        from ..runtime import ensure_variant

        self.mi = mi = ensure_variant()
        import drjit as dr

        from ..plugins.bsdf_elo_bse import TABLE_SIZE

        self.dr = dr
        nodes = check_nodes(nodes)
        self.material = get_material(material)
        self.names = tuple(detectors)
        self.lobe_width_deg = float(lobe_width_deg)
        pos, wts, nrm = [], [], []
        for name in self.names:
            disc = detectors[name]
            pts, w = disc_nodes_world(disc, nodes)
            pos.append(pts)
            wts.append(w)
            nrm.append(np.broadcast_to(disc.normal, pts.shape))
        self.n_nodes = len(wts[0])
        # layout [detector][node]: index = k * n_nodes + j
        self._pos = [mi.Float(np.concatenate(pos)[:, c].astype(np.float32)) for c in range(3)]
        self._nrm = [mi.Float(np.concatenate(nrm)[:, c].astype(np.float32)) for c in range(3)]
        self._w = mi.Float(np.concatenate(wts).astype(np.float32))
        self._table = mi.Float(_lobe_table(self.material.describe(), self.lobe_width_deg, TABLE_SIZE))
        self._table_size = TABLE_SIZE
        self._diffuse = dr.opaque(mi.Float, self.material.eta0 / np.pi)
        self._inv_width = dr.opaque(mi.Float, 1.0 / self.lobe_width_deg)

    def _setup(self, beam_dirs, n):
        from ..plugins.bsdf_elo_bse import table_lookup

        dr = self.dr
        cos_t = -dr.dot(n, beam_dirs)
        # a non-finite normal must not reach the table's gather index (out of bounds); its g is 0
        cos_t = dr.select(dr.isfinite(cos_t), cos_t, 0.0)
        # below 1: acos has an infinite derivative at 1 (a facet square to the beam), and the
        # inversion differentiates this; the angle changes by < 0.1 deg, W(theta) by < 1e-7
        theta_deg = dr.acos(dr.clip(cos_t, 0.0, COS_MAX)) * (180.0 / dr.pi)
        weight = table_lookup(self._table, theta_deg, self._table_size)
        mirror = n * (2.0 * cos_t) + beam_dirs
        return (self._diffuse, weight, theta_deg * self._inv_width, n, mirror, cos_t > 0)

    def node_positions(self) -> np.ndarray:
        """World positions of the rule's nodes, (K, J, 3): detector k, node j."""
        pos = np.stack([np.asarray(a, np.float64) for a in self._pos], axis=-1)
        return pos.reshape(len(self.names), self.n_nodes, 3)

    def signals(self, points, beam_dirs, normals, visible=None) -> list:
        """N_1,d/N_0 per normal and detector: ``out[i][k]`` (Float) for the i-th of ``normals``
        (a list of unit Vector3f) at the landing ``points`` (Point3f) of beams ``beam_dirs``
        (Vector3f, directions of travel). Several normals share the geometry of each node.
        ``visible`` (optional, per detector a Bool of J x width, node-major) keeps each node's
        contribution where it is True (False where the surface hides that node from the landing
        point)."""
        from ..plugins.bsdf_elo_bse import world_eval

        dr, mi = self.dr, self.mi
        setups = [self._setup(beam_dirs, n) for n in normals]
        n_det, n_nodes = len(self.names), self.n_nodes
        width = dr.width(points)
        lane = dr.arange(mi.UInt32, width)
        acc0 = tuple(dr.zeros(mi.Float, width) for _ in range(len(normals) * n_det))

        def cond(j, *acc):
            return j < n_nodes

        def body(j, *acc):
            acc = list(acc)
            for k in range(n_det):
                idx = j + k * n_nodes
                q = mi.Point3f(*[dr.gather(mi.Float, a, idx) for a in self._pos])
                nd = mi.Vector3f(*[dr.gather(mi.Float, a, idx) for a in self._nrm])
                w = dr.gather(mi.Float, self._w, idx)
                v = q - points
                inv_r2 = dr.rcp(dr.squared_norm(v))
                d = v * dr.sqrt(inv_r2)
                solid = dr.abs(dr.dot(d, nd)) * w * inv_r2  # |cos psi| dA / r^2
                if visible is not None:
                    solid = dr.select(dr.gather(mi.Bool, visible[k], j * width + lane), solid, 0.0)
                for i, setup in enumerate(setups):
                    acc[i * n_det + k] = dr.fma(world_eval(setup, d), solid, acc[i * n_det + k])
            return (j + 1, *acc)

        j, *acc = dr.while_loop((mi.UInt32(0), *acc0), cond, body, label="elo_facet_model")
        return [acc[i * n_det:(i + 1) * n_det] for i in range(len(normals))]


def normals_from_gradient(dzdx, dzdy) -> np.ndarray:
    """Unit normals n_S = [-dZ/dx, -dZ/dy, 1]/|.| (Eq. 16), shape (..., 3)."""
    dzdx = np.asarray(dzdx, float)
    n = np.stack([-dzdx, -np.asarray(dzdy, float), np.ones_like(dzdx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def to_vector(mi, a):
    """(N, 3) numpy -> Vector3f."""
    a = np.asarray(a, np.float32).reshape(-1, 3)
    return mi.Vector3f(*[floats(mi, a[:, c]) for c in range(3)])


def model_images(geometry, dzdx=None, dzdy=None, heights=None, *, nodes=DEFAULT_NODES) -> dict[str, np.ndarray]:
    """1st-event images of every detector of ``geometry`` for a gradient field (a flat plate when
    ``dzdx``/``dzdy`` are None), each (H, W) float64: the forward model the analysis inverts."""
    shape = geometry.shape
    points, dirs = geometry.beam(heights)
    zeros = np.zeros(shape)
    normals = normals_from_gradient(zeros if dzdx is None else dzdx, zeros if dzdy is None else dzdy)
    model = FacetModel(geometry.detectors, geometry.material, nodes=nodes)
    mi = model.mi
    sig = model.signals(mi.Point3f(to_vector(mi, points)), to_vector(mi, dirs), [to_vector(mi, normals)])[0]
    model.dr.eval(sig)
    return {name: np.asarray(s, dtype=np.float64).reshape(shape) for name, s in zip(model.names, sig)}
