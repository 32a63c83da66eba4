"""What the detector signals can tell: the Cramér-Rao bound of the surface gradient (issue 27).

Each pixel's N detector signals are modelled by the 1st event of one flat facet
(:class:`~.detector_model.FacetModel`: full g_BSE, the discs, the pixel's own beam and landing
point), as the model-based gradient (:mod:`.model_gradient`) inverts them. The measurement model
is the one that fit uses,

    C_k = s m_k(p, q) + noise,        m_k = S_k(n_S) / S_k(flat),   n_S = [p, q, 1] / norm,

with p = -dZ/dx, q = -dZ/dy (Eq. 16) and s a per-pixel scale (material contrast, beam drift) that
the fit eliminates (s = sum C m / sum m^2). The bound therefore treats s as a nuisance parameter:
the Fisher matrix is taken over (p, q, s) and the bound on (p, q) is the (p, q) block of its
inverse, which is larger than the inverse of the (p, q) block alone (the price of not knowing s).

Fisher matrix: F = J^T diag(1/sigma_k^2) J with J_k = d mean_k / d(p, q, s). The derivatives of
the Dr.Jit model are central differences (step :data:`CRB_STEP`; the model is smooth in (p, q)
away from a detector's masking line). Noise:

* a number: Gaussian noise of that standard deviation on every corrected image C_k (what the
  model fit's unweighted least squares is efficient for; the metric test uses it);
* :class:`SignalNoise`: the signal chain in counts. Detector k collects Poisson(N_0 S_k) electrons
  of the N_0 primaries of a pixel (thinning a Poisson beam into disjoint detectors keeps them
  independent), plus amplifier noise of ``amplifier_electrons`` (rms, in electrons per pixel):
  sigma_k^2 = N_0 S_k + sigma_amp^2. The flat reference is taken as noise-free (a mean of many
  recordings). The variance's own dependence on (p, q) is left out of F (for pure Poisson noise F
  is then exact; with amplifier noise the bound is slightly conservative).

Results are in slope units (dZ/dx, dZ/dy): the standard deviations of an unbiased estimate, and
``sigma_worst``, the square root of the larger eigenvalue of the 2 x 2 covariance (the direction
in which the gradient is least well fixed).

:func:`design_metrics` turns a detector system into the numbers a designer compares: the
worst-pixel bound over the field for slopes up to ``s_max``, the share of facets (over the field
and slopes up to ``s_mask``) that hide at least one detector (Sec. 4.3, centre criterion), the
share that leave fewer than three detectors (no solution for (p, q, s)), and the signal level.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..constants import (
    AMPLIFIER_NOISE_V,
    BEAM_CURRENT_A,
    DEFAULT_MATERIAL,
    ELEMENTARY_CHARGE_C,
    FIELD_MM,
    PIXEL_DWELL_S,
    TRANSIMPEDANCE_V_PER_A,
    WORK_DISTANCE_MM,
)
from ..errors import EloInputError
from .detector_model import DEFAULT_NODES, FacetModel, to_vector
from .noise import check_noise

#: Central-difference step in p and q for the model's derivative (float32 signals: a step of
#: 1e-3 keeps the round-off of the difference near 1e-4 relative).
CRB_STEP = 1e-3
#: Relative conditioning below which a Fisher matrix counts as singular (the signals cannot fix
#: (p, q, s)); its bound is reported as infinite, and by :func:`design_metrics` as SIGMA_CAP.
SINGULAR_RCOND = 1e-9
#: Bound reported by :func:`design_metrics` for a facet whose gradient the signals cannot fix
#: (slope units: far beyond any real slope, so it sorts last, never NaN).
SIGMA_CAP = 1e3
#: Slope samples of :func:`design_metrics`: azimuths per ring (rings at s_max/2 and s_max, plus 0).
PRECISION_AZIMUTHS = 8
#: Masking samples: radii (area-uniform) x azimuths over the slope disc of radius s_mask.
MASK_SAMPLES = (8, 24)


@dataclass(frozen=True)
class SignalNoise:
    """Noise of the detector signal chain of one pixel, in counted electrons.

    Attributes
    ----------
    primary_electrons : float
        N_0, primary electrons per pixel (beam current x dwell time / e).
    amplifier_electrons : float
        RMS amplifier noise per pixel, as an equivalent number of collected electrons.

    Examples
    --------
    The defaults of the package (3 mA, 1 us per pixel, 1 mV rms at 1e5 V/A):

    >>> noise = SignalNoise.from_chain()
    >>> f"{noise.primary_electrons:.3g} {noise.amplifier_electrons:.3g}"
    '1.87e+10 6.24e+04'
    """

    primary_electrons: float
    amplifier_electrons: float = 0.0

    def __post_init__(self):
        n0, amp = float(self.primary_electrons), float(self.amplifier_electrons)
        if not (np.isfinite(n0) and n0 > 0):
            raise EloInputError(f"primary electrons per pixel {self.primary_electrons!r}: must be finite and > 0")
        if not (np.isfinite(amp) and amp >= 0):
            raise EloInputError(f"amplifier noise {self.amplifier_electrons!r} electrons: must be finite and >= 0")
        object.__setattr__(self, "primary_electrons", n0)
        object.__setattr__(self, "amplifier_electrons", amp)

    @classmethod
    def from_chain(cls, beam_current_a: float = BEAM_CURRENT_A, dwell_s: float = PIXEL_DWELL_S,
                   amplifier_v: float = AMPLIFIER_NOISE_V,
                   transimpedance_v_per_a: float = TRANSIMPEDANCE_V_PER_A) -> "SignalNoise":
        """The noise of a beam current (A), a dwell time per pixel (s) and an amplifier whose
        output carries ``amplifier_v`` rms (V) at ``transimpedance_v_per_a``: its input-referred
        current over one dwell, in electrons.

        Examples
        --------
        >>> SignalNoise.from_chain(1e-3, 1e-7, 0.0).amplifier_electrons
        0.0
        """
        for name, v in (("beam current", beam_current_a), ("dwell time", dwell_s),
                        ("transimpedance", transimpedance_v_per_a)):
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise EloInputError(f"{name} {v!r}: must be a finite number > 0")
        if not (isinstance(amplifier_v, (int, float)) and np.isfinite(amplifier_v) and amplifier_v >= 0):
            raise EloInputError(f"amplifier noise {amplifier_v!r} V: must be a finite number >= 0")
        n0 = beam_current_a * dwell_s / ELEMENTARY_CHARGE_C
        amp = amplifier_v / transimpedance_v_per_a * dwell_s / ELEMENTARY_CHARGE_C
        return cls(n0, amp)


@dataclass
class GradientBound:
    """The Cramér-Rao bound of the gradient per pixel (arrays of the input's shape).

    Attributes
    ----------
    sigma_dzdx, sigma_dzdy : ndarray
        Bound on the standard deviation of dZ/dx and dZ/dy (slope units; inf where the signals
        cannot fix the gradient).
    sigma_worst : ndarray
        Square root of the larger eigenvalue of the (dZ/dx, dZ/dy) covariance bound.
    visible : ndarray of int
        Detectors that see the facet (the model's signal > 0).
    signal : ndarray
        Sum over detectors of the facet's 1st-event signal, N_1/N_0.
    """

    sigma_dzdx: np.ndarray
    sigma_dzdy: np.ndarray
    sigma_worst: np.ndarray
    visible: np.ndarray
    signal: np.ndarray


def crb_covariance(jacobian, sigma) -> np.ndarray:
    """Inverse Fisher matrix of independent Gaussian observations: (J^T diag(sigma^-2) J)^-1.

    Parameters
    ----------
    jacobian : array_like (..., K, P)
        Derivatives of the K observations' means with respect to the P parameters.
    sigma : array_like (..., K)
        Standard deviation of each observation (> 0).

    Returns
    -------
    ndarray (..., P, P)
        The covariance bound; where the Fisher matrix is singular (relative conditioning below
        :data:`SINGULAR_RCOND`) every entry is inf.

    Examples
    --------
    Two parameters seen through three observations of noise 0.1; the third is their sum:

    >>> J = [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]
    >>> crb_covariance(J, [0.1, 0.1, 0.1]).round(5).tolist()
    [[0.00667, -0.00333], [-0.00333, 0.00667]]
    >>> bool(np.isinf(crb_covariance([[1.0, 1.0], [2.0, 2.0]], [1.0, 1.0])).all())
    True
    """
    J = np.asarray(jacobian, float)
    w = 1.0 / np.square(np.asarray(sigma, float))
    F = np.einsum("...kp,...k,...kq->...pq", J, w, J)
    # scale to a unit diagonal: the conditioning then measures identifiability, not units
    d = np.sqrt(np.clip(np.einsum("...pp->...p", F), 0.0, None))
    ok = np.all(d > 0, axis=-1)
    ds = np.where(d > 0, d, 1.0)
    Fn = F / (ds[..., :, None] * ds[..., None, :])
    eig = np.linalg.eigvalsh(Fn)
    ok &= np.isfinite(eig).all(axis=-1) & (eig[..., 0] > SINGULAR_RCOND * eig[..., -1])
    P = F.shape[-1]
    safe = np.where(ok[..., None, None], Fn, np.eye(P))
    inv = np.linalg.inv(safe) / (ds[..., :, None] * ds[..., None, :])
    return np.where(ok[..., None, None], inv, np.inf)


def facet_signals(detectors: Mapping, material, points, beam_dirs, p, q, *, step: float = CRB_STEP,
                  nodes=DEFAULT_NODES) -> dict[str, np.ndarray]:
    """The 1st-event signals of a facet (p, q) at each landing point, their derivatives in p and
    q, and the flat plate's signals at the same points: the model of the bound.

    Parameters
    ----------
    detectors : mapping of str to Disc
        The detectors.
    material : str
        Surface material.
    points, beam_dirs : array_like (n, 3)
        Landing points (mm) and unit beam directions of travel.
    p, q : array_like (n,)
        Facet slopes p = -dZ/dx, q = -dZ/dy.
    step : float
        Central-difference step in p and q.
    nodes : (int, int)
        Disc rule of the model.

    Returns
    -------
    dict
        ``S``, ``dS_dp``, ``dS_dq``, ``flat``: arrays (K, n) of N_1,k/N_0 (K detectors in the
        order of ``detectors``).

    Examples
    --------
    >>> from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    >>> g = ScanGeometry.nominal((1, 1), 80.0, 272.0, 127.0)
    >>> out = facet_signals(g.detectors, g.material, [[0.0, 0.0, 0.0]], [[0.0, 0.0, -1.0]], [0.0], [0.0])
    >>> out["S"].shape, bool(np.allclose(out["S"], out["flat"]))
    ((4, 1), True)
    >>> # tilting the facet towards +x (p > 0) raises the right detector's signal and lowers the left one's alike
    >>> bool(out["dS_dp"][0, 0] > 0), bool(abs(out["dS_dp"][1, 0] + out["dS_dp"][0, 0]) < 1e-3 * out["dS_dp"][0, 0])
    (True, True)
    """
    model = FacetModel(detectors, material, nodes=nodes)
    mi, dr = model.mi, model.dr
    pts = np.asarray(points, float).reshape(-1, 3)
    dirs = np.asarray(beam_dirs, float).reshape(-1, 3)
    p = np.broadcast_to(np.asarray(p, float), (len(pts),))
    q = np.broadcast_to(np.asarray(q, float), (len(pts),))
    h = float(step)
    sets = [(p, q), (p + h, q), (p - h, q), (p, q + h), (p, q - h), (0.0 * p, 0.0 * q)]
    normals = []
    for a, b in sets:
        n = np.stack([a, b, np.ones_like(a)], axis=-1)
        normals.append(to_vector(mi, n / np.linalg.norm(n, axis=-1, keepdims=True)))
    sig = model.signals(mi.Point3f(to_vector(mi, pts)), to_vector(mi, dirs), normals)
    dr.eval(sig)
    # float64 before differencing: the signals are float32, their difference must not round again
    S = np.array([[np.asarray(s, np.float64) for s in one] for one in sig])  # (6, K, n)
    return {"S": S[0], "dS_dp": (S[1] - S[2]) / (2 * h), "dS_dq": (S[3] - S[4]) / (2 * h), "flat": S[5]}


def bound_from_signals(signals: Mapping, noise, scale: float = 1.0) -> dict[str, np.ndarray]:
    """The bound on (dZ/dx, dZ/dy) from :func:`facet_signals`' output and a noise model.

    Parameters
    ----------
    signals : mapping
        ``S``, ``dS_dp``, ``dS_dq``, ``flat`` (K, n).
    noise : float or SignalNoise
        Gaussian standard deviation of each STSA-corrected image (a number), or the signal chain.
    scale : float
        The true per-pixel scale s (1: the flat plate's material and beam current).

    Returns
    -------
    dict
        ``sigma_dzdx``, ``sigma_dzdy``, ``sigma_worst`` (n,), slope units, inf where singular;
        ``covariance`` (n, 3, 3) over (p, q, s).

    Examples
    --------
    Three detectors whose signals change as +p, -p and +q, of noise 0.01:

    >>> one = np.ones((3, 1))
    >>> sig = {"S": one, "flat": one, "dS_dp": np.array([[1.0], [-1.0], [0.0]]), "dS_dq": np.array([[0.0], [0.0], [1.0]])}
    >>> out = bound_from_signals(sig, 0.01)
    >>> round(float(out["sigma_dzdx"][0]), 5), round(float(out["sigma_dzdy"][0]), 5)
    (0.00707, 0.01225)
    """
    S, Sp, Sq, flat = (np.asarray(signals[k], float) for k in ("S", "dS_dp", "dS_dq", "flat"))
    if isinstance(noise, SignalNoise):
        n0 = noise.primary_electrons
        mean, dp, dq = scale * n0 * S, scale * n0 * Sp, scale * n0 * Sq
        sigma = np.sqrt(np.clip(mean, 0.0, None) + noise.amplifier_electrons ** 2)
        ds = n0 * S
    else:
        level = check_noise(noise)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(flat > 0, 1.0 / flat, 0.0)
        mean, dp, dq, ds = scale * S * inv, scale * Sp * inv, scale * Sq * inv, S * inv
        sigma = np.full_like(mean, level)
    # a detector with no expected signal and no noise carries no information (not a 0/0)
    sigma = np.where(sigma > 0, sigma, np.inf)
    J = np.stack([dp, dq, ds], axis=-1)  # (K, n, 3)
    cov = crb_covariance(np.moveaxis(J, 0, 1), np.moveaxis(sigma, 0, 1))  # (n, 3, 3)
    a, d, b = cov[:, 0, 0], cov[:, 1, 1], cov[:, 0, 1]
    with np.errstate(invalid="ignore"):
        worst = np.sqrt((a + d) / 2 + np.sqrt(((a - d) / 2) ** 2 + b * b))
    worst = np.where(np.isfinite(a), worst, np.inf)
    # dZ/dx = -p: the same standard deviation
    return {"sigma_dzdx": np.sqrt(a), "sigma_dzdy": np.sqrt(d), "sigma_worst": worst, "covariance": cov}


def gradient_bound(geometry, dzdx=0.0, dzdy=0.0, *, noise, heights=None, scale: float = 1.0,
                   nodes=DEFAULT_NODES) -> GradientBound:
    """The Cramér-Rao bound of the gradient at every pixel of a scan.

    Parameters
    ----------
    geometry : ScanGeometry
        Field, beam, detectors, material (:mod:`.scan_geometry`); any number of detectors.
    dzdx, dzdy : float or ndarray (H, W)
        The true gradient (broadcast to the scan's shape).
    noise : float or SignalNoise
        As in :func:`bound_from_signals`.
    heights : ndarray (H, W), optional
        Surface heights for the landing points (None: z = 0).
    scale : float
        The true per-pixel scale s.
    nodes : (int, int)
        Disc rule of the model.

    Returns
    -------
    GradientBound

    Examples
    --------
    The nominal ATHENE layout (zeta = 25 deg, 50 mm discs), a flat plate, corrected images with
    1 % noise: each slope is fixed to about 0.015 at the centre of the field:

    >>> from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    >>> g = ScanGeometry.nominal((3, 3), 80.0, 272.0, 127.0)
    >>> b = gradient_bound(g, noise=0.01)
    >>> round(float(b.sigma_dzdx[1, 1]), 4), round(float(b.sigma_dzdy[1, 1]), 4), int(b.visible.min())
    (0.0151, 0.0151, 4)
    """
    shape = tuple(geometry.shape)
    points, dirs = geometry.beam(heights)
    dzdx = np.broadcast_to(np.asarray(dzdx, float), shape)
    dzdy = np.broadcast_to(np.asarray(dzdy, float), shape)
    sig = facet_signals(geometry.detectors, geometry.material, points.reshape(-1, 3), dirs.reshape(-1, 3),
                        -dzdx.ravel(), -dzdy.ravel(), nodes=nodes)
    if heights is not None:  # the flat reference is recorded on z = 0
        fp, fd = geometry.beam(None)
        sig["flat"] = facet_signals(geometry.detectors, geometry.material, fp.reshape(-1, 3), fd.reshape(-1, 3),
                                    0.0, 0.0, nodes=nodes)["flat"]
    out = bound_from_signals(sig, noise, scale)
    return GradientBound(sigma_dzdx=out["sigma_dzdx"].reshape(shape), sigma_dzdy=out["sigma_dzdy"].reshape(shape),
                         sigma_worst=out["sigma_worst"].reshape(shape),
                         visible=(sig["S"] > 0).sum(axis=0).reshape(shape), signal=sig["S"].sum(axis=0).reshape(shape))


def slope_samples(s_max: float, azimuths: int = PRECISION_AZIMUTHS) -> tuple[np.ndarray, np.ndarray]:
    """Gradients (dZ/dx, dZ/dy) at which the precision is judged: 0 and rings at s_max/2, s_max.

    Examples
    --------
    >>> gx, gy = slope_samples(0.5, 4)
    >>> len(gx), round(float(np.hypot(gx, gy).max()), 3)
    (9, 0.5)
    """
    phi = np.arange(int(azimuths)) * 2 * np.pi / int(azimuths)
    r = np.concatenate([[0.0], np.repeat([0.5 * s_max, s_max], len(phi))])
    a = np.concatenate([[0.0], phi, phi])
    return r * np.cos(a), r * np.sin(a)


def masked_shares(centers, points, s_mask: float, samples=MASK_SAMPLES) -> tuple[float, float]:
    """Share of facets that hide at least one detector, and of those that leave fewer than three
    visible, over the points and the slopes up to ``s_mask`` in magnitude (area-uniform in the slope
    disc). A detector is hidden when its centre lies on or behind the facet's tangent plane
    (Sec. 4.3).

    Parameters
    ----------
    centers : array_like (K, 3)
        Detector centres (mm).
    points : array_like (n, 3)
        Surface points (mm).
    s_mask : float
        Largest slope magnitude.
    samples : (int, int)
        Radii and azimuths of the slope samples.

    Returns
    -------
    (float, float)
        masked share, unsolvable share.

    Examples
    --------
    Table 1's zeta = 25 deg layout at the field centre: a facet hides the detector it turns away
    from once its slope passes 1/0.467 = 2.14:

    >>> c = [[127, 0, 272], [-127, 0, 272], [0, 127, 272], [0, -127, 272]]
    >>> masked_shares(c, [[0.0, 0.0, 0.0]], 2.0), masked_shares(c, [[0.0, 0.0, 0.0]], 3.0)[0] > 0
    ((0.0, 0.0), True)
    """
    nr, na = samples
    r = np.sqrt((np.arange(nr) + 0.5) / nr) * float(s_mask)
    a = np.arange(na) * 2 * np.pi / na
    gx = (r[:, None] * np.cos(a)[None, :]).ravel()
    gy = (r[:, None] * np.sin(a)[None, :]).ravel()
    n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)  # (m, 3), unnormalised: only the sign counts
    c = np.asarray(centers, float).reshape(-1, 3)
    pts = np.asarray(points, float).reshape(-1, 3)
    to_det = c[None, :, :] - pts[:, None, :]  # (n, K, 3)
    seen = np.einsum("mc,nkc->nmk", n, to_det) > 0
    hidden = (~seen).sum(axis=-1)
    return float(np.mean(hidden > 0)), float(np.mean(seen.sum(axis=-1) < 3))


def design_metrics(detectors: Mapping, *, field_mm: float = FIELD_MM, work_distance_mm: float = WORK_DISTANCE_MM,
                   material: str = DEFAULT_MATERIAL, grid: int = 5, s_max: float = 0.5, s_mask: float = 1.0,
                   noise=None, nodes=DEFAULT_NODES) -> dict[str, float]:
    """The figures of merit of a detector system over a scan field (first-event model, no render).

    Parameters
    ----------
    detectors : mapping of str to Disc
        The detectors (any number >= 3).
    field_mm, work_distance_mm : float
        Scan field (square) and the beam pivot's height.
    material : str
        Surface material.
    grid : int
        The field is judged at grid x grid points (its pixel centres).
    s_max : float
        Precision is judged for slope magnitudes up to this (:func:`slope_samples`).
    s_mask : float
        Masking is judged for slopes up to this (:func:`masked_shares`).
    noise : float or SignalNoise, optional
        Default: :meth:`SignalNoise.from_chain` (the package's beam, dwell and amplifier).
    nodes : (int, int)
        Disc rule of the model.

    Returns
    -------
    dict
        ``sigma_worst`` (the largest bound over field points and slope samples, capped at
        :data:`SIGMA_CAP`), ``sigma_median``, ``sigma_flat`` (worst over the field for the flat
        plate), ``masked_share``, ``unsolvable_share``, ``signal_min`` (smallest summed 1st-event
        signal N_1/N_0 of the flat plate over the field).

    Examples
    --------
    Table 1's zeta = 25 deg and zeta = 50 deg layouts: the flatter detectors fix the gradient
    better and hide more often.

    >>> from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    >>> m25 = design_metrics(ScanGeometry.nominal((1, 1), 80.0, 272.0, 127.0).detectors, grid=3)
    >>> m50 = design_metrics(ScanGeometry.nominal((1, 1), 80.0, 192.7, 229.6).detectors, grid=3)
    >>> bool(m50["sigma_worst"] < m25["sigma_worst"]), bool(m50["masked_share"] > m25["masked_share"])
    (True, True)
    """
    from .scan_geometry import ScanGeometry

    if len(detectors) < 3:
        raise EloInputError(f"{len(detectors)} detector(s): the gradient and the scale need at least 3")
    for name, v in (("s_max", s_max), ("s_mask", s_mask)):
        if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
            raise EloInputError(f"{name}={v!r}: a slope magnitude must be finite and >= 0")
    noise = SignalNoise.from_chain() if noise is None else noise
    geometry = ScanGeometry(field_mm=field_mm, shape=(int(grid), int(grid)), detectors=detectors,
                            work_distance_mm=work_distance_mm, material=material)
    points, dirs = geometry.beam(None)
    pts, dirs = points.reshape(-1, 3), dirs.reshape(-1, 3)
    gx, gy = slope_samples(s_max)
    m, n = len(gx), len(pts)
    # every point with every slope sample: one model call of n x m lanes
    sig = facet_signals(detectors, material, np.repeat(pts, m, axis=0), np.repeat(dirs, m, axis=0),
                        np.tile(-gx, n), np.tile(-gy, n), nodes=nodes)
    sigma = np.minimum(bound_from_signals(sig, noise)["sigma_worst"], SIGMA_CAP).reshape(n, m)
    centers = np.array([d.center for d in detectors.values()])
    masked, unsolvable = masked_shares(centers, pts, s_mask)
    return {"sigma_worst": float(sigma.max()), "sigma_median": float(np.median(sigma)),
            "sigma_flat": float(sigma[:, 0].max()), "masked_share": masked, "unsolvable_share": unsolvable,
            "signal_min": float(sig["flat"].sum(axis=0).reshape(n, m)[:, 0].min())}
