"""Surface gradient by inverting the 1st-event model per pixel (beyond Eq. 26).

Eq. 26 is exact for point detectors and Lambert's law; with the full g_BSE of Eq. 13 its specular
lobe (which follows the beam tilt across the field) biases the slopes by tens of per cent. Here each
pixel's facet normal n_S = [p, q, 1]/|.| (p = -dZ/dx, q = -dZ/dy, Eq. 16) is the one whose modelled
STSA-corrected images best match the four measured ones:

    minimise over (p, q, s):   sum_k ( C_k - s m_k(p, q) )^2,     m_k = S_k(n_S) / S_k(flat),

with S_k the 1st event of :class:`~.detector_model.FacetModel` (full g_BSE, exact C(theta), the
discs of the header or a calibration, the pixel's own beam direction and landing point) and s a
common scale (material contrast, beam-current drift). s is eliminated in closed form
(s = sum C m / sum m^2, variable projection); (p, q) follow Levenberg-Marquardt from the Eq. 26
start, with a forward-difference Jacobian, vectorised over all pixels in one Dr.Jit kernel per
iteration.

What it assumes: every pixel sees one flat facet (no shadowing by neighbours), a single-ray beam
(no blur), and only the 1st event (later events, e.g. a chamber's, enter the measured images but
not the model; a modelled 2nd event of the flat plate can be subtracted, ``flat_second_event``).
What breaks these shows in the per-pixel residual: pixels whose residual exceeds
:data:`RESIDUAL_SIGMAS` times the image's noise level are flagged ``model_residual``.

Uncertainty: with 4 values and 3 unknowns one degree of freedom is left per pixel; the noise level
sigma of the corrected images is taken from the median residual over the image (or given), and the
covariance of (p, q) is sigma^2 (J^T J)^-1.

Bias: the fit is nonlinear in the images, so their noise biases it, at second order by
b = 1/2 sum_k sigma_k^2 d^2 p / d C_k^2 (the same for q), with sigma_k proportional to detector k's
signal (the noise of a ratio of two recordings is relative). At the field's centre the detectors'
symmetry cancels it; off the centre it does not, and it grows with the distance: a slope bias of
about 1.3e-4 at the edge of an 80 mm field at 1 % noise on object and flat (zeta25), which integrates
into a bowl of micrometres that no noise seed averages away. ``noise_bias=True`` removes it per pixel
(:func:`_noise_bias`: two refits with the four values moved by +-:data:`BIAS_STEP` noise levels
under Hadamard signs that cancel the cross-terms over 2 x 2 pixels). Against the mean over the
noise by quadrature the correction leaves 1 % of the bias on tilted facets, 10 % on a level one
(tests/test_model_gradient.py). It is off by default because the fit has a second systematic error
of the opposite sign on sharp-walled relief, the beam blur it does not model: on the melt plate
(512^2, 0.27 mm beam) a bowl of -2.0 um without any noise, which the noise bias offsets at 1 %
noise, so that removing the noise bias alone took its start from 3.8 to 4.2 um (1500^2: 1.6 to
2.0 um), while on the rough layer (smooth at the beam's scale) it took the error away from the
defects from 4.91 to 4.66 um (ten noise seeds) and on the steep hills the start from 36 to 33 um
(docs/analysis.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..constants import DETECTOR_NAMES
from ..errors import EloInputError
from .detector_model import DEFAULT_NODES, FacetModel, to_vector
from .gradient import MASK_BITS, MIN_CORRECTED, GradientResult, surface_gradient
from .jit_arrays import floats
from .noise import check_noise, local_chi2
from .stsa import MIN_SUM, check_images

#: Levenberg-Marquardt iterations (each: one kernel of three model evaluations).
ITERATIONS = 10
#: Forward-difference step in p and q.
FD_STEP = 1e-3
#: A pixel stops when its accepted step in p and q is below this (float32 resolution of a slope ~1).
CONVERGED_STEP = 2e-6
#: Largest change of p or q in one step.
MAX_STEP = 0.5
#: A pixel whose residual exceeds this many noise levels is flagged ``model_residual``.
RESIDUAL_SIGMAS = 6.0
#: ... and never below this misfit sqrt(sum_k r_k^2) (corrected units, the flat plate's images are 1):
#: on noise-free renders facet interiors fit to < 1e-3 and pixels straddling a ridge to < 3e-3;
#: their fitted normal is the pixel's mean one, which integration needs. Only what no facet can
#: produce (shadowing, a detector blocked by a neighbour, strong later events) is masked.
MIN_RESIDUAL = 1e-2
#: Slopes beyond this are outside the model's range (a facet steeper than 80 deg).
MAX_SLOPE = 5.7
#: Relief (RMS of the first pass's integrated heights, mm) above which :func:`model_gradient_refined`
#: fits again with the landing points on the surface. With them at z = 0 the heights came out off
#: by 1.2-1.3 % of the relief's RMS, with them on the first pass's surface by 0.5 % (the hills scaled
#: to 0.08-1.0 mm RMS, 128^2, single-ray beam, no noise: 1.11 -> 0.43 um at 0.084 mm, 12.1 -> 5.1 um
#: at 1.0 mm); below this the first pass's error stays under 1 um. A pass costs about as much as the
#: first (1500^2: 3.9 s for one, 4.9 s for two).
AUTO_RELIEF_MM = 0.05
#: The fit's noise bias (:func:`_noise_bias`): each pixel refitted with its detectors' values moved
#: by +- this many noise levels. At 1 % noise the quadrature of tests/test_model_gradient.py leaves
#: 1 % of the bias on tilted facets with 1, 10 % on a level one (there the bias is 3e-5 and the
#: differences' fourth-order term -3e-6); with 1.5 / 2 / 3 that term grows to 18 / 26 / 47 %.
BIAS_STEP = 1.0
#: Levenberg-Marquardt iterations of each refit, from the fitted (p, q): with 4 the correction
#: differs from 10's by 1.2e-6 RMS (it is 1.8e-4 RMS itself; sine relief 0.3 mm, 400^2, 1 % noise).
BIAS_ITERATIONS = 4
#: Lanes per kernel launch of the refits (two per pixel): 4M floats per array.
BIAS_LANES = 1 << 22
#: Largest bias taken, in the slope's standard deviations: beyond, the fit is not smooth over the
#: noise's reach (a facet near a masking line). On the validation layers (400^2 and 512^2, 1 % noise
#: on object and flat) the per-pixel estimate is 0.001-0.005 of the standard deviation (median),
#: 0.04-0.23 (99th percentile), beyond 1 on 0.003 % of the steep hills' pixels and nowhere else.
BIAS_MAX = 1.0
#: median of chi^2 with one degree of freedom
_CHI2_1_MEDIAN = 0.454936


@dataclass
class ModelGradientResult(GradientResult):
    """:class:`GradientResult` plus what the model fit adds (arrays (H, W)).

    Attributes
    ----------
    residual : ndarray
        RMS misfit of the four corrected images, sqrt(sum_k r_k^2 / 4) (corrected units).
    dzdx_sigma, dzdy_sigma : ndarray
        One-sigma uncertainty of dZ/dx, dZ/dy from the noise level and the Jacobian.
    scale : ndarray
        The common scale s (1 for the flat plate's material and beam current).
    noise : float
        Noise level of the corrected images used for the uncertainty (estimated or given).
    iterations : int
        Levenberg-Marquardt iterations run.
    height_passes : int
        Fits run, each with the landing points on the heights of the one before
        (:func:`model_gradient_refined`).
    """

    residual: np.ndarray = None
    dzdx_sigma: np.ndarray = None
    dzdy_sigma: np.ndarray = None
    scale: np.ndarray = None
    noise: float = float("nan")
    iterations: int = 0
    height_passes: int = 1


def _fit(model, points, beam, measured, weights, flat_model, p0, q0, iterations, fd_step):
    """Levenberg-Marquardt on (p, q) for all pixels; returns numpy p, q, s, cost, J^T J terms and
    the modelled corrected images s m_k at the solution. ``weights`` (0 or 1 per detector and
    pixel) leave a masked detector out of the fit."""
    mi, dr = model.mi, model.dr
    Float = mi.Float

    def residuals(p, q, differences=True):
        """Residuals, cost and scale at (p, q) and, with ``differences``, at (p + h, q), (p, q + h):
        one loop over the nodes."""
        normals = [dr.normalize(mi.Vector3f(p, q, 1.0))]
        if differences:
            normals += [dr.normalize(mi.Vector3f(p + fd_step, q, 1.0)), dr.normalize(mi.Vector3f(p, q + fd_step, 1.0))]
        out = []
        for sig in model.signals(points, beam, normals):
            m = [s / f for s, f in zip(sig, flat_model)]
            smm = sum_(w * mk * mk for w, mk in zip(weights, m))
            s = dr.select(smm > 0, sum_(w * c * mk for w, c, mk in zip(weights, measured, m)) / smm, 0.0)
            r = [w * (c - s * mk) for w, c, mk in zip(weights, measured, m)]
            out.append((r, sum_(rk * rk for rk in r), s, m))
        return out

    def jacobian(r0, rp, rq):
        jp = [(a - b) * (1.0 / fd_step) for a, b in zip(rp, r0)]
        jq = [(a - b) * (1.0 / fd_step) for a, b in zip(rq, r0)]
        return (sum_(x * x for x in jp), sum_(x * x for x in jq), sum_(x * y for x, y in zip(jp, jq)),
                sum_(x * y for x, y in zip(jp, r0)), sum_(x * y for x, y in zip(jq, r0)))

    def cond(it, done, *state):
        return (it < iterations) & ~done

    def body(it, done, p, q, bp, bq, lam, best_cost, sb):
        (r0, cost, s, _), (rp, _, _, _), (rq, _, _, _) = residuals(p, q)
        # keep the step if it lowered the cost, else go back to the best point and damp more
        better = cost < best_cost
        a11, a22, a12, g1, g2 = jacobian(r0, rp, rq)
        d11 = a11 * (1.0 + lam) + 1e-12
        d22 = a22 * (1.0 + lam) + 1e-12
        det = d11 * d22 - a12 * a12
        dp = -(d22 * g1 - a12 * g2) / det
        dq = -(d11 * g2 - a12 * g1) / det
        step = dr.maximum(dr.abs(dp), dr.abs(dq))
        shrink = dr.select(step > MAX_STEP, MAX_STEP / step, 1.0)
        # a rejected step is retried from the best point, a tenth as long, with 10x the damping
        new_p = dr.select(better, p + dp * shrink, bp + (p - bp) * 0.1)
        new_q = dr.select(better, q + dq * shrink, bq + (q - bq) * 0.1)
        stuck = ~(dr.isfinite(new_p) & dr.isfinite(new_q))  # a singular step: stay at the best point
        new_p, new_q = dr.select(stuck, bp, new_p), dr.select(stuck, bq, new_q)
        lam = dr.select(better, lam * 0.3, lam * 10.0)
        bp, bq = dr.select(better, p, bp), dr.select(better, q, bq)
        sb = dr.select(better, s, sb)
        best_cost = dr.select(better, cost, best_cost)
        # a pixel whose accepted step is below float32 resolution stops iterating (its lanes idle)
        done = better & (step * shrink < CONVERGED_STEP)
        return (it + 1, done, dr.clip(new_p, -MAX_SLOPE, MAX_SLOPE), dr.clip(new_q, -MAX_SLOPE, MAX_SLOPE),
                bp, bq, lam, best_cost, sb)

    n_px = dr.width(p0)
    state = (dr.zeros(mi.UInt32, n_px), dr.full(mi.Bool, False, n_px), Float(p0), Float(q0), Float(p0), Float(q0), dr.full(Float, 1e-3, n_px),
             dr.full(Float, np.inf, n_px), dr.zeros(Float, n_px))
    # one symbolic loop: a single kernel for all iterations, cached by Dr.Jit between runs
    _, _, p, q, bp, bq, lam, best_cost, sb = dr.while_loop(state, cond, body, label="elo_model_gradient")
    ((_, cost, _, _),) = residuals(p, q, differences=False)
    # final: the best of the last trial and the stored best, with the Jacobian at that point
    use_new = cost < best_cost
    p, q = dr.select(use_new, p, bp), dr.select(use_new, q, bq)
    dr.eval(p, q)
    (r0, cost, s, m), (rp, _, _, _), (rq, _, _, _) = residuals(p, q)
    a11, a22, a12, _, _ = jacobian(r0, rp, rq)
    out = [p, q, s, cost, a11, a22, a12, *[s * mk for mk in m]]
    dr.eval(*out)
    return [np.asarray(v, dtype=np.float64) for v in out]


def _noise_bias(model, points, dirs, measured, weights, flat_model, p, q, noise, level, shape):
    """The fit's own bias at the images' noise ``noise`` (corrected units), detector k's noise being
    ``noise * level[k]``, to second order: b = 1/2 sum_k sigma_k^2 d^2 p / d C_k^2 (and the same of
    q). Each pixel is refitted twice from the fitted (p, q), with all its detectors' values moved by
    +- :data:`BIAS_STEP` noise levels, by the signs of one row of a 4 x 4 Hadamard matrix, the row
    set by the pixel's place in its 2 x 2 tile: the central difference of the two refits is
    sum_jk r_j r_k h_j h_k d^2 p / d C_j d C_k, and over the four rows the products r_j r_k of
    j != k cancel. What a single pixel keeps of them is a pattern at the Nyquist frequency, of the
    bias's own size (1e-4 at 1 % noise against the slope's scatter of 1e-2), which integration
    takes to nanometres. Two refits instead of the eight of the diagonal's own differences; both
    run in one kernel (their lanes side by side, :data:`BIAS_LANES` at most per launch). Numpy in
    and out: ``points``, ``dirs`` (N, 3); ``measured``, ``weights``, ``flat_model``, ``level``
    (K, N); ``p``, ``q`` (N,); ``shape`` the image's (N pixels in C order)."""
    mi = model.mi
    k_det, n_px = measured.shape
    hadamard = np.array([[1, 1, 1, 1], [1, -1, 1, -1], [1, 1, -1, -1], [1, -1, -1, 1]], float)[:, :k_det]
    rows, cols = np.indices(shape).reshape(2, -1)
    signs = hadamard[2 * (rows % 2) + cols % 2].T                      # (K, N)
    bias_p, bias_q = np.zeros(n_px), np.zeros(n_px)
    chunk = max(BIAS_LANES // 2, 1)
    for a in range(0, n_px, chunk):
        sl = slice(a, min(a + chunk, n_px))

        def both(v):  # (K, m) -> K arrays of 2 m lanes, the + move's then the - move's
            return np.tile(v[:, sl], (1, 2))
        move = BIAS_STEP * noise * level[:, sl] * signs[:, sl]
        moved = both(measured) + np.concatenate([move, -move], axis=1)
        pk, qk, *_ = _fit(model, mi.Point3f(to_vector(mi, np.tile(points[sl], (2, 1)))),
                          to_vector(mi, np.tile(dirs[sl], (2, 1))),
                          [floats(mi, v) for v in moved], [floats(mi, v) for v in both(weights)],
                          [floats(mi, v) for v in both(flat_model)], floats(mi, np.tile(p[sl], 2)),
                          floats(mi, np.tile(q[sl], 2)), BIAS_ITERATIONS, FD_STEP)
        m = sl.stop - sl.start
        scale = 0.5 / BIAS_STEP ** 2
        bias_p[sl] = scale * (pk.reshape(2, m) - p[sl]).sum(axis=0)
        bias_q[sl] = scale * (qk.reshape(2, m) - q[sl]).sum(axis=0)
    return bias_p, bias_q


def sum_(terms):
    terms = list(terms)
    acc = terms[0]
    for t in terms[1:]:
        acc = acc + t
    return acc


def model_gradient(images: Mapping, flats: Mapping | None, geometry, *, heights=None,
                   flat_second_event: Mapping | None = None, noise: float | None = None,
                   iterations: int = ITERATIONS, nodes=DEFAULT_NODES,
                   min_corrected: float = MIN_CORRECTED, min_sum: float = MIN_SUM,
                   geometric_margin: float = 0.0, start: GradientResult | None = None,
                   noise_bias: bool = False) -> ModelGradientResult:
    """Four detector images -> STSA correction -> per-pixel model fit -> gradient + mask.

    Parameters
    ----------
    images : mapping of str to ndarray (H, W)
        R, L, B, F of the object (keys ``right``, ``left``, ``back``, ``front``).
    flats : mapping or None
        Flat-plate images of the same detectors, beam and field; None if ``images`` are already
        STSA-corrected.
    geometry : ScanGeometry
        Field, beam, detectors (discs) and material (:mod:`.scan_geometry`).
    heights : ndarray (H, W), optional
        Surface heights (mm) for the landing points, e.g. integrated from a first pass
        (:func:`model_gradient_refined`); None: z = 0.
    flat_second_event : mapping of str to ndarray, optional
        Share of events >= 2 in each flat-plate image (e.g. ``e2 / (e1 + e2)`` of a render of the
        flat plate in the chamber). The flat's 1st event is then flat (1 - share) and the object's
        is taken as object - flat share (the chamber's 2nd event varies slowly over the field and
        little with the local slope).
    noise : float, optional
        Noise level (standard deviation) of the corrected images, for the uncertainty and the
        residual flag; None: estimated from the residuals.
    iterations : int
        Levenberg-Marquardt iterations.
    nodes : (int, int)
        Disc rule of the model.
    min_corrected, min_sum, geometric_margin : float
        Mask thresholds as in :func:`~.gradient.surface_gradient`.
    start : GradientResult, optional
        The starting gradient (default: Eq. 26 of the same images).
    noise_bias : bool
        Remove the fit's own bias at the images' noise level (:func:`_noise_bias`; a second-order
        correction, two more refits of each pixel in one kernel). Off by default: on sharp-walled
        relief it uncovers the opposite bias of the fit's missing beam blur (module docstring).

    Returns
    -------
    ModelGradientResult

    Examples
    --------
    A tilted plane dZ/dx = 0.1 in images of the point-detector model with the paper's g_BSE,
    fitted with the nominal geometry (field 20 mm, d_h = 272 mm, d_w = 127 mm):

    >>> import numpy as np
    >>> from elo_mitsuba.analysis import flat_plate_images, point_detector_images
    >>> from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    >>> shape, field, d_h, d_w = (4, 4), 20.0, 272.0, 127.0
    >>> kw = dict(model="g_bse", detector_radius_mm=25.0)
    >>> flats = flat_plate_images(shape, field, d_h, d_w, **kw)
    >>> images = point_detector_images(np.full(shape, 0.1), np.zeros(shape), field, d_h, d_w, **kw)
    >>> result = model_gradient(images, flats, ScanGeometry.nominal(shape, field, d_h, d_w))
    >>> type(result).__name__, result.dzdx.shape, bool(result.mask.any())
    ('ModelGradientResult', (4, 4), False)
    >>> round(float(result.dzdx.mean()), 2), round(float(result.dzdy.mean()), 2) + 0.0
    (0.1, 0.0)
    """
    from ..arguments import fraction, real_array, shown, whole_number

    whole_number("iterations", iterations, 1, 1000)
    if not isinstance(noise_bias, (bool, np.bool_)):
        raise EloInputError(f"noise_bias={shown(noise_bias)}: must be True or False")
    fraction("min_corrected", min_corrected)
    fraction("min_sum", min_sum, 0.0, 2.0)  # R^C + L^C is 2 on a flat plate
    fraction("geometric_margin", geometric_margin)
    if not hasattr(geometry, "detectors") or not hasattr(geometry, "field_mm"):
        raise EloInputError("geometry: must be a ScanGeometry (analysis.scan_geometry)")
    if noise is not None:
        noise = check_noise(noise)
    d_h, d_w = geometry.symmetric_layout()
    images = check_images(images, "object images" if flats is not None else "corrected images")
    if heights is not None:
        heights = real_array("heights", heights, shape=tuple(geometry.shape))
        if not np.all(np.isfinite(heights)):
            raise EloInputError("heights: hold NaN or Inf; need a height (mm) at every pixel")
    if start is not None and not all(hasattr(start, k) for k in ("dzdx", "dzdy", "mask")):
        raise EloInputError(f"start={shown(start)}: must be a GradientResult (dzdx, dzdy, mask), e.g. of surface_gradient")
    if flat_second_event is not None:
        if flats is None:
            raise EloInputError("flat_second_event needs the flat-plate images")
        flat_second_event = check_images(flat_second_event, "flat_second_event")
        share = {n: np.clip(flat_second_event[n], 0.0, 0.99) for n in DETECTOR_NAMES}
        flats = {n: np.asarray(flats[n], float) * (1.0 - share[n]) for n in DETECTOR_NAMES}
        images = {n: np.asarray(images[n], float) - np.asarray(flats[n]) * share[n] / (1.0 - share[n])
                  for n in DETECTOR_NAMES}
    eq26 = surface_gradient(images, flats, geometry.field_mm, d_h, d_w, min_corrected=min_corrected,
                            min_sum=min_sum, geometric_margin=geometric_margin)
    shape = eq26.dzdx.shape
    if tuple(shape) != tuple(geometry.shape):
        raise EloInputError(f"images are {shape[1]}x{shape[0]} px, the scan geometry {geometry.shape[1]}x"
                            f"{geometry.shape[0]}; they must describe one scan")
    start = eq26 if start is None else start

    model = FacetModel(geometry.detectors, geometry.material, nodes=nodes)
    mi, dr = model.mi, model.dr
    points, dirs = geometry.beam(heights)
    beam = to_vector(mi, dirs)
    pts = mi.Point3f(to_vector(mi, points))
    if heights is None:  # the flat plate lands where the object does
        flat_pts, flat_beam = pts, beam
    else:
        flat_points, flat_dirs = geometry.beam(None)
        flat_pts, flat_beam = mi.Point3f(to_vector(mi, flat_points)), to_vector(mi, flat_dirs)
    flat_model = model.signals(flat_pts, flat_beam, [mi.Vector3f(0.0, 0.0, 1.0)])[0]
    dr.eval(flat_model)
    # float32 as the kernels see them: the noise bias's refits move these values
    measured_np = np.stack([np.asarray(eq26.corrected[n], np.float32).ravel() for n in model.names]).astype(float)
    measured = [floats(mi, v) for v in measured_np]
    # a detector the facet hides from (corrected image ~0) is left out: three values still fix
    # p, q and s; the model must then agree that it sees (almost) nothing (checked below)
    dark = np.stack([np.asarray(eq26.corrected[n]) <= min_corrected for n in model.names])
    n_dark = dark.sum(axis=0)
    one_dark = n_dark == 1
    weights_np = np.stack([np.where(one_dark, ~dark[k], True).ravel() for k in range(len(model.names))]).astype(float)
    weights = [floats(mi, v) for v in weights_np]
    p0 = np.where(start.mask, 0.0, -start.dzdx)
    q0 = np.where(start.mask, 0.0, -start.dzdy)
    if one_dark.any():
        # start just past the masking line of the hidden detector (n_S . d = -0.2 in p,q-form)
        for k, name in enumerate(model.names):
            sel = one_dark & dark[k]
            if sel.any():
                c = np.asarray(geometry.detectors[name].center)
                dz = c[2] - points[..., 2]
                dx, dy = (c[0] - points[..., 0]) / dz, (c[1] - points[..., 1]) / dz
                t = 1.2 / np.maximum(dx * dx + dy * dy, 1e-6)
                p0 = np.where(sel, -t * dx, p0)
                q0 = np.where(sel, -t * dy, q0)
    p0 = np.clip(p0, -MAX_SLOPE * 0.9, MAX_SLOPE * 0.9).astype(np.float32).ravel()
    q0 = np.clip(q0, -MAX_SLOPE * 0.9, MAX_SLOPE * 0.9).astype(np.float32).ravel()
    p, q, s, cost, a11, a22, a12, *predicted = _fit(model, pts, beam, measured, weights, flat_model, floats(mi, p0),
                                                    floats(mi, q0), int(iterations), FD_STEP)
    det = a11 * a22 - a12 * a12

    residual = np.sqrt(np.maximum(cost, 0.0) / 4.0).reshape(shape)
    four = ~(eq26.reasons & (MASK_BITS["invalid_input"] | MASK_BITS["detector_dark"] | MASK_BITS["sum_small"])
             ).astype(bool)
    usable = four | (one_dark & ~(eq26.reasons & MASK_BITS["invalid_input"]).astype(bool))
    if noise is None:
        # residual^2 * 4 = sum r^2 ~ sigma^2 chi^2_1 (4 values, 3 unknowns): four-detector pixels
        sel = (residual * 2.0)[four]
        noise = float(np.sqrt(np.median(sel ** 2) / _CHI2_1_MEDIAN)) if sel.size else float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):
        var_p = np.where(det > 0, a22 / det, np.inf) * noise ** 2
        var_q = np.where(det > 0, a11 / det, np.inf) * noise ** 2
    if noise_bias and np.isfinite(noise) and noise > 0:
        fitted = np.stack(predicted)
        mean = np.mean(fitted, axis=0)
        level = np.where(mean > 0, np.maximum(fitted, 0.0) / np.where(mean > 0, mean, 1.0), 1.0)
        bias_p, bias_q = _noise_bias(model, points.reshape(-1, 3), np.asarray(dirs).reshape(-1, 3), measured_np,
                                     weights_np, np.stack([np.asarray(v, float) for v in flat_model]), p, q, noise,
                                     level, shape)
        # the expansion holds where the bias is small against the slope's own scatter; beyond, the
        # fit is not smooth over the noise's reach (a facet near a masking line, a refit that left
        # for another minimum) and its bias is not known
        valid = (np.isfinite(bias_p) & np.isfinite(bias_q) & (bias_p ** 2 <= BIAS_MAX ** 2 * var_p)
                 & (bias_q ** 2 <= BIAS_MAX ** 2 * var_q))
        p, q = np.where(valid, p - bias_p, p), np.where(valid, q - bias_q, q)
    # where the facet model does not reproduce the four values to within the noise (the beam
    # straddling a pore's rim, a step), the noise-only bound is scaled by the local Birge ratio
    birge = np.sqrt(np.maximum(local_chi2(np.where(np.isfinite(residual), 2.0 * residual, 0.0),
                                          noise if np.isfinite(noise) and noise > 0 else 1.0), 1.0))
    sigma_p = np.sqrt(var_p).reshape(shape) * birge
    sigma_q = np.sqrt(var_q).reshape(shape) * birge
    dzdx = -p.reshape(shape)
    dzdy = -q.reshape(shape)
    limit = max(RESIDUAL_SIGMAS * (noise if np.isfinite(noise) else 0.0), MIN_RESIDUAL)
    bad_fit = ~np.isfinite(residual) | (residual * 2.0 > limit)
    # the hidden detector: the model at the fitted facet must see (almost) nothing either, else
    # something else hides it (a neighbour's shadow) and the three values are not this facet's
    pred_dark = np.max(np.where(dark, np.stack([v.reshape(shape) for v in predicted]), 0.0), axis=0)
    bad_fit |= one_dark & (pred_dark > 2.0 * min_corrected + limit)
    # solvable: a regular Jacobian (the noise level may be unknown: no pixel with four detectors)
    unsolved = ~(det > 0).reshape(shape) | ~np.isfinite(det).reshape(shape) | (np.abs(p.reshape(shape)) >= MAX_SLOPE) \
        | (np.abs(q.reshape(shape)) >= MAX_SLOPE) | ~np.isfinite(dzdx) | ~np.isfinite(dzdy)

    geo_mask = np.zeros(shape, dtype=bool)
    pts = points.reshape(shape + (3,))
    n = np.stack([p.reshape(shape), q.reshape(shape), np.ones(shape)], axis=-1)
    n_hidden = np.zeros(shape, dtype=int)
    for disc in geometry.detectors.values():
        to_det = np.asarray(disc.center) - pts
        cos = np.sum(n * to_det, axis=-1) / (np.linalg.norm(n, axis=-1) * np.linalg.norm(to_det, axis=-1))
        geo_mask |= cos <= geometric_margin
        n_hidden += cos <= geometric_margin
    # the fitted facet may hide at most the one detector left out
    geo_mask = np.where(one_dark, n_hidden > 1, geo_mask)
    keep = MASK_BITS["invalid_input"] | MASK_BITS["detector_dark"] | MASK_BITS["sum_small"]
    # one hidden detector is solved from the other three: not a reason to mask (nor is the
    # geometric masking of that detector, which is what hides it)
    solved3 = one_dark & ~bad_fit
    eq26_reasons = np.where(solved3, eq26.reasons & MASK_BITS["invalid_input"], eq26.reasons & keep)
    reasons = (eq26_reasons + MASK_BITS["geometric"] * geo_mask
               + MASK_BITS["model_residual"] * (bad_fit & usable)
               + MASK_BITS["not_solved"] * (unsolved & usable)).astype(np.uint8)
    mask = reasons != 0
    z = np.zeros(shape)

    def clean(a):
        return np.where(mask | ~np.isfinite(a), 0.0, a)

    return ModelGradientResult(
        dzdx=clean(dzdx), dzdy=clean(dzdy), mx=eq26.mx, my=eq26.my, sum_x=eq26.sum_x, sum_y=eq26.sum_y,
        mask=mask, reasons=reasons, corrected=eq26.corrected,
        residual=np.where(np.isfinite(residual), residual, 0.0), dzdx_sigma=clean(sigma_p), dzdy_sigma=clean(sigma_q),
        scale=np.where(mask, z, s.reshape(shape)), noise=float(noise), iterations=int(iterations))


