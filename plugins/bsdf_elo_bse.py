"""BSDF ``elo_bse``: the BSE scattering function g_BSE of Eq. 13 (Renner et al. 2023).

``eval`` *is* g_BSE, a probability per steradian with the cosine of alpha inside, so a path
traced from the gun accumulates N_d/N_0. Direction convention (local frame, normal = +z):
``si.wi`` points back to where the electron came from (-p_E), ``wo`` where it goes. One-sided:
zero when either direction is at or below the surface.

    g_BSE = eta0/pi cos(alpha) + W(theta) max(cos beta, 0)^k,
    W(theta) = (eta(theta) - eta0)/C(theta) (k+1)/(2 pi),  k = theta / lobe_width,

with eta by Eqs. 10/12 and C(theta) computed from its definition (docs/paper-notes.md §1); W is
tabulated once per material in :func:`elo_mitsuba.physics.scattering.lobe_weight_table`.

Sampling: with S(theta) = eta0 + (eta - eta0)/C the density g_BSE/S is a mixture of a cosine
lobe (probability eta0/S) and the Phong lobe about the mirror direction (probability
(eta - eta0)/(C S)); lobe samples that fall below the surface are rejected. The sample weight
g/pdf is therefore the constant S(theta) for every accepted sample (zero variance per sample)
and the accepted fraction is eta/S.

XML parameters: ``material`` (preset name or composition "Ti:0.9,Al:0.06,V:0.04", default
Ti-6Al-4V), ``lobe`` (bool, default true; false = Lambert part only, Figs. 12-13 right),
``lobe_width`` (deg, default 13). ``mi.traverse`` exposes ``lobe_width``; a material is changed
in place with :meth:`EloBSE.set_material` (same kernel, no recompilation).
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from elo_mitsuba.constants import DEFAULT_MATERIAL, LOBE_WIDTH_DEG
from elo_mitsuba.errors import EloInputError
from elo_mitsuba.physics.materials import get_material
from elo_mitsuba.physics.scattering import lobe_weight_table

TABLE_SIZE = 4097  # linear interpolation of W(theta): < 3e-6 relative even for 1 deg lobes
_INV_PI = 1.0 / np.pi


def incidence_deg(cos_t, sin_t):
    """The angle of incidence (deg) from its cosine and sine, 0 where grazing from below. Not
    acos(cos): near normal incidence acos turns a last-bit change of the cosine (an FMA on one CPU,
    not on another) into 1e-4 of the angle, enough to change how many of a sample's paths go to
    the lobe (ceil(q k - xi)) between instruction sets."""
    return dr.atan2(sin_t, dr.maximum(cos_t, 0.0)) * (180.0 / dr.pi)


def table_lookup(table, theta_deg, size, offset=None, active=True):
    """A function of the incidence angle (W(theta), eta(theta)) by linear interpolation of
    ``table`` on the uniform 0..90 deg grid of ``size`` nodes, starting at index ``offset``
    (a material's slot in a scene table)."""
    pos = theta_deg * ((size - 1) / 90.0)
    # NaN (a degenerate normal) would cast to an arbitrary index and read outside the table
    pos = dr.select(dr.isfinite(pos), pos, 0.0)
    i0 = mi.UInt32(dr.clip(dr.floor(pos), 0, size - 2))
    frac = pos - mi.Float(i0)
    index = i0 if offset is None else offset + i0
    w0 = dr.gather(mi.Float, table, index, active)
    w1 = dr.gather(mi.Float, table, index + 1, active)
    return dr.fma(frac, w1 - w0, w0)


class EloBSE(mi.BSDF):
    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        material = props.get("material", DEFAULT_MATERIAL)
        lobe = props.get("lobe", True)
        if isinstance(lobe, str) or not (isinstance(lobe, bool) or lobe in (0, 1)):  # bool("false") is True
            raise EloInputError(f"elo_bse: lobe={lobe!r}; must be true or false (<boolean name=\"lobe\" value=\"false\"/>)")
        self.lobe = bool(lobe)
        width = float(props.get("lobe_width", LOBE_WIDTH_DEG))
        if not (np.isfinite(width) and width > 0):
            raise EloInputError(f"elo_bse: lobe_width={width!r} deg; must be a positive number")
        self.lobe_width = mi.Float(width)
        self.material = None
        self.eta0 = mi.Float(0.0)
        self.lobe_table = mi.Float(np.zeros(TABLE_SIZE))
        self.eta_table = mi.Float(np.zeros(TABLE_SIZE))
        self.set_material(material)
        flags_d = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        flags_g = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        self.m_components = [flags_d, flags_g]
        self.m_flags = flags_d | flags_g

    # ---- parameters ------------------------------------------------------------------------------
    def set_material(self, material):
        """Switch the target material (preset, composition string or mapping) in place."""
        self.material = get_material(material)
        self._update_tables()

    def _update_tables(self):
        width = float(self.lobe_width[0])
        if not (np.isfinite(width) and width > 0):
            raise EloInputError(f"elo_bse: lobe_width={width!r} deg; must be a positive number")
        _, w = lobe_weight_table(self.material, width, TABLE_SIZE, self.lobe)
        # Assign into the existing (opaque) variables so re-renders reuse the compiled kernel.
        self.eta0 = dr.opaque(mi.Float, self.material.eta0)
        self.lobe_table = mi.Float(w.astype(np.float32))
        # eta(theta) (Eqs. 10-12): the fraction that leaves; a detector plate with this BSDF
        # collects the rest, 1 - eta (integrator elo)
        self.eta_table = mi.Float(self.material.eta_deg(np.linspace(0.0, 90.0, TABLE_SIZE)).astype(np.float32))
        dr.make_opaque(self.eta0, self.lobe_table, self.eta_table, self.lobe_width)

    def traverse(self, callback):
        callback.put("lobe_width", self.lobe_width, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys=[]):
        self._update_tables()

    # ---- g_BSE ----------------------------------------------------------------------------------
    def _lobe(self, wi):
        """(k, W(theta)) for the local incident direction: exponent and tabulated lobe weight."""
        theta_deg = incidence_deg(wi.z, dr.sqrt(dr.fma(wi.x, wi.x, wi.y * wi.y)))
        k = theta_deg / self.lobe_width
        return k, table_lookup(self.lobe_table, theta_deg, TABLE_SIZE)

    def _terms(self, wi, wo):
        """(g_BSE, S, valid) for local directions; g = 0 where wi or wo is at/below the surface."""
        k, weight = self._lobe(wi)
        cos_t, cos_a = wi.z, wo.z
        # cos(beta) between wo and the mirror direction of p_E = -wi: (-wi.x, -wi.y, wi.z)
        cos_b = cos_t * cos_a - wi.x * wo.x - wi.y * wo.y
        lobe = dr.select(cos_b > 0, dr.power(dr.maximum(cos_b, 1e-30), k), 0.0)
        g = self.eta0 * _INV_PI * cos_a + weight * lobe
        valid = (cos_t > 0) & (cos_a > 0)
        # S = eta0 + (eta - eta0)/C = eta0 + W 2 pi/(k+1): the mixture's normaliser
        s = self.eta0 + weight * (2.0 * dr.pi) / (k + 1.0)
        return dr.select(valid, g, 0.0), s, valid

    def eval(self, ctx, si, wo, active=True):
        g, _, _ = self._terms(si.wi, wo)
        return mi.Spectrum(dr.select(active, g, 0.0))

    def pdf(self, ctx, si, wo, active=True):
        g, s, valid = self._terms(si.wi, wo)
        return dr.select(active & valid & (s > 0), g / s, 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        g, s, valid = self._terms(si.wi, wo)
        ok = active & valid & (s > 0)
        return mi.Spectrum(dr.select(active, g, 0.0)), dr.select(ok, g / s, 0.0)

    def sample(self, ctx, si, sample1, sample2, active=True):
        wi = si.wi
        k, weight = self._lobe(wi)
        q_lobe = lobe_probability(self.eta0, weight, k)
        pick_lobe = sample1 < q_lobe

        # Phong lobe about the mirror direction: cos(beta) = u^(1/(k+1))
        cos_b = dr.power(dr.maximum(sample2.x, 1e-30), 1.0 / (k + 1.0))
        sin_b = dr.safe_sqrt(1.0 - cos_b * cos_b)
        sin_p, cos_p = dr.sincos(2.0 * dr.pi * sample2.y)
        mirror = mi.Vector3f(-wi.x, -wi.y, wi.z)
        wo_lobe = mi.Frame3f(mirror).to_world(mi.Vector3f(sin_b * cos_p, sin_b * sin_p, cos_b))
        wo_diff = mi.warp.square_to_cosine_hemisphere(sample2)
        wo = dr.select(pick_lobe, wo_lobe, wo_diff)

        g, s, valid = self._terms(wi, wo)
        ok = active & valid & (s > 0) & (g > 0)
        bs = mi.BSDFSample3f()
        bs.wo = wo
        bs.pdf = dr.select(ok, g / s, 0.0)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(
            dr.select(pick_lobe, int(mi.BSDFFlags.GlossyReflection), int(mi.BSDFFlags.DiffuseReflection))
        )
        bs.sampled_component = dr.select(pick_lobe, mi.UInt32(1), mi.UInt32(0))
        # g / pdf = S for every accepted sample
        return bs, mi.Spectrum(dr.select(ok, s, 0.0))

    def to_string(self):
        mode = "full" if self.lobe else "diffuse-only"
        return (f"EloBSE[material={self.material.describe()}, eta0={self.material.eta0:.5f}, "
                f"lobe_width={float(self.lobe_width[0]):g} deg, {mode}]")


def lobe_probability(eta0, weight, k):
    """The probability that ``sample`` draws the lobe: its share (eta - eta0)/C = W 2 pi/(k + 1)
    of S = eta0 + that (the mixture's normaliser), for the lobe weight W and exponent k of the
    angle of incidence. The integrator's split of continuation paths uses the same share."""
    lobe_mass = weight * (2.0 * dr.pi) / (k + 1.0)
    return lobe_mass / (eta0 + lobe_mass)


# ---- g_BSE in world coordinates, from the tables of every elo_bse of a scene ------------------------
# The integrator evaluates g_BSE for many detector directions per scattering point. Instead of one
# virtual call per direction it gathers, by the BSDF id of the surface interaction, the same
# quantities _lobe and _terms use (eta0, 1/lobe_width, the W(theta) table) and evaluates Eq. 13 in
# world coordinates; the setup (angle of incidence, table lookup, mirror direction) is shared by
# all directions of one point.
def is_elo_bse(bsdf) -> bool:
    """Whether ``bsdf`` is an ``elo_bse`` (has its tables)."""
    return bsdf is not None and all(hasattr(bsdf, a) for a in ("eta0", "lobe_table", "eta_table", "lobe_width"))


def scene_tables(scatterers):
    """g_BSE of every scattering surface from per-BSDF tables, without a virtual call: the
    BSDF id of a surface interaction indexes (eta0, 1/lobe_width, W(theta) table) of its
    ``elo_bse``. None (use ``bsdf.eval`` by dispatch) if a scatterer has another BSDF."""
    bsdfs = {}
    for shape in scatterers:
        bsdf = shape.bsdf()
        if not is_elo_bse(bsdf):
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


def world_setup(tables, si, wi_world, alive):
    """Per scattering point: what g_BSE shares between directions (same formulas as
    elo_bse's ``_terms``, in world coordinates)."""
    t = tables
    size = t["size"]
    bid = dr.reinterpret_array(mi.UInt32, si.bsdf())
    slot = dr.gather(mi.UInt32, t["slot_of"], bid, alive & (bid < dr.width(t["slot_of"])))
    eta0 = dr.gather(mi.Float, t["eta0"], slot, alive)
    inv_width = dr.gather(mi.Float, t["inv_width"], slot, alive)
    return _setup(eta0, inv_width, lambda theta_deg: table_lookup(t["lobe"], theta_deg, size, slot * size, alive),
                  si.sh_frame.n, wi_world, alive)


def normal_setup(bsdf, n, wi_world, alive=True):
    """:func:`world_setup` of one ``elo_bse`` for given (world) normals ``n`` and incident
    directions ``wi_world``, without a surface interaction (the far field's tabulated mean)."""
    return _setup(bsdf.eta0, 1.0 / bsdf.lobe_width,
                  lambda theta_deg: table_lookup(bsdf.lobe_table, theta_deg, TABLE_SIZE, None, alive),
                  n, wi_world, alive)


def _setup(eta0, inv_width, lobe_weight, n, wi_world, alive):
    cos_t = dr.dot(n, wi_world)
    theta_deg = incidence_deg(cos_t, dr.norm(dr.cross(n, wi_world)))
    k = theta_deg * inv_width
    weight = lobe_weight(theta_deg)
    mirror = n * (2.0 * cos_t) - wi_world  # mirror direction of p_E = -wi about n
    return (eta0 * (1.0 / dr.pi), weight, k, n, mirror, alive & (cos_t > 0))


def world_eval(setup, d):
    """g_BSE (cosine included) towards the world direction ``d`` from a :func:`world_setup`."""
    diffuse, weight, k, n, mirror, ok = setup
    cos_a = dr.dot(n, d)
    cos_b = dr.dot(mirror, d)
    lobe = dr.select(cos_b > 0, dr.power(dr.maximum(cos_b, 1e-30), k), 0.0)
    g = dr.fma(diffuse, cos_a, weight * lobe)
    return dr.select(ok & (cos_a > 0), g, 0.0)


def _eval_directions(bsdf, ctx, si, wos, active):
    """g_BSE for several local directions in ONE dispatch; identical work (angle of incidence,
    table lookup) is shared by Dr.Jit's common-subexpression elimination."""
    return [bsdf.eval(ctx, si, wo, active)[0] for wo in wos]


def collected_fraction(bsdf, cos_incidence):
    """1 - eta(theta) of a detector plate carrying ``bsdf`` (an ``elo_bse``), for the cosine of
    the angle between the arriving electrons and the plate normal (either face): the charge it
    keeps; the backscattered rest travels on."""
    theta_deg = dr.acos(dr.clip(cos_incidence, 0.0, 1.0)) * (180.0 / dr.pi)
    return 1.0 - table_lookup(bsdf.eta_table, theta_deg, TABLE_SIZE)


def eval_world(tables, si, bsdf, ctx, ray, alive, dirs_world):
    """g_BSE for the world directions ``dirs_world`` at ``si`` (reached along ``ray``): from
    :func:`scene_tables` when every scatterer has ``elo_bse``, else by one dispatch of ``bsdf``."""
    if tables is not None:
        setup = world_setup(tables, si, -ray.d, alive)
        return [world_eval(setup, d) for d in dirs_world]
    return dr.dispatch(bsdf, _eval_directions, ctx, si, [si.to_local(d) for d in dirs_world], active=alive)


PLUGIN_CLASS = EloBSE
