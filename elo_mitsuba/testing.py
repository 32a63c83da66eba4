"""Independent references for the BSDF ``elo_bse`` and the calls that hold the plugin to them
(as Mitsuba ships ``mitsuba.testing`` and ``mitsuba.chi2`` for its own BSDFs).

The tests (``tests/test_bsdf.py``) and the validation (``validation/bsdf_report.py``) use this
module as their one reference for g_BSE through Mitsuba. The references do not use the plugin nor
the renderer's tables:

* :func:`eta_ref`, :func:`eta0_ref` -- η(θ) and η0 written out from Eqs. 10-12, Eq. 10 per element
  and summed with the weight fractions (Castaing's rule, ``docs/paper-notes.md §5``);
* :func:`hemisphere_nodes` -- a 2-D Gauss product rule over the upper hemisphere in a frame
  adapted to the lobe, so that the integral of ``eval`` needs no C(θ) table
  (``docs/paper-notes.md §1``).

The second half calls the plugin in its local frame (normal +z; ``wi`` = −p_E points back to
where the electron came from, ``docs/paper-notes.md §4``): :func:`bsdf_eval`, :func:`bsdf_pdf`,
:func:`bsdf_sample`, :func:`energy` and Mitsuba's chi² harness :func:`chi2_run`. They take the
Mitsuba variant module ``mi`` (:func:`elo_mitsuba.ensure_variant`) and import Dr.Jit and
``mitsuba.chi2`` only when called, so importing this module needs numpy alone.
"""

from __future__ import annotations

import numpy as np

#: Incidence angles (deg) of the energy check: hemisphere integral of ``eval`` = η(θ).
THETAS_ENERGY = (0.0, 10.0, 30.0, 50.0, 70.0, 80.0, 85.0, 89.0, 89.9)
#: Incidence angles (deg) of the chi² sampling check.
THETAS_CHI2 = (0.0, 30.0, 60.0, 75.0, 85.0, 89.0)
#: Materials of the energy check.
MATERIALS = ("Ti-6Al-4V", "Cu", "316L")
#: Samples per chi² test.
CHI2_SAMPLES = 1_000_000

# --- eta(theta) from Eqs. 10-12 ----------------------------------------------------------------
_Z = {"Al": 13, "Si": 14, "Ti": 22, "V": 23, "Cr": 24, "Mn": 25, "Fe": 26, "Ni": 28, "Cu": 29,
      "Nb": 41, "Mo": 42}
_COMPOSITIONS = {
    "Ti-6Al-4V": {"Ti": 0.90, "Al": 0.06, "V": 0.04},   # docs/paper-notes.md §5
    "Cu": {"Cu": 1.0},
    "316L": None,  # taken from the preset table (its nominal fractions are data, not physics)
}
_B = 0.89  # Eq. 10: eta at grazing incidence


def composition(name):
    """Weight fractions ``{element: c_i}`` of material ``name``.

    Parameters
    ----------
    name : str
        ``"Ti-6Al-4V"``, ``"Cu"`` (written out here) or another preset of
        :data:`elo_mitsuba.physics.PRESETS`.

    Returns
    -------
    dict
    """
    comp = _COMPOSITIONS.get(name)
    if comp is None:
        from elo_mitsuba.physics import PRESETS

        comp = PRESETS[name]
    return comp


def _eta0_element(symbol):
    """Eq. 11: η0 of one element."""
    z = _Z[symbol]
    return -0.0254 + 0.016 * z - 1.86e-4 * z ** 2 + 8.3e-7 * z ** 3


def eta0_ref(name):
    """η0 of material ``name``: Eq. 11 per element, weighted by the fractions (Eq. 12).

    Parameters
    ----------
    name : str
        Material (see :func:`composition`).

    Returns
    -------
    float
    """
    return sum(c * _eta0_element(s) for s, c in composition(name).items())


def eta_ref(name, theta_deg):
    """η(θ) of material ``name``: Eq. 10 per element, summed with the weight fractions (Eq. 12).

    Parameters
    ----------
    name : str
        Material (see :func:`composition`).
    theta_deg : float or array_like
        Incidence angle (deg).

    Returns
    -------
    float or ndarray
    """
    cos_t = np.cos(np.deg2rad(theta_deg))
    return sum(c * _B * (_eta0_element(s) / _B) ** cos_t for s, c in composition(name).items())