def model_gradient_refined(images, flats, geometry, *, passes: int | None = None, **kw) -> ModelGradientResult:
    """:func:`model_gradient`, then again with the landing points on the integrated heights.

    Pass 2 moves each landing point onto the surface reconstructed from pass 1 (normal
    integration, :func:`~.integrate.integrate_gradient`, its mean set to 0): the beam lands off its
    z = 0 aim point and the detectors are seen from another height. ``passes`` None: a second pass
    where the first pass's relief exceeds :data:`AUTO_RELIEF_MM` RMS and its heights resolve it
    (:func:`.sampling_check.resolution_warning` says nothing): on relief the scan does not resolve
    the integrated heights are further off than z = 0. The corrugated sheet's slopes of exactly
    +-1 came out 7e-4 off (median) with one pass, 2.3e-3 with two at 256^2 and 3.8e-3 at 40^2,
    where its heights err by 0.4 mm RMS against a relief of +-0.35 mm.
    """
    from .integrate import integrate_gradient
    from .sampling_check import resolution

    if passes is not None and (isinstance(passes, bool) or passes not in (1, 2, 3)):
        raise EloInputError(f"passes={passes!r}: choose 1, 2, 3 or None (auto)")
    done, want = 1, None if passes is None else int(passes)
    bias = kw.pop("noise_bias", False)
    # a pass known not to be the last only places the landing points: the heights its noise bias
    # tilts by a few micrometres over the field are a thousandth of the detectors' distance
    res = model_gradient(images, flats, geometry, noise_bias=bias and (want is None or want == 1), **kw)
    while want is None or done < want:
        height, _ = integrate_gradient(res.dzdx, res.dzdy, geometry.field_mm, mask=res.mask)
        keep = ~res.mask if (~res.mask).any() else np.ones(res.mask.shape, bool)
        height = height - np.mean(height[keep])
        if want is None:
            if np.sqrt(np.mean(height[keep] ** 2)) <= AUTO_RELIEF_MM:
                break
            if resolution(res.dzdx, res.dzdy, geometry.field_mm, height, res.mask,
                          lambda gx, gy, field, m: integrate_gradient(gx, gy, field, mask=m))["warning"]:
                break
            want = 2
        done += 1
        res = model_gradient(images, flats, geometry, heights=height, start=res, noise_bias=bias and done == want, **kw)
    res.height_passes = done
    return res
