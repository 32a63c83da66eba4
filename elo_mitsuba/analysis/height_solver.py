"""The objective of inverse ELO imaging and its Gauss-Newton solve over one field (the solver of
:func:`~.inversion.invert_heights`, of its local refinement and of its step search).

The unknowns are the heights on the scan grid; the forward model is
:class:`~.height_model.HeightModel`, differentiated by Dr.Jit:

    minimise over g:   sum_px,k rho( C_k - s M_k(g) )  +  alpha/2 sum |L g / d|^2

* C_k = I_k / F_k, the STSA-corrected measured images (object over flat plate, Eq. 15: gains and
  the flat's eta cancel); M_k(h) = B_k(h) / B_k(flat) the same ratio of the model's images.
* s: a scale per pixel (material contrast, beam-current drift), eliminated in closed form at every
  step (s = sum C M / sum M^2), as in the model gradient.
* Shadowing is evaluated at every step and held fixed within it (it has no derivative).
* rho: Huber's norm with threshold :data:`HUBER_K` noise levels (a pixel that no surface of the
  model explains, e.g. a spatter particle, pulls with a bounded force); the noise level comes from
  the images' second differences (:func:`estimate_noise`) or is given.
* g: the heights at the pixels' corners (:mod:`.height_model`); the result is their cubic
  interpolation at the pixel centres (:func:`~.height_model.pixels_from_corners`).
* The regulariser: second differences of g along rows and columns, divided by the pixel pitch
  (the change of slope from one pixel to the next), weighted by ``alpha`` in corrected-image units
  squared (default :data:`ALPHA_PER_NOISE2` noise variances). The images do not see the corner
  checkerboard; the regulariser fixes it. Planes cost nothing (border differences vanish).

Gauss-Newton: at each step the model and its per-pixel derivatives (forward-mode AD over each
pixel's four corners) are evaluated once, and the scale s is projected out of them (variable
projection); the normal equations are solved matrix-free by conjugate gradients, preconditioned by their constant-coefficient (cosine-transform) version, which
makes the long wavelengths, hard for plain CG, as cheap as the short ones. A step is taken only if
it lowers the objective (halved up to :data:`LINE_SEARCH` times otherwise): the result is never
worse, in the objective, than the start. A start that already reproduces the images to within
their noise is returned as it is (Morozov's discrepancy principle, :data:`DISCREPANCY`: the steps
would fit the noise). Otherwise it stops when a step lowers the objective by less than ``tol``
(relative), after ``iterations`` steps, or when the time budget is spent.

The height uncertainty (:func:`height_uncertainty`): white noise of the images' level drawn
:data:`UNCERTAINTY_PROBES` times and propagated through the normal equations at the solution, so
that a user sees how many micrometres of the height map the noise alone leaves, pixel by pixel.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from ..grid import pixel_size
from .jit_arrays import floats
from .noise import MIN_FLAT, estimate_noise
from .stsa import spike_bound
from .height_model import (HeightModel, SuperResolvedModel, corners_from_pixels,
                           pixels_from_corners)

#: Disc rule of the model: its 16 nodes also resolve a disc's partial shadowing (the RMS
#: difference to the renderer on a shadowed relief: 7.0 % with (1, 4), 3.5 % with (2, 8); tests/).
NODES = (2, 8)
#: Gauss-Newton steps at most (per scale).
ITERATIONS = 10
#: Scales of the coarse-to-fine solve (factors 8, 4, 2, then full resolution), run when the solve
#: at full resolution alone does not reproduce the images to within their noise, and kept if it
#: ends at a lower objective: the coarse scales fit the long wavelengths first, where shadows
#: decided at a wrong start otherwise hold the solve (hills under 15 deg detectors, 256^2: misfit
#: 0.039 against a noise of 0.015 and 168 um after 10 steps at full resolution, 160 um after 20;
#: 82 um coarse to fine). Not run first: where full resolution alone fits to the noise, coarse to
#: fine can fit it as well with another filling of the shadowed pixels (model images at 128^2:
#: 63 um alone, 83 um coarse to fine).
SCALES = 4
#: ... each with at least this many pixels on the shorter side.
MIN_SCALE_PX = 32
#: Conjugate-gradient iterations per Gauss-Newton step (the preconditioned system converges fast: at
#: 512^2, 10 iterations leave 7e-5 of the step, 20 leave 3e-8).
CG_ITERATIONS = 12
#: Stop when a step lowers the objective by less than this fraction.
TOL = 5e-3
#: Morozov's discrepancy principle, at the start: a start whose modelled images already reproduce
#: the measured ones to within the noise, i.e. whose residual RMS is at most this factor times
#: what the true surface itself would leave, noise x sqrt(1 - 1/detectors) (the per-pixel scale
#: takes one datum per pixel), is returned as it is: the images hold nothing it does not explain,
#: and the steps would fit the noise. On the melt plate at 1 % noise the integrated model gradient
#: leaves 0.0120 against 0.0124 expected of the truth, and ten steps to 0.0111 raised the height
#: error from 3.9 to 4.3 um (validation row I2). Not applied between steps: on the steep hills the
#: first step already reaches 0.78 noise levels while the next five still lower the height error
#: from 8.7 to 4.9 um (row I3); there the regulariser, not the misfit, separates relief from noise.
#: With later events held fixed from renders, their Monte Carlo error (``later_error``,
#: ``flat_later_error``) is part of what the truth would leave. The factor is 5 % above 1, as the
#: principle wants it (tau > 1): neither the noise level (its estimate from second differences
#: was 0.6 % high on the melt plate) nor the model (its own accuracy, :data:`MIN_NOISE`) is exact;
#: at exactly 1 the melt plate at 1500^2, whose start leaves 0.01236 against 0.01232, was refined
#: from 1.6 to 2.0 um.
DISCREPANCY = 1.05
#: Weight of the curvature regulariser per noise variance: alpha = ALPHA_PER_NOISE2 sigma^2
#: (corrected-image units^2 per (slope change per pixel)^2). Chosen on model images of a random
#: relief (0.3-1 % noise, beam FWHM 0-3 px) and checked on renders: a tenth to ten times it moves
#: the hills' error by < 6 %, the melt plate's by < 15 % (validation rows I2, I3).
ALPHA_PER_NOISE2 = 30.0
#: ... and never below this (noise-free images still leave the corner checkerboard to fix).
MIN_ALPHA = 1e-6
#: The largest weight a user may give: 30 x noise^2 is at most 30 (noise <= 1), and at 1e6 the
#: curvature already flattens any relief; 1e300 overflowed the float32 preconditioner.
MAX_ALPHA = 1e6
#: Noise level assumed at least (corrected units): the model's own accuracy (discretisation of the
#: surface, the disc rule, the beam blur's mixing), measured as the misfit RMS the true heights leave
#: on noise-free renders (0.27 mm beam, --quality default): 1.6e-3 on the rough layer, 1.8e-3 on
#: the melt plate, 4.5e-3 on the hills (their penumbrae); a noise-free render is not fitted below it,
#: and the regulariser weighs it as noise (at 1e-3 the noise-free melt plate was fitted to 1.0 um,
#: at 2e-3 to 0.9 um against 1.6 um for the start).
MIN_NOISE = 2e-3
#: Noise draws propagated through the solution for its height uncertainty
#: (:func:`height_uncertainty`; each costs one CG solve, about a Gauss-Newton step). The image's
#: RMS is what they fix well: on the melt plate at 512^2 it varies by 1.0 % over four seeds with 4
#: draws and by 1.1 % with 8; a pixel's own value has a relative error of about 1/sqrt(2 draws),
#: which costs coverage: within 2x of height_error 89-93 % of pixels with 4 draws, 91-95 % with 8,
#: 93-96 % with 16 on the four surfaces of validation/study_defects.py (steps, hills, rough layer,
#: melt plate); the melt plate at 1500^2 inverts in 265 s with 8 (regions included).
UNCERTAINTY_PROBES = 8
#: Threads the probes are solved in at most (each adds about 0.15 GB at 1500^2: four probes took
#: 0.76 GB in one thread, 1.19 GB in four).
MAX_PROBE_THREADS = 4
#: Huber threshold, in noise levels.
HUBER_K = 2.0
#: Step halvings tried when a full step does not lower the objective.
LINE_SEARCH = 4
#: A pixel whose misfit exceeds this many noise levels is untrusted (the model does not reproduce
#: its images: a later event the model holds wrong, a partly shadowed disc, a feature below the
#: pixel pitch) ...
MISFIT_SIGMAS = 4.0
#: ... and never below this misfit (corrected units).
MIN_MISFIT = 5e-3
#: A robust curvature penalty where a region's images demand relief that the quadratic one flattens
#: (:func:`solve_robust`, the local refinement at defects): each curvature term is weighted by
#: Cauchy's 1 / (1 + (kappa / kappa_0)^2), kappa the change of slope at that corner and kappa_0 this
#: many times the median over the window, reweighted :data:`ROBUST_ROUNDS` times (iteratively
#: reweighted least squares). Measured on the rough layer (400^2, 0.27 mm beam, 1 % noise, 2 x 2
#: sub-pixel facets), error within 1 mm of the pores and bumps (start 11.9 um): quadratic 9.2 um;
#: Huber's weight at 1x / 3x the median 6.5 / 6.7 um; Cauchy's at 1.5x / 3x 7.6 / 6.2 um (1.5x
#: frees the noise's curvature too: the bumps went 6 -> 11 um).
ROBUST_SCALE = 3.0
#: Reweightings of :func:`solve_robust` (3: 6.2 um as above; 6: 6.3 um).
ROBUST_ROUNDS = 3
#: The robust pass is taken only where some curvature term's weight would fall below this (a
#: change of slope beyond 3 kappa_0, :func:`frees_curvature`): elsewhere it has nothing to free and
#: costs its solves. The smallest weight on the quadratic refinement's heights (one facet a pixel):
#: on the rough layer's 11 regions (pores and bumps, 400^2) 0.004-0.038; on the melt plate's 7
#: (512^2, at the melt squares' rims) 0.077-0.23, where the pass had taken 30 s and left the heights
#: as they were (3.8 um).
ROBUST_FREE = 0.05


@dataclass
class InversionResult:
    """What :func:`~.inversion.invert_heights` returns (and :func:`solve_field`, without the fields it fills
    after the field's solve).

    Attributes
    ----------
    height : ndarray (H, W)
        Heights (mm) where each pixel's beam lands, package orientation.
    start_height : ndarray (H, W)
        The starting heights.
    misfit : ndarray (H, W)
        RMS over the detectors of C_k - s M_k at the solution (corrected units).
    predicted : dict of str to ndarray
        The modelled corrected images s M_k at the solution.
    scale : ndarray (H, W)
        The per-pixel scale s.
    mask : ndarray of bool (H, W)
        Untrusted pixels: misfit above :data:`MISFIT_SIGMAS` noise levels (or a pixel without
        weight, e.g. a dark flat).
    noise : float
        The noise level used for Huber's norm (corrected units).
    alpha : float
        The regulariser's weight used.
    history : list of dict
        Per Gauss-Newton step: iteration, objective, rms misfit, step length, seconds.
    stopped : str
        Why it stopped (``converged``, ``iterations``, ``time budget``, ``no descent``, ``fits to
        the noise at the start``; and whether coarse to fine ran).
    discrepancy_level : float
        The residual RMS below which the images count as reproduced to within their noise
        (:data:`DISCREPANCY` times what the true surface would leave).
    height_error : ndarray (H, W) or None
        Standard error (mm) of each height, relative to the image mean: the noise's part
        (``height_error_noise``) scaled, where the model does not reproduce the images to within
        their noise, by the square root of the misfit's local chi-square per datum
        (:func:`~.noise.local_chi2` of ``misfit`` over ``expected_misfit``; Birge's ratio, taken
        locally, never below 1), and in quadrature the regulariser's bias (``height_error_bias``),
        the model's slope gain (``height_error_model``) and the uncertainty of a ``floating`` part's
        offset.
        None with ``uncertainty_probes=0``.
    height_error_rms : float
        Its RMS over the image (mm; NaN when not computed).
    floating : ndarray of bool (H, W) or None
        Parts of the field that bands of misfit above the noise (a cliff) cut off from its largest
        part, or bands of steep slope where the misfit is above the noise on part of them (a small
        cliff, :func:`~.step_offsets.edge_parts`): their offset to it is not measured by the
        slopes, and ``height_error`` holds the
        offset as recovered (:func:`~.step_offsets.offset_errors`), or, where the part was lifted
        to the step its shadows show, that step's uncertainty (:mod:`.step_offsets`).
    height_error_noise : ndarray (H, W) or None
        The noise's part alone (:func:`height_uncertainty`): the height error the images' noise
        leaves, pixel by pixel.
    height_error_bias : ndarray (H, W) or None
        The magnitude of the regulariser's bias (:func:`regulariser_bias`), in ``height_error``
        in quadrature.
    height_error_model : ndarray (H, W) or None
        The model's systematic part, :data:`MODEL_SLOPE_GAIN` times the height above or below the
        mean, in ``height_error`` in quadrature.
    start_misfit : ndarray (H, W) or None
        The misfit of the start, as ``misfit``.
    expected_misfit : float
        The misfit RMS per pixel the true surface would leave (the noise less the datum the scale
        takes, the held-fixed later events' error): ``discrepancy_level`` without the factor.
    regions : list of Region
        The local refinement's regions (:mod:`.local_inversion`); empty when it did not run.
    steps : list of StepOffset
        The floating parts whose offset was searched in their shadows (:mod:`.step_offsets`), each
        ``lifted`` or ``kept``; empty when none floated or the local refinement did not run.
    sampling : dict or None
        With a single-ray beam and a gradient as the start: whether the scan resolves the relief
        (:func:`~.inversion.start_resolution`: ``half_sampling_mm``, ``relief_rms_mm``,
        ``warning``, ``flag``); where it warns, ``half_sampling_mm`` is in ``height_error`` in
        quadrature.
    bowl : dict or None
        Where the heights hold a field-wide bowl larger than their relief
        (:func:`~.inversion.bowl_check`: ``bowl_mm``, ``relief_mm``, ``warning``, ``flag``); the
        bowl is then in ``height_error`` in quadrature.
    """

    height: np.ndarray
    start_height: np.ndarray
    misfit: np.ndarray
    predicted: dict
    scale: np.ndarray
    mask: np.ndarray
    noise: float
    alpha: float
    history: list = field(default_factory=list)
    stopped: str = ""
    discrepancy_level: float = 0.0
    height_error: np.ndarray | None = None
    height_error_rms: float = float("nan")
    height_error_noise: np.ndarray | None = None
    height_error_bias: np.ndarray | None = None
    height_error_model: np.ndarray | None = None
    floating: np.ndarray | None = None
    start_misfit: np.ndarray | None = None
    expected_misfit: float = 0.0
    regions: list = field(default_factory=list)
    steps: list = field(default_factory=list)
    sampling: dict | None = None
    bowl: dict | None = None
    #: what :func:`height_uncertainty` needs of the solution, dropped once it has run
    _linearised: tuple | None = field(default=None, repr=False, compare=False)


# ---- the objective ------------------------------------------------------------------------------
def _second_differences(h):
    """Second differences along columns and rows; 0 on the border (the border is free: a plane
    there costs nothing)."""
    lx, ly = np.zeros_like(h), np.zeros_like(h)
    lx[:, 1:-1] = h[:, :-2] + h[:, 2:] - 2.0 * h[:, 1:-1]
    ly[1:-1] = h[:-2] + h[2:] - 2.0 * h[1:-1]
    return lx, ly


def _second_differences_t(vx, vy):
    """The transpose of :func:`_second_differences` (the border's values do not enter)."""
    out = np.zeros_like(vx)
    ix, iy = vx[:, 1:-1], vy[1:-1]
    out[:, :-2] += ix
    out[:, 2:] += ix
    out[:, 1:-1] -= 2.0 * ix
    out[:-2] += iy
    out[2:] += iy
    out[1:-1] -= 2.0 * iy
    return out


def _huber(r, k):
    """Huber's loss of each residual: r^2 / 2 within k, k (|r| - k / 2) beyond (c = min(|r|, k):
    c (c / 2 - k) + k |r|, one branch-free expression)."""
    a = np.abs(r)
    c = np.minimum(a, k)
    return c * (0.5 * c - k) + k * a


def _huber_weights(r, k):
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-30))


class _Problem:
    """The objective at one scan: measured ratios, weights, the model and the flat's model."""

    def __init__(self, model, corrected, weights, flat_images, alpha, dx, dy, free=None, links=None):
        self.model = model
        self.free = free  # (corners) bool: the unknowns that may change; None: all (mean held)
        self.links = links  # (corners) weight of each curvature term (cut across a cliff); None: 1
        self.c = corrected            # (K, H, W)
        self.w = weights              # (K, H, W) 0/1
        self.bf = flat_images         # (K, H, W)
        self.alpha = float(alpha)
        self.dx, self.dy = dx, dy

    def scan_heights(self, corners):
        """Heights at the scan pixels' centres from the model's corner heights."""
        if isinstance(self.model, SuperResolvedModel):
            return self.model.scan_heights(corners)
        return pixels_from_corners(corners)

    def start_corners(self, h0):
        """The model's corner heights from scan-pixel heights (cubic; on the fine grid upsampled first)."""
        if isinstance(self.model, SuperResolvedModel):
            f = self.model.factor
            return corners_from_pixels(upsample(h0, f, self.model.shape))
        return corners_from_pixels(h0)

    def ratios(self, lin):
        return lin.images / self.bf

    def fit_scale(self, m):
        smm = np.sum(self.w * m * m, axis=0)
        scm = np.sum(self.w * self.c * m, axis=0)
        return np.where(smm > 0, np.maximum(scm, 0.0) / np.where(smm > 0, smm, 1.0), 0.0)

    def regulariser(self, h):
        lx, ly = _second_differences(h)
        k = 1.0 if self.links is None else self.links
        return 0.5 * self.alpha * (float(np.sum(k * (lx / self.dx) ** 2)) + float(np.sum(k * (ly / self.dy) ** 2)))

    def cost(self, h, lin, threshold):
        """Objective with Huber's threshold ``threshold`` (corrected units), residuals, scale, ratios."""
        m = self.ratios(lin)
        s = self.fit_scale(m)
        r = self.w * (self.c - s * m)
        return float(np.sum(_huber(r, threshold))) + self.regulariser(h), r, s, m


def _preconditioner(shape, cx, cy, cc, alpha, dx, dy, sigma_px):
    """The inverse of the normal equations on the corner grid with constant coefficients, diagonal
    in the DCT-II basis: the patch's slopes transfer 2 sin(w/2) cos(w'/2), its centre height
    cos(w/2) cos(w'/2), the beam profile exp(-(sigma w)^2 / 2) each."""
    h, w = shape
    wy = np.pi * np.arange(h) / h
    wx = np.pi * np.arange(w) / w
    gy = np.exp(-0.5 * (sigma_px[0] * wy) ** 2)
    gx = np.exp(-0.5 * (sigma_px[1] * wx) ** 2)
    sy, sx = np.sin(wy / 2)[:, None], np.sin(wx / 2)[None, :]
    ky, kx = np.cos(wy / 2)[:, None], np.cos(wx / 2)[None, :]
    blur2 = (gy[:, None] * gx[None, :]) ** 2
    data = blur2 * (4.0 * cx * (sx * ky) ** 2 + 4.0 * cy * (sy * kx) ** 2 + cc * (kx * ky) ** 2)
    lap = (4.0 * sy ** 2) ** 2 / dy ** 2 + (4.0 * sx ** 2) ** 2 / dx ** 2
    eig = data + alpha * lap
    eig = eig + 1e-9 * max(float(eig.max()), 1e-30)
    eig[0, 0] = np.inf  # the mean height is not changed (the images hardly see it)
    inv = (1.0 / eig).astype(np.float32)

    def apply(v):
        from scipy.fft import dctn, idctn

        # every core, in float32 like the products it preconditions: at 1500^2 the two transforms
        # were a third of a CG iteration in one thread, and on the 1501^2 corner grid (a slow FFT
        # size) float32 takes 0.05 s against 0.12 s
        t = dctn(np.asarray(v, np.float32), norm="ortho", workers=-1)
        t *= inv
        return idctn(t, norm="ortho", workers=-1).astype(float)

    return apply


class _NormalEquations:
    """The Gauss-Newton normal equations at one linearisation, (J^T W J + alpha L^T L) x = b,
    solved matrix-free by preconditioned CG.

    J is the derivative of the residual with the scale s eliminated (Kaufman's form of variable
    projection): s dm/dh projected, per pixel and in the W inner product over the detectors,
    orthogonally to m. A change that brightens all detectors alike is taken up by s and does not
    count; without the projection the steps are several times too short on relief."""

    def __init__(self, problem: _Problem, lin, s, m, weights):
        self.problem, self.lin, self.m = problem, lin, m
        self.wt = problem.w * weights  # W per (k, px)
        self.g = s / problem.bf
        wmm = np.sum(self.wt * m * m, axis=0)
        self.wmm = np.where(wmm > 0, wmm, 1.0)
        tl, tr, bl, br = lin.partials  # d/d corner, STENCIL order
        f = self.wt * self.g * self.g
        if f.shape[1:] != lin.partials.shape[2:]:  # sub-pixels: each carries 1/r^2 of its pixel's data
            r = lin.partials.shape[2] // f.shape[1]
            f = np.repeat(np.repeat(f, r, axis=1), r, axis=2) / (r ** 4)
        coef = [float(np.mean(np.sum(f * a ** 2, axis=0))) for a in
                (0.5 * (tr + br - tl - bl), 0.5 * (tl + tr - bl - br), tl + tr + bl + br)]
        corners = tuple(n + 1 for n in lin.partials.shape[2:])
        self.precond = _preconditioner(corners, coef[0], coef[1], coef[2], problem.alpha, problem.dx,
                                       problem.dy, problem.model.sigma_px)
        # the products' factors as Dr.Jit arrays, once per linearisation
        from ..runtime import ensure_variant

        self._mi = ensure_variant()
        self._corner_shape = corners
        self._g = self._to_dr(np.broadcast_to(self.g, m.shape))
        # m normalised per pixel (sum_k W m^2 = 1): the projection m (m^T W u) / (m^T W m) without a
        # 1 / (m^T W m) that float32 cannot hold where the model's images are faint
        m_unit = m / np.sqrt(self.wmm)
        self._m = self._to_dr(m_unit)
        self._wt_m = self._to_dr(self.wt * m_unit)
        self._gw = self._to_dr(self.g * self.wt)

    def _to_dr(self, a) -> list:
        mi = self._mi
        return [floats(mi, x) for x in a]

    def _weighted_projection(self, u: list) -> list:
        """g W (u - m (m^T W u) / (m^T W m)) per pixel, in Dr.Jit (K Floats)."""
        along = sum(wm * x for wm, x in zip(self._wt_m, u))
        return [gw * (x - m * along) for gw, m, x in zip(self._gw, self._m, u)]

    def _corners_np(self, c) -> np.ndarray:
        return np.asarray(c, np.float32).reshape(self._corner_shape).astype(float)

    def data_rhs(self, r):
        """J^T W r of residuals (or data perturbations) r (K, H, W)."""
        return self._corners_np(self.problem.model.jacobian_t_dr(self.lin, self._weighted_projection(self._to_dr(r))))

    def regulariser_gradient(self, h):
        """alpha L^T L h."""
        p = self.problem
        lx, ly = _second_differences(h)
        k = 1.0 if p.links is None else p.links
        return p.alpha * _second_differences_t(k * lx / p.dx ** 2, k * ly / p.dy ** 2)

    def apply(self, v):
        """(J^T W J + alpha L^T L) v, the data term in Dr.Jit (float32; one pass of gathers each way)."""
        model = self.problem.model
        if self.problem.free is not None:
            v = v * self.problem.free
        ju = model.jacobian_dr(self.lin, floats(self._mi, v))
        q = self._weighted_projection([g * x for g, x in zip(self._g, ju)])
        out = self._corners_np(model.jacobian_t_dr(self.lin, q)) + self.regulariser_gradient(v)
        return out if self.problem.free is None else out * self.problem.free

    def solve(self, rhs, cg_iterations):
        """x with zero mean (the mean height is not changed: the images hardly see it); with fixed
        corners (``problem.free``) zero on them instead, the CG run in the free subspace."""
        free = self.problem.free

        def precond(v):
            return self.precond(v) if free is None else self.precond(v * free) * free

        x = np.zeros_like(rhs)
        res = rhs.copy() if free is None else rhs * free
        z = precond(res)
        p = z.copy()
        rz = float(np.sum(res * z))
        r0 = np.sqrt(float(np.sum(res * res)))
        for _ in range(int(cg_iterations)):
            ap = self.apply(p)
            pap = float(np.sum(p * ap))
            if not pap > 0:
                break
            a = rz / pap
            x += a * p
            res -= a * ap
            if np.sqrt(float(np.sum(res * res))) < 1e-4 * r0:
                break
            z = precond(res)
            rz_new = float(np.sum(res * z))
            p = z + (rz_new / rz) * p
            rz = rz_new
        return x - x.mean() if free is None else x


def _solve_step(problem: _Problem, h, lin, r, s, m, weights, cg_iterations):
    """Gauss-Newton step: (J^T W J + alpha L^T L) dh = J^T W r - alpha L^T L h."""
    eq = _NormalEquations(problem, lin, s, m, weights)
    return eq.solve(eq.data_rhs(r) - eq.regulariser_gradient(h), cg_iterations)


def height_uncertainty(eq: _NormalEquations, sigma: float, probes: int, cg_iterations: int, seed: int = 0):
    """Standard error (mm) of each pixel's height, relative to the image mean, that noise of level
    ``sigma`` in the corrected images leaves in the solution (its linearisation ``eq``).

    The noise propagated through one Gauss-Newton solve, dh = (J^T W J + alpha L^T L)^-1 J^T W e,
    estimated from ``probes`` draws of white noise e (each one CG solve): its variance per pixel is
    the mean of dh^2 (the relative error of a pixel's estimate is about 1/sqrt(2 probes); the
    image's RMS is much better determined). What it leaves out: the bias of the regulariser and of
    the model, and a noisy start's own error where the start is kept (it has the same noise part
    to the extent that the start is an efficient estimate)."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(seed)
    n = int(probes)

    def propagated(z):
        dh = eq.problem.scan_heights(eq.solve(eq.data_rhs(sigma * eq.problem.w * z), cg_iterations))
        return (dh - dh.mean()) ** 2

    # the probes are independent solves whose numpy work releases the GIL: on two cores four probes
    # at 1500^2 took 20.9 s in four threads and 38.6 s in one, with identical results; drawn and
    # summed in order, as many at a time as there are threads (a draw is 72 MB at 1500^2)
    threads = max(1, min(n, os.cpu_count() or 1, MAX_PROBE_THREADS))
    acc = np.zeros(eq.problem.c.shape[1:])
    with ThreadPoolExecutor(threads) as pool:
        for first in range(0, n, threads):
            draws = [rng.standard_normal(eq.problem.c.shape) for _ in range(min(threads, n - first))]
            for term in pool.map(propagated, draws):
                acc += term
    return np.sqrt(acc / max(n, 1))


def _held_fixed_variance(corrected, img, flt, weights, names, later_error, flat_later_error) -> float:
    """Mean variance, in corrected units, that the Monte Carlo errors of the held-fixed later events
    give the model's ratio (object over flat): C^2 ((e_o / I)^2 + (e_f / F)^2) over the weighted
    data, with the measured images standing in for the model's."""
    total = np.zeros_like(corrected)
    for errors, base in ((later_error, img), (flat_later_error, flt)):
        if errors is None:
            continue
        e = np.stack([np.asarray(errors[n], float) if n in errors else np.zeros(base.shape[1:]) for n in names])
        total += np.where(weights > 0, (corrected * e / np.where(base > 0, base, 1.0)) ** 2, 0.0)
    return float(np.sum(total) / max(np.sum(weights), 1.0))


#: Weight of the curvature terms that cross a band of misfit around a floating part (a cliff): not
#: 0, so that the part's offset stays where the field's solve put it rather than in a null space.
CUT_LINK = 1e-3
#: The cut's heights are taken only if the trusted pixels further than this from the bands fit
#: better with them.
CUT_BESIDE_PX = 2


def pixel_corners(pixels) -> np.ndarray:
    """The corners (H + 1, W + 1) of the pixels ``pixels`` (H, W): the curvature terms they touch.

    Examples
    --------
    >>> pixel_corners(np.array([[True, False]])).astype(int).tolist()
    [[1, 1, 0], [1, 1, 0]]
    """
    pixels = np.asarray(pixels, bool)
    out = np.zeros((pixels.shape[0] + 1, pixels.shape[1] + 1), bool)
    for di in (0, 1):
        for dj in (0, 1):
            out[di:di + pixels.shape[0], dj:dj + pixels.shape[1]] |= pixels
    return out


def cut_across(setup: _Setup, result: InversionResult, band, settings) -> None:
    """Solve again with the band's pixels out of the data and the curvature terms across it cut
    (:data:`CUT_LINK`), so that a cliff's wrongly integrated offset does not bend the relief
    around it; ``result`` takes the new heights (with misfit, scale and predicted images of the full
    data) if the trusted pixels beyond :data:`CUT_BESIDE_PX` of the bands fit better with them (the cut
    objective falls whatever the bands hold: on the melt plate without noise the bands at the melt
    squares' rims were cut and the map's error rose from 0.645 to 0.697 um; on a raised square
    whose lift the search refused, tests/test_local_inversion.py, the square stayed 15.9 um off
    against 9.1 um uncut).

    Over the whole field, not in windows around the bands: the bands' misfit bends the field at
    long wavelengths too. Measured on the stepped layer (400^2), windows of 4 or 8 mm saved 16 s
    but left a bend of +-7 um across the field that the whole-field cut removes (median error on
    the trusted pixels 2.7 against 1.5 um; height_error within 1x / 2x on 50 / 75 % of pixels
    against 71 / 93 %)."""
    from scipy.ndimage import binary_dilation

    p = setup.problem
    links = np.where(binary_dilation(pixel_corners(band)), CUT_LINK, 1.0)
    w = np.where(band[None], 0.0, p.w)
    cut = _Problem(p.model, p.c, w, p.bf, p.alpha, p.dx, p.dy, free=p.free, links=links)
    res = _solve_scale(dataclasses.replace(setup, problem=cut), result.height, result.start_height, **settings)
    if len(res.history) < 2 or res.stopped.endswith("start kept"):
        result.stopped += "; cut across the cliffs: no step"
        return
    # the cut objective falls whatever the band holds; what a wrong offset did is bend the relief
    # beside it, so the relief beside it must fit better (a melt square's rim is no cliff)
    trial = dataclasses.replace(result)
    take_heights(setup, trial, res.height)
    beside = ~binary_dilation(band, iterations=CUT_BESIDE_PX) & ~result.mask
    if beside.any() and np.mean(trial.misfit[beside] ** 2) >= np.mean(result.misfit[beside] ** 2):
        result.stopped += "; cut across the cliffs: kept (the relief beside them fitted no better)"
        return
    for name in ("height", "misfit", "scale", "predicted", "mask"):  # what take_heights set on the trial
        setattr(result, name, getattr(trial, name))
    result.stopped += f"; cut across the cliffs: {len(res.history) - 1} steps"


def take_heights(setup: _Setup, result: InversionResult, heights) -> None:
    """``result`` takes the pixel heights ``heights`` with the misfit, scale, predicted images and
    mask of the full data there."""
    p = setup.problem
    corners_h = p.start_corners(heights)
    _, r, s_, m = p.cost(corners_h, p.model.evaluate(corners_h), HUBER_K * setup.noise)
    result.height = np.array(heights, float)
    result.misfit = np.sqrt(np.sum(r ** 2, axis=0) / np.maximum(np.sum(p.w, axis=0), 1.0))
    result.scale = s_
    result.predicted = {n: s_ * m[k] for k, n in enumerate(setup.names)}
    result.mask = (result.misfit > max(MISFIT_SIGMAS * setup.noise, MIN_MISFIT)) | (np.sum(p.w, axis=0) < 3)


def data_term(images: Mapping, flats: Mapping, geometry, *, fwhm_mm: float, noise: float, alpha: float,
              later: Mapping | None = None, flat_later: Mapping | None = None, nodes=NODES,
              factor: int = 1) -> Callable[[np.ndarray], float]:
    """The objective's data term (Huber's norm of the corrected residuals, without the regulariser)
    as a function of the model's corner heights, on a surface ``factor`` times finer than the scan,
    with the shadowing evaluated at each call: for searches that Gauss-Newton steps cannot make (a
    cliff's shadow has no derivative; :mod:`.step_offsets`).

    Examples
    --------
    >>> from .scan_geometry import ScanGeometry
    >>> geo = ScanGeometry.nominal((16, 16), 3.2, 100.0, 150.0)
    >>> flat = HeightModel(geo, shadows=False).images(np.zeros((16, 16)))
    >>> term = data_term(flat, flat, geo, fwhm_mm=0.0, noise=0.01, alpha=1e-3)
    >>> term(corners_from_pixels(np.zeros((16, 16)))) < 1e-12
    True
    """
    setup = _set_up(ScaleData(images, flats, later, flat_later, None, None), geometry, fwhm_mm=fwhm_mm,
                    alpha=alpha, noise=noise, shadows=True, nodes=nodes, factor=int(factor))
    problem, k = setup.problem, HUBER_K * setup.noise

    def value(corners) -> float:
        _, r, _, _ = problem.cost(corners, problem.model.evaluate(corners), k)
        return float(np.sum(_huber(r, k)))
    return value


def misfit_of(setup: _Setup, heights) -> np.ndarray:
    """The misfit (RMS over the detectors, per pixel) of pixel heights ``heights``."""
    problem = setup.problem
    corners = problem.start_corners(heights)
    _, r, _, _ = problem.cost(corners, problem.model.evaluate(corners), HUBER_K * setup.noise)
    return np.sqrt(np.sum(r ** 2, axis=0) / np.maximum(np.sum(problem.w, axis=0), 1.0))


def _with_uncertainty(result: InversionResult, probes: int, cg_iterations: int) -> InversionResult:
    """The result with its ``height_error`` (``probes`` > 0) and without the linearisation it kept."""
    state, result._linearised = result._linearised, None
    if probes > 0 and state is not None:
        problem, corners, visible, r, s, m, k, sigma = state
        lin = problem.model.evaluate(corners, derivatives=True, visible=visible)
        eq = _NormalEquations(problem, lin, s, m, _huber_weights(r, k))
        result.height_error = height_uncertainty(eq, sigma, probes, cg_iterations)
        result.height_error_rms = float(np.sqrt(np.mean(result.height_error ** 2)))
        result.height_error_bias = np.abs(regulariser_bias(eq, corners, cg_iterations))
    return result


def regulariser_bias(eq: _NormalEquations, corners, cg_iterations: int) -> np.ndarray:
    """The regulariser's bias (mm) at the solution ``corners``, relative to the image mean:
    linearised, the solution is (J^T W J + alpha L^T L)^-1 J^T W J of the truth, so it misses it by
    -(J^T W J + alpha L^T L)^-1 alpha L^T L h, evaluated at the solution (one CG solve). It is what
    the curvature penalty flattens: on the steep hills (slopes to 1.26) the inversion's 4.9 um
    error is twice what the noise leaves, with a misfit at the noise level."""
    return -eq.problem.scan_heights(eq.solve(eq.regulariser_gradient(corners), cg_iterations))


class ScaleData:
    """The measured images (and held-fixed later events with their errors) at one scale."""

    def __init__(self, images, flats, later, flat_later, later_error, flat_later_error):
        self.images, self.flats = images, flats
        self.later, self.flat_later = later, flat_later
        self.later_error, self.flat_later_error = later_error, flat_later_error

    def coarse(self, f):
        """The same data averaged over blocks of f x f pixels (errors of a mean of f^2 pixels)."""
        def mean(d, scale=1.0):
            return None if d is None else {n: block_mean(np.asarray(v, float), f) * scale for n, v in d.items()}
        return ScaleData(mean(self.images), mean(self.flats), mean(self.later), mean(self.flat_later),
                          mean(self.later_error, 1.0 / f), mean(self.flat_later_error, 1.0 / f))


def scale_factors(shape, scales: int) -> list[int]:
    """The coarse scales of a solve, coarsest first: factors 2^k (k < ``scales``) that divide the
    image and leave at least :data:`MIN_SCALE_PX` pixels on its shorter side."""
    out = []
    # no factor above the shorter side's can leave MIN_SCALE_PX pixels: scales=2^63 asked for 2^(2^63)
    top = min(max(int(scales), 1) - 1, max(min(shape) // MIN_SCALE_PX, 1).bit_length() - 1)
    for k in range(top, 0, -1):
        f = 1 << k
        if shape[0] % f == 0 and shape[1] % f == 0 and min(shape) // f >= MIN_SCALE_PX:
            out.append(f)
    return out


def block_mean(a, f: int) -> np.ndarray:
    """Mean over blocks of f x f pixels (the image's size a multiple of f)."""
    h, w = a.shape
    return np.asarray(a, float).reshape(h // f, f, w // f, f).mean(axis=(1, 3))


def upsample(h, f: int, shape) -> np.ndarray:
    """Heights of a grid f times coarser, interpolated (cubic) at the pixel centres of ``shape``."""
    from scipy.ndimage import map_coordinates

    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    return map_coordinates(np.asarray(h, float), [(yy + 0.5) / f - 0.5, (xx + 0.5) / f - 0.5], order=3,
                           mode="nearest")


@dataclass
class _Setup:
    """The objective at one scale, as the solves from different starts share it: the problem, the
    noise level and the variance the held-fixed later events add to what the truth would leave."""

    problem: _Problem
    noise: float
    model_var: float
    names: tuple


def _set_up(data, geometry, *, fwhm_mm, alpha, noise, shadows, nodes, factor=1, fixed_border=0) -> _Setup:
    """Corrected images, weights, the flat's and the object's models at one scale; ``factor``
    sub-pixels per pixel and axis (:class:`~.height_model.SuperResolvedModel`), the heights within
    ``fixed_border`` pixels of the edge held at the start's."""
    shape = tuple(geometry.shape)
    names = tuple(geometry.detectors)
    images, flats, later, flat_later = data.images, data.flats, data.later, data.flat_later
    dx, dy = pixel_size(shape, geometry.field_mm)
    img = np.stack([np.asarray(images[n], float) for n in names])
    flt = np.stack([np.asarray(flats[n], float) for n in names])
    floor = MIN_FLAT * np.median(flt, axis=(1, 2), keepdims=True)
    # a pixel that is not finite, or saturated or glitched (above SPIKE x its image's median),
    # weighs nothing: the command line refuses such images, the Python API leaves them out
    bound = np.array([[[spike_bound(x)]] for x in (*img, *flt)])
    good = (np.isfinite(img) & np.isfinite(flt) & (flt > floor)
            & (np.abs(img) <= bound[:len(names)]) & (np.abs(flt) <= bound[len(names):]))
    corrected = np.where(good, img / np.where(good, flt, 1.0), 0.0)
    weights = good.astype(float)
    flat_model = HeightModel(geometry, fwhm_mm=fwhm_mm, later=flat_later, shadows=False, nodes=nodes)
    bf = flat_model.evaluate(np.zeros((shape[0] + 1, shape[1] + 1))).images.astype(float)
    if factor > 1:
        model = SuperResolvedModel(geometry, factor, fwhm_mm=fwhm_mm, later=later, shadows=shadows, nodes=nodes)
        dx, dy = dx / factor, dy / factor
    else:
        model = HeightModel(geometry, fwhm_mm=fwhm_mm, later=later, shadows=shadows, nodes=nodes)
    free = None
    if fixed_border > 0:
        b = int(fixed_border) * int(factor)
        free = np.zeros((model.shape[0] + 1, model.shape[1] + 1))
        free[b:free.shape[0] - b, b:free.shape[1] - b] = 1.0
    if noise is None:
        noise = max(estimate_noise(corrected, weights), MIN_NOISE)
    if alpha is None:
        alpha = max(ALPHA_PER_NOISE2 * noise ** 2, MIN_ALPHA)
    problem = _Problem(model, corrected, weights, np.maximum(bf, 1e-12), alpha, dx, dy, free=free)
    # the residual RMS of the true surface: the noise, less the datum per pixel the scale takes,
    # and the Monte Carlo error of the held-fixed later events in the model's ratio
    model_var = _held_fixed_variance(corrected, img, flt, weights, names, data.later_error, data.flat_later_error)
    return _Setup(problem, float(noise), model_var, names)


def _solve_scale(setup: _Setup, h0, start_height, *, iterations, cg_iterations, tol, discrepancy, budget,
                 progress, t0, scale=1, corners=None) -> InversionResult:
    """Gauss-Newton at one scale (:func:`_set_up`) from the pixel heights ``h0`` (or from the model's
    corner heights ``corners``, whose scan heights ``h0`` must be); ``start_height`` is what the
    result reports as its start."""
    problem, noise, model_var, names = setup.problem, setup.noise, setup.model_var, setup.names
    model, weights, alpha = problem.model, problem.w, problem.alpha
    g0 = problem.start_corners(h0) if corners is None else np.array(corners, float)
    h = g0.copy()  # the unknowns: corner heights
    k = HUBER_K * noise
    lin = model.evaluate(h)  # derivatives only if a step is taken
    start_cost, r, s, m = problem.cost(h, lin, k)
    start_state = (start_cost, r, s, m)
    start_visible = h_visible = lin.visible  # the shadowing at the start, at the current heights
    cost = start_cost
    history = [{"iteration": 0, "objective": cost, "rms": float(np.sqrt(np.mean(r[weights > 0] ** 2))),
                "step": 0.0, "seconds": time.perf_counter() - t0, "scale": scale}]
    if progress:
        progress(history[-1])
    enough = discrepancy * np.sqrt(noise ** 2 * (1.0 - 1.0 / len(names)) + model_var)
    stopped = "iterations"
    if history[-1]["rms"] <= enough:
        stopped, iterations = "fits to the noise at the start", 0
    if iterations > 0:
        lin = model.evaluate(h, derivatives=True, visible=lin.visible)
    for it in range(1, int(iterations) + 1):
        hw = _huber_weights(r, k)
        dh = _solve_step(problem, h, lin, r, s, m, hw, cg_iterations)
        tau, accepted = 1.0, False
        for _ in range(LINE_SEARCH + 1):
            if not np.all(np.isfinite(dh)):
                break
            trial = h + tau * dh
            tlin = model.evaluate(trial)
            tcost, tr, ts, tm = problem.cost(trial, tlin, k)
            if tcost < cost:
                accepted = True
                break
            tau *= 0.5
        if not accepted:
            stopped = "no descent"
            break
        gain = (cost - tcost) / max(abs(cost), 1e-300)
        h, h_visible = trial, tlin.visible
        cost, r, s, m = tcost, tr, ts, tm
        history.append({"iteration": it, "objective": cost, "rms": float(np.sqrt(np.mean(r[weights > 0] ** 2))),
                        "step": float(tau * np.sqrt(np.mean(dh ** 2))), "tau": tau, "seconds": time.perf_counter() - t0,
                        "scale": scale})
        if progress:
            progress(history[-1])
        if gain < tol:
            stopped = "converged"
            break
        if budget is not None and time.perf_counter() - t0 > budget:
            stopped = "time budget"
            break
        if it < iterations:
            # the shadowing of these heights was found by the line search: not marched again
            lin = model.evaluate(h, derivatives=True, visible=tlin.visible)
    kept = history[-1]["objective"] >= start_cost
    if kept:  # no step was taken (each is kept only if it lowers the objective)
        h = g0.copy()
        _, r, s, m = start_state
        stopped += "" if stopped.startswith("fits") else ", start kept"
    misfit = np.sqrt(np.sum(r ** 2, axis=0) / np.maximum(np.sum(weights, axis=0), 1.0))
    predicted = {n: (s * m[k]) for k, n in enumerate(names)}
    mask = (misfit > max(MISFIT_SIGMAS * noise, MIN_MISFIT)) | (np.sum(weights, axis=0) < 3)
    # a kept start is returned as given
    visible = start_visible if kept else h_visible
    return InversionResult(height=h0.copy() if kept else problem.scan_heights(h), start_height=start_height,
                           misfit=misfit, predicted=predicted, scale=s, mask=mask, noise=float(noise),
                           alpha=float(alpha), history=history, stopped=stopped, discrepancy_level=float(enough),
                           _linearised=(problem, h, visible, r, s, m, k, float(np.sqrt(noise ** 2 + model_var))))


def robust_links(corners, dx: float, dy: float, where, scale: float = ROBUST_SCALE) -> np.ndarray:
    """Weights (corners) of the curvature terms for :func:`solve_robust`: Cauchy's
    1 / (1 + (kappa / kappa_0)^2) at the corners of the pixels ``where`` (on the model's grid), 1
    elsewhere; kappa = |(second differences along x / dx, along y / dy)| at ``corners``, kappa_0 =
    ``scale`` times its median over the grid (the relief's own curvature, which stays penalised).

    Examples
    --------
    >>> g = 0.01 * np.add.outer(np.sin(np.arange(9.0)), np.cos(np.arange(9.0)))   # a gentle relief
    >>> g[4, 4] -= 1.0                                  # and a pit one corner deep
    >>> w = robust_links(g, 1.0, 1.0, np.ones((8, 8), bool))
    >>> float(w[4, 4]) < 1e-3, 0.5 < float(w[2, 6]) < 1.0, float(w[0, 0])   # freed at the pit only
    (True, True, 1.0)
    >>> float(robust_links(g, 1.0, 1.0, np.zeros((8, 8), bool))[4, 4])
    1.0
    """
    lx, ly = _second_differences(np.asarray(corners, float))
    kappa = np.hypot(lx / dx, ly / dy)
    curved = kappa[kappa > 0]
    kappa0 = scale * float(np.median(curved)) if curved.size else 0.0
    weights = 1.0 / (1.0 + (kappa / kappa0) ** 2) if kappa0 > 0 else np.ones_like(kappa)
    return np.where(pixel_corners(where), weights, 1.0)


def frees_curvature(heights, pixel_mm, where, free: float = ROBUST_FREE) -> bool:
    """Whether the robust penalty would free a curvature term at the pixels ``where`` of the pixel
    heights ``heights`` (:func:`robust_links` of their corners below ``free``): a pit or peak whose
    change of slope lies beyond 3 kappa_0.

    Examples
    --------
    >>> h = 0.01 * np.add.outer(np.sin(np.arange(12.0)), np.cos(np.arange(12.0)))
    >>> everywhere = np.ones((12, 12), bool)
    >>> frees_curvature(h, (0.2, 0.2), everywhere)
    False
    >>> h[6, 6] -= 0.3
    >>> frees_curvature(h, (0.2, 0.2), everywhere)
    True
    """
    links = robust_links(corners_from_pixels(np.asarray(heights, float)), pixel_mm[0], pixel_mm[1], where)
    return bool(np.min(links) < free)


def solve_robust(setup: _Setup, result: InversionResult, where, settings: dict,
                 rounds: int = ROBUST_ROUNDS) -> InversionResult:
    """From ``result`` (a solve of ``setup``), the solve again with the curvature penalty robust at
    the pixels ``where`` (scan grid): ``rounds`` times, each with the weights of
    :func:`robust_links` at the previous round's corners (iteratively reweighted least squares).
    The quadratic penalty flattens a pit or a peak a few pixels wide, whose curvature is far beyond
    the relief's around it, in proportion to that curvature; Cauchy's weight lets the data decide
    there. The last round's result, its objective with the last weights."""
    p = setup.problem
    f = p.model.factor if isinstance(p.model, SuperResolvedModel) else 1
    fine = np.kron(np.asarray(where, bool), np.ones((f, f), bool)) if f > 1 else np.asarray(where, bool)
    out = result
    for _ in range(int(rounds)):
        corners = out._linearised[1] if out._linearised is not None else p.start_corners(out.height)
        links = robust_links(corners, p.dx, p.dy, fine)
        robust = dataclasses.replace(setup, problem=_Problem(p.model, p.c, p.w, p.bf, p.alpha, p.dx, p.dy,
                                                             free=p.free, links=links))
        out = _solve_scale(robust, p.scan_heights(corners), result.start_height, corners=corners, **settings)
    out.stopped = f"{result.stopped}; robust curvature ({int(rounds)} reweightings): {out.stopped}"
    return out


def solve_field(data: ScaleData, geometry, h0, *, fwhm_mm: float, alpha, noise, shadows: bool, nodes,
                super_resolution: int = 1, fixed_border: int = 0, scales: int = SCALES, iterations: int = ITERATIONS,
                cg_iterations: int = CG_ITERATIONS, tol: float = TOL, discrepancy: float = DISCREPANCY,
                budget: float | None = None, progress=None, t0: float | None = None,
                uncertainty_probes: int = 0, robust=None) -> tuple[InversionResult, _Setup]:
    """Solve the whole field from the pixel heights ``h0`` (inputs checked by the caller).

    At full resolution first; if that does not reproduce the images to within their noise, coarse
    to fine (:func:`scale_factors`) from the same start, kept if it ends at a lower objective (the
    discrepancy principle decides); both full-resolution solves share one set-up. Then the noise's
    part of the height error (``uncertainty_probes`` draws), the start's misfit and the misfit the
    true surface would leave. With ``robust`` (a pixel mask), the solve goes on with a robust
    curvature penalty at those pixels (:func:`solve_robust`), and the height error is that solve's.

    Returns
    -------
    result : InversionResult
    setup : _Setup
        The full-resolution objective, for what the caller does next with the same data.
    """
    t0 = time.perf_counter() if t0 is None else t0
    shape = tuple(geometry.shape)
    model_settings = dict(fwhm_mm=fwhm_mm, alpha=alpha, shadows=shadows, nodes=nodes)
    settings = dict(cg_iterations=cg_iterations, tol=tol, discrepancy=discrepancy, progress=progress,
                    iterations=iterations, budget=budget, t0=t0)
    full = _set_up(data, geometry, noise=noise, factor=int(super_resolution), fixed_border=int(fixed_border),
                   **model_settings)
    result = single = _solve_scale(full, h0, h0, **settings)
    factors = scale_factors(shape, scales)
    if factors and single.history[-1]["rms"] > single.discrepancy_level and (
            budget is None or time.perf_counter() - t0 <= budget):
        h, done, previous = None, [], None
        for f in factors:  # coarse to fine: the long wavelengths first, where shadows cannot trap them
            coarse = dataclasses.replace(geometry, shape=(shape[0] // f, shape[1] // f))
            start_c = block_mean(h0, f) if h is None else upsample(h, previous // f, coarse.shape)
            previous = f
            res = _solve_scale(_set_up(data.coarse(f), coarse, noise=None if noise is None else noise / f,
                                       **model_settings), start_c, start_c, scale=f, **settings)
            h, res._linearised = res.height, None
            done.append(f"1/{f}: {len(res.history) - 1} steps")
        fine = _solve_scale(full, upsample(h, previous, shape), h0, **settings)
        if fine.history[-1]["objective"] >= single.history[-1]["objective"]:
            single.stopped += f" (coarse to fine ended higher: {', '.join(done)})"
        else:
            fine.stopped += f" (coarse to fine: {', '.join(done)}, then 1/1; at full resolution alone the misfit " \
                            f"stayed at {single.history[-1]['rms']:.4g})"
            result = fine
    if robust is not None and np.any(robust) and iterations > 0:
        result = solve_robust(full, result, robust, settings)
    result = _with_uncertainty(result, uncertainty_probes, cg_iterations)
    result.start_misfit = misfit_of(full, h0)
    result.expected_misfit = float(result.discrepancy_level / discrepancy) if discrepancy > 0 else float(
        np.sqrt(full.noise ** 2 * (1.0 - 1.0 / len(full.names)) + full.model_var))
    return result, full