def wi_of(theta_deg, phi_deg=0.0):
    """Unit vector ``wi`` (towards the gun) at polar angle ``theta_deg`` and azimuth ``phi_deg``."""
    t, p = np.deg2rad(theta_deg), np.deg2rad(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


# --- hemisphere quadrature ------------------------------------------------------------------------

def _gauss(n, a, b):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (b - a) * (x + 1.0) + a, 0.5 * (b - a) * w


def hemisphere_nodes(theta_deg, lobe_width_deg=13.0, n_gamma=48, n_psi=48):
    """Nodes and weights of a 2-D Gauss product rule over the upper hemisphere.

    Spherical coordinates (gamma, psi) about the lobe axis r (the mirror direction of the beam,
    ``wi`` in the xz-plane). Each ring gamma is clipped analytically to the part above the
    horizon, so the integrand is smooth on every ring; gamma is split into panels at the lobe's
    scale 1/sqrt(k+1) (doubling), at 90 deg (edge of the lobe) and where rings touch the horizon,
    with nodes clustered at panel ends. Integrates products of cos(alpha) and cos^k(beta) to
    about 1e-12.

    Parameters
    ----------
    theta_deg : float
        Incidence angle (deg) of ``wi`` = :func:`wi_of` (theta_deg).
    lobe_width_deg : float
        Lobe width; k = theta_deg / lobe_width_deg (``docs/paper-notes.md §3``).
    n_gamma, n_psi : int
        Gauss nodes per gamma panel and per ring.

    Returns
    -------
    wo : ndarray (N, 3)
        Unit directions with wo_z >= 0.
    w : ndarray (N,)
        Positive weights (solid angle, sr).
    """
    th = np.deg2rad(theta_deg)
    k = theta_deg / lobe_width_deg
    st, ct = np.sin(th), np.cos(th)
    r = np.array([-st, 0.0, ct])
    e1 = np.array([ct, 0.0, st])
    e2 = np.array([0.0, 1.0, 0.0])
    breaks = {0.0, np.pi, np.pi / 2, abs(np.pi / 2 - th), min(np.pi, np.pi / 2 + th)}
    g = 1.0 / np.sqrt(k + 1.0)
    while g < np.pi:
        breaks.add(g)
        g *= 2.0
    breaks = np.array(sorted(breaks))
    breaks = breaks[np.concatenate([[True], np.diff(breaks) > 1e-12])]
    t, wt = _gauss(n_gamma, 0.0, 1.0)
    m, dm = 0.5 * (1 - np.cos(np.pi * t)), 0.5 * np.pi * np.sin(np.pi * t)
    gam = np.concatenate([a + (b - a) * m for a, b in zip(breaks[:-1], breaks[1:])])
    w_gam = np.concatenate([wt * dm * (b - a) for a, b in zip(breaks[:-1], breaks[1:])])
    sg, cg = np.sin(gam), np.cos(gam)
    with np.errstate(divide="ignore", invalid="ignore"):
        # the ring is above the horizon for cos(psi) > a
        a = np.where(sg * st > 0, -cg * ct / (sg * st), np.where(cg * ct > 0, -np.inf, np.inf))
    psi_max = np.where(a <= -1, np.pi, np.where(a >= 1, 0.0, np.arccos(np.clip(a, -1, 1))))
    s, ws = _gauss(n_psi, -1.0, 1.0)
    psi = psi_max[:, None] * s[None, :]
    w = (w_gam * sg * psi_max)[:, None] * ws[None, :]
    wo = cg[:, None, None] * r + sg[:, None, None] * (
        np.cos(psi)[..., None] * e1 + np.sin(psi)[..., None] * e2)
    wo, w = wo.reshape(-1, 3), w.ravel()
    keep = w > 0
    return wo[keep], w[keep]


def binomial_se(p, n):
    """Standard error of a fraction ``p`` estimated from ``n`` samples (floored at 10 counts)."""
    return float(np.sqrt(max(p * (1.0 - p), 10.0 / n) / n))


# --- calling the plugin in the local frame (needs Mitsuba) -----------------------------------------

def _vec(mi, a):
    a = np.asarray(a, dtype=np.float64)
    return mi.Vector3f(*[np.ascontiguousarray(a[:, i]) for i in range(3)])


def _si(mi, wi, n):
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = _vec(mi, np.broadcast_to(np.asarray(wi, dtype=np.float64), (n, 3)))
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    return si


def bsdf_eval(mi, bsdf, wi, wo):
    """``bsdf.eval`` (g_BSE per sr including cos(alpha)) for ``wi`` (3,) or (N, 3), ``wo`` (N, 3).

    Parameters
    ----------
    mi : module
        The Mitsuba variant (:func:`elo_mitsuba.ensure_variant`).
    bsdf : mitsuba.BSDF
        A loaded ``elo_bse``.
    wi, wo : array_like
        Local-frame directions (normal +z).

    Returns
    -------
    ndarray (N,)
    """
    wo = np.atleast_2d(wo)
    wi = np.broadcast_to(np.asarray(wi, dtype=np.float64), wo.shape)
    v = bsdf.eval(mi.BSDFContext(), _si(mi, wi, len(wo)), _vec(mi, wo))
    return np.array(v, dtype=np.float64).ravel()


def bsdf_pdf(mi, bsdf, wi, wo):
    """``bsdf.pdf`` (density of the plugin's sampling, 1/sr); arguments as :func:`bsdf_eval`."""
    wo = np.atleast_2d(wo)
    wi = np.broadcast_to(np.asarray(wi, dtype=np.float64), wo.shape)
    return np.array(bsdf.pdf(mi.BSDFContext(), _si(mi, wi, len(wo)), _vec(mi, wo)),
                    dtype=np.float64).ravel()


def bsdf_sample(mi, bsdf, wi, n, seed=0):
    """``n`` samples of ``bsdf.sample`` for one ``wi`` (3,).

    Returns
    -------
    wo : ndarray (n, 3)
    weight : ndarray (n,)
        eval/pdf (0 for rejected samples).
    pdf : ndarray (n,)
    """
    rng = np.random.default_rng(seed)
    u = rng.random((3, n))
    bs, weight = bsdf.sample(mi.BSDFContext(), _si(mi, wi, n), mi.Float(u[0]),
                             mi.Point2f(u[1], u[2]))
    return (np.array(bs.wo, dtype=np.float64).T, np.array(weight, dtype=np.float64).ravel(),
            np.array(bs.pdf, dtype=np.float64).ravel())


def energy(mi, bsdf, theta_deg, lobe_width_deg=13.0):
    """Hemisphere integral of ``eval`` at incidence ``theta_deg`` by :func:`hemisphere_nodes`.

    Equals η(θ) (:func:`eta_ref`) for a correct plugin (Eq. 2 with Eqs. 10/12).
    """
    wo, w = hemisphere_nodes(theta_deg, lobe_width_deg)
    return float(np.sum(w * bsdf_eval(mi, bsdf, wi_of(theta_deg), wo)))


def chi2_run(mi, theta_deg, extra='<string name="material" value="Ti-6Al-4V"/>',
             sample_count=CHI2_SAMPLES, test_count=len(THETAS_CHI2)):
    """Mitsuba's chi² test of ``elo_bse`` sampling against its ``pdf`` at incidence ``theta_deg``.

    Parameters
    ----------
    mi : module
        The Mitsuba variant (imported so that the plugin is registered).
    theta_deg : float
        Incidence angle (deg) of ``wi`` = :func:`wi_of` (theta_deg).
    extra : str
        XML properties of the BSDF.
    sample_count : int
        Samples drawn.
    test_count : int
        Number of tests run together (Šidák correction of the significance level 0.01).

    Returns
    -------
    accepted : bool
    p_value : float
    hist_mass, pdf_mass : float
        Fraction of the samples in the histogram, and the tabulated pdf's integral.
    test : mitsuba.chi2.ChiSquareTest
    """
    import drjit as dr
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    sample, pdf = BSDFAdapter("elo_bse", extra, wi=[float(x) for x in wi_of(theta_deg)])
    test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample, pdf_func=pdf,
                         sample_dim=3, sample_count=sample_count, res=101)
    test.tabulate_histogram()
    test.tabulate_pdf()
    ok = test.run(0.01, test_count=test_count, quiet=True)
    hist_mass = float(dr.sum(test.histogram)[0]) / sample_count
    pdf_mass = float(dr.sum(test.pdf)[0]) / sample_count
    return ok, float(test.p_value), hist_mass, pdf_mass, test
