"""The BSE scattering function g_BSE of Eq. 13 and its lobe normalisation C(theta).

Pure numpy. Conventions (docs/paper-notes.md §3, §4):

* ``theta``: angle between the surface normal n_S and the reversed beam direction -p_E;
* ``alpha``: angle between n_S and the outgoing direction d;
* ``beta``: angle between d and the mirror direction of p_E about n_S;
* k = theta / 13 deg with theta in **degrees** (``lobe_width_deg`` = 13 by default).

g_BSE(theta, alpha, beta) = eta0/pi cos(alpha) + (eta(theta) - eta0)/C(theta) (k+1)/(2 pi) cos^k(beta)

is a probability per steradian (the cosine of alpha is inside it). Both cosines are clamped at 0:
g_BSE vanishes below the surface and outside the lobe's hemisphere.

C(theta) is **computed from its definition** (the printed Eq. 14 is wrong, docs/paper-notes.md §1): the
integral over the upper hemisphere of the normalised lobe (k+1)/(2 pi) max(cos beta, 0)^k whose
axis is tilted by theta from the normal, so that the lobe part of g_BSE integrates to
eta(theta) - eta0 and all of g_BSE to eta(theta) (Eq. 2).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..constants import LOBE_WIDTH_DEG
from ..errors import EloInputError

_GL_ORDER = 96


def lobe_exponent(theta_deg, lobe_width_deg=LOBE_WIDTH_DEG):
    """Phong exponent k = theta / lobe_width (theta in degrees), Eq. 13's text.

    Parameters
    ----------
    theta_deg : array_like
        Incidence angle(s) in degrees.
    lobe_width_deg : float
        Lobe width in degrees (13 in the paper).

    Returns
    -------
    ndarray
        k (unitless).

    Examples
    --------
    >>> float(lobe_exponent(26.0))
    2.0
    """
    if not lobe_width_deg > 0:
        raise EloInputError(f"lobe width {lobe_width_deg!r} deg: must be > 0")
    return np.asarray(theta_deg, dtype=float) / float(lobe_width_deg)


@lru_cache(maxsize=None)
def _gauss_legendre_01(n: int):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


def lobe_normalisation(theta_deg, lobe_width_deg=LOBE_WIDTH_DEG):
    """C(theta): hemisphere integral of the normalised Phong lobe of Eq. 13 (replaces Eq. 14).

    With the lobe axis r at angle theta from the normal, polar angle gamma about r and
    u = cos(gamma), the part of the ring at gamma that lies above the surface is
    acos(clip(-u cot(theta) / sqrt(1 - u^2), -1, 1)) / pi; the ring is entirely above the
    surface for u >= sin(theta). Hence the 1-D form

        C = 1 - s^(k+1) + int_0^s (k+1) u^k acos(-u cot(theta)/sqrt(1-u^2)) / pi du,  s = sin(theta),

    evaluated by Gauss-Legendre quadrature after u = s (1 - t^2), which removes the square-root
    behaviour of acos at u = s. Measured accuracy: better than 1e-7 at the paper's lobe width
    (13 deg), about 3e-6 for very wide lobes (k < 0.1), where u^k is steep at u = 0.

    Parameters
    ----------
    theta_deg : array_like
        Incidence angle(s) in degrees, clipped to [0, 90].
    lobe_width_deg : float
        Lobe width (13 deg in the paper): k = theta / lobe_width_deg.

    Returns
    -------
    ndarray
        C(theta), 1 at theta = 0 and 1/2 at theta = 90 deg for every k.

    Examples
    --------
    >>> lobe_normalisation([0.0, 45.0, 90.0]).round(4).tolist()
    [1.0, 0.9525, 0.5]
    """
    theta_deg = np.clip(np.asarray(theta_deg, dtype=float), 0.0, 90.0)
    k = lobe_exponent(theta_deg, lobe_width_deg)[..., None]
    theta = np.deg2rad(theta_deg)[..., None]
    s = np.sin(theta)
    cos_t = np.cos(theta)
    t, w = _gauss_legendre_01(_GL_ORDER)
    u = s * (1.0 - t * t)
    du_dt = 2.0 * s * t
    with np.errstate(divide="ignore", invalid="ignore"):
        # -u cot(theta) / sqrt(1 - u^2), written to stay finite at theta = 0 (s = 0) and 90 deg.
        arg = np.where(s > 0, -u * cos_t / (np.maximum(s, 1e-300) * np.sqrt(np.maximum(1.0 - u * u, 1e-300))), -1.0)
    frac = np.arccos(np.clip(arg, -1.0, 1.0)) / np.pi
    integrand = (k + 1.0) * np.power(u, k) * frac * du_dt
    partial = np.sum(w * integrand, axis=-1)
    c = 1.0 - np.power(s[..., 0], k[..., 0] + 1.0) + partial
    return c


def lobe_normalisation_table(n=1025, lobe_width_deg=LOBE_WIDTH_DEG):
    """C(theta) on ``n`` equidistant angles from 0 to 90 deg, for linear interpolation in kernels.

    Returns ``(theta_deg, c)``. With 1025 nodes linear interpolation is accurate to < 1e-6.

    Parameters
    ----------
    n : int
        Number of angles.
    lobe_width_deg : float
        Lobe width in degrees.

    Returns
    -------
    theta_deg, c : ndarray (n,)

    Examples
    --------
    >>> theta, c = lobe_normalisation_table(n=3)
    >>> theta.tolist(), c.round(4)[[0, -1]].tolist()
    ([0.0, 45.0, 90.0], [1.0, 0.5])
    """
    theta = np.linspace(0.0, 90.0, int(n))
    return theta, lobe_normalisation(theta, lobe_width_deg)


#: Repairs of the second coefficient of the printed Eq. 14 (docs/paper-notes.md §1).
_EQ14_REPAIRS = {"4.06e-3": 4.06e-3, "4.06e-4": 4.06e-4}


def lobe_normalisation_eq14_repaired(theta_deg, repair="4.06e-3"):
    """The printed polynomial Eq. 14 with its second coefficient repaired: **not** the default.

    C(theta) = 1.01 - a theta + 1.36e-5 theta^2 - 1.71e-6 theta^3, a = 4.06e-3 or 4.06e-4.
    The printed a = 4.06 is negative above 0.25 deg. Both repairs still reach zero below 90 deg,
    where g_BSE would blow up; this function refuses those angles.

    Parameters
    ----------
    theta_deg : array_like
        Incidence angle(s) in degrees.
    repair : {"4.06e-3", "4.06e-4"}
        Which repair of the second coefficient.

    Returns
    -------
    ndarray
        C(theta) by the repaired polynomial.

    Raises
    ------
    EloInputError
        For an unknown repair or any theta where the polynomial is <= 0.01.

    Examples
    --------
    >>> lobe_normalisation_eq14_repaired([0.0, 30.0]).round(4).tolist()
    [1.01, 0.8...]
    """
    if repair not in _EQ14_REPAIRS:
        raise EloInputError(f"Eq. 14 repair {repair!r}: choose one of {', '.join(_EQ14_REPAIRS)}")
    a = _EQ14_REPAIRS[repair]
    th = np.asarray(theta_deg, dtype=float)
    c = 1.01 - a * th + 1.36e-5 * th**2 - 1.71e-6 * th**3
    limit = eq14_valid_limit_deg(repair)
    if np.any(th > limit) or np.any(th < 0):
        bad = float(np.max(th))
        raise EloInputError(
            f"Eq. 14 (repair {repair}) is non-positive at theta={bad:g} deg; it is only usable "
            f"for 0 <= theta <= {limit:.2f} deg. Use the exact lobe_normalisation instead."
        )
    return c


def eq14_valid_limit_deg(repair="4.06e-3") -> float:
    """Largest angle (deg) below which the repaired Eq. 14 stays above 0.01.

    Parameters
    ----------
    repair : {"4.06e-3", "4.06e-4"}

    Returns
    -------
    float
        The angle in degrees.

    Examples
    --------
    >>> 0 < eq14_valid_limit_deg() < 90
    True
    """
    a = _EQ14_REPAIRS[repair]
    th = np.linspace(0.0, 90.0, 90001)
    c = 1.01 - a * th + 1.36e-5 * th**2 - 1.71e-6 * th**3
    bad = np.nonzero(c <= 0.01)[0]
    return 90.0 if bad.size == 0 else float(th[bad[0] - 1])


def g_bse_local(wi, wo, material, lobe=True, lobe_width_deg=LOBE_WIDTH_DEG):
    """g_BSE (Eq. 13) in the local frame of the surface (normal = +z).

    Parameters
    ----------
    wi : array_like, shape (..., 3)
        Unit vector pointing back to where the electron came from (-p_E).
    wo : array_like, shape (..., 3)
        Unit vector of the outgoing direction d.
    material : Material
        Provides ``eta0`` (Eq. 11/12) and ``eta(theta)`` (Eqs. 10/12).
    lobe : bool
        False keeps only the diffuse (Lambert) part, as in the right halves of Figs. 12-13.

    Returns
    -------
    ndarray
        Probability per steradian; 0 where wi or wo is at or below the surface.

    Examples
    --------
    >>> import numpy as np
    >>> from elo_mitsuba.physics.materials import get_material
    >>> up = np.array([0.0, 0.0, 1.0])
    >>> round(float(g_bse_local(up, up, get_material())), 4)      # normal incidence, seen from above
    0.0765
    >>> float(g_bse_local(up, np.array([0.0, 0.0, -1.0]), get_material()))   # below the surface
    0.0
    """
    wi = np.asarray(wi, dtype=float)
    wo = np.asarray(wo, dtype=float)
    # mirror of p_E = -wi about the normal is (-wi_x, -wi_y, wi_z)
    cos_b = -wi[..., 0] * wo[..., 0] - wi[..., 1] * wo[..., 1] + wi[..., 2] * wo[..., 2]
    return _g_from_cosines(wi[..., 2], wo[..., 2], cos_b, material, lobe, lobe_width_deg)


def g_bse(normal, beam_dir, out_dir, material, lobe=True, lobe_width_deg=LOBE_WIDTH_DEG):
    """g_BSE (Eq. 13) for world-space vectors.

    Parameters
    ----------
    normal : array_like (..., 3)
        Surface normal n_S (any length, e.g. the p,q-form [n_Sx, n_Sy, 1] of Eq. 16).
    beam_dir : array_like (..., 3)
        Beam direction of travel p_E (pointing into the surface), any length.
    out_dir : array_like (..., 3)
        Direction d towards the detector, any length.
    material : Material
        Provides ``eta0`` and ``eta(theta)``.

    Returns
    -------
    ndarray
        g_BSE per steradian (0 where the detector or the beam is behind the surface).

    Examples
    --------
    >>> from elo_mitsuba.physics.materials import get_material
    >>> ti64 = get_material("Ti-6Al-4V")
    >>> round(float(g_bse([0, 0, 1], [0, 0, -1], [0, 0, 1], ti64)), 4)    # flat plate, vertical beam
    0.0765
    >>> round(float(g_bse([0, 0, 1], [0, 0, -1], [127, 0, 272], ti64)), 4)  # towards a zeta25 detector
    0.0693
    """
    n = _unit(normal)
    p = _unit(beam_dir)
    d = _unit(out_dir)
    n, p, d = np.broadcast_arrays(n, p, d)
    wi = -p
    cos_t = np.sum(n * wi, axis=-1)
    cos_a = np.sum(n * d, axis=-1)
    mirror = p - 2.0 * np.sum(p * n, axis=-1)[..., None] * n
    cos_b = np.sum(mirror * d, axis=-1)
    return _g_from_cosines(cos_t, cos_a, cos_b, material, lobe, lobe_width_deg)


def _g_from_cosines(cos_t, cos_a, cos_b, material, lobe, lobe_width_deg):
    """Eq. 13 from cos(theta), cos(alpha), cos(beta); zero where theta or alpha >= 90 deg."""
    valid = (cos_t > 0) & (cos_a > 0)
    g = material.eta0 / np.pi * np.maximum(cos_a, 0.0)
    if lobe:
        theta = np.arccos(np.clip(cos_t, 0.0, 1.0))
        theta_deg = np.rad2deg(theta)
        k = lobe_exponent(theta_deg, lobe_width_deg)
        c = lobe_normalisation(theta_deg, lobe_width_deg)
        # max(cos beta, 0)^k with 0^0 guarded: the lobe is 0 outside its hemisphere, never NaN.
        lobe_val = np.where(cos_b > 0, np.power(np.maximum(cos_b, 0.0), k), 0.0)
        g = g + (material.eta(theta) - material.eta0) / c * (k + 1.0) / (2.0 * np.pi) * lobe_val
    return np.where(valid, g, 0.0)


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def lobe_weight_table(material, lobe_width_deg=LOBE_WIDTH_DEG, n=1025, lobe=True):
    """Tabulated lobe weight of Eq. 13 for the kernels: W(theta) = (eta - eta0)/C (k+1)/(2 pi).

    g_BSE = eta0/pi cos(alpha) + W(theta) max(cos beta, 0)^k. Returns ``(theta_deg, W)`` on ``n``
    equidistant angles over [0, 90] deg; ``lobe=False`` gives W = 0 (diffuse-only). Linear
    interpolation in theta is accurate to better than 1e-6 relative with the default n.

    Parameters
    ----------
    material : Material
        The target (:func:`~elo_mitsuba.physics.materials.get_material`): ``eta0``, ``eta(theta)``.
    lobe_width_deg : float
        Lobe width in degrees.
    n : int
        Number of angles.
    lobe : bool
        False: W = 0.

    Returns
    -------
    theta_deg, w : ndarray (n,)
        Angles in degrees and W in 1/sr.

    Examples
    --------
    >>> from elo_mitsuba.physics.materials import get_material
    >>> theta, w = lobe_weight_table(get_material("Ti-6Al-4V"), n=3)
    >>> theta.tolist(), float(w[0]), bool(w[-1] > 0)
    ([0.0, 45.0, 90.0], 0.0, True)
    """
    theta_deg = np.linspace(0.0, 90.0, int(n))
    if not lobe:
        return theta_deg, np.zeros_like(theta_deg)
    k = lobe_exponent(theta_deg, lobe_width_deg)
    c = lobe_normalisation(theta_deg, lobe_width_deg)
    w = (material.eta(np.deg2rad(theta_deg)) - material.eta0) / c * (k + 1.0) / (2.0 * np.pi)
    return theta_deg, w
