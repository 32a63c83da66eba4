"""The height map whose modelled images match the measured ones (inverse ELO imaging): the
pipeline of ``invert``.

Per-pixel gradients (:mod:`.model_gradient`) assume that each pixel sees one flat facet under a
single-ray beam, and integrating them afterwards forgets that the four images come from *one*
surface. Here the unknowns are the heights themselves, and the forward model is
:class:`~.height_model.HeightModel` (the 1st event of the renderer's g_BSE on disc detectors,
shadowing, the beam profile, fixed later events), differentiated by Dr.Jit. In order:

1. The start: the model gradient, integrated (:func:`start_heights`), or heights given.
2. The field's solve (:func:`~.height_solver.solve_field`; the objective, Gauss-Newton, the
   discrepancy principle and the noise's part of the height error are described there).
3. Where the misfit stays above the noise, region by region, a finer solve in a window
   (:mod:`.local_inversion`); a region never ends worse than its start.
4. Parts of the field that bands of misfit cut off (a cliff) are searched for the step their
   shadows show (:mod:`.step_offsets`), and the field is solved again with the curvature terms
   across the bands cut (:func:`~.height_solver.cut_across`).
5. The error bars: the noise's part scaled by the local misfit where it exceeds the noise, the
   regulariser's bias, the model's slope gain (:data:`MODEL_SLOPE_GAIN`) and a floating part's
   offset, in quadrature; what a single-ray scan leaves open (:func:`start_resolution`) and a
   field-wide bowl larger than the relief (:func:`bowl_check`) where they are found.

When the field's solve took steps, the correction of the start that all of this made is kept
only where the start's misfit exceeds the noise, elsewhere its long wavelengths only; where kept,
its band finer than the beam only where the correction as the beam sees it leaves a misfit above
the noise (:mod:`.fine_band`).
"""

from __future__ import annotations

import time
from typing import Callable, Mapping

import numpy as np

from ..budget import check_inversion
from ..constants import DETECTOR_NAMES
from ..errors import EloInputError
from ..grid import pixel_size
from ..schema import FWHM_RANGE, is_fwhm
from .height_solver import (CG_ITERATIONS, DISCREPANCY, ITERATIONS, MAX_ALPHA, NODES, SCALES, TOL, UNCERTAINTY_PROBES,
                            InversionResult, ScaleData, cut_across, solve_field, take_heights)
from .fine_band import band_weight, beam_px, gated, half_wavelength, low_pass_px
from .local_inversion import refine_regions, threshold
from .noise import check_noise, local_chi2
from .quadric import bowl_exceeds, fit_quadric
from .step_offsets import offset_errors, search_offsets
from .stsa import check_images

#: Relative accuracy of the model's slope response, a systematic of every height it returns: the
#: model of Sec. 2 and the renderer disagree on a facet's slope by 0.13-0.51 % (validation row G1,
#: 9 facets of slope 0.2-1; RMS 0.39 %, taken as the standard error), and a gain error k on every
#: slope makes the heights k (h - mean h) off. In ``height_error`` as ``height_error_model`` =
#: k |h - mean h|, in quadrature: it matters where the relief spans millimetres (the hills' heights
#: came out 0.14-0.26 % low at 128^2-256^2, with and without perspective, noise and the reference
#: quality, a bias the misfit cannot see) and is below 0.5 um on relief of +-0.1 mm.
MODEL_SLOPE_GAIN = 4e-3


def _fill_masked(a, mask, sigma=3.0):
    """Masked values replaced by a Gaussian-weighted mean of the trusted ones nearby (normalised
    convolution, widened until every pixel has neighbours)."""
    from scipy.ndimage import gaussian_filter

    if not mask.any():
        return a
    good = (~mask).astype(float)
    if not good.any():
        return np.zeros_like(a)
    out = np.array(a, float)
    s = sigma
    todo = mask.copy()
    while todo.any() and s < 4 * max(a.shape):
        num = gaussian_filter(np.where(mask, 0.0, a), s, mode="nearest")
        den = gaussian_filter(good, s, mode="nearest")
        ok = todo & (den > 1e-6)
        out[ok] = num[ok] / den[ok]
        todo &= ~ok
        s *= 2.0
    out[todo] = 0.0
    return out


def start_gradient(gradient, geometry) -> tuple[np.ndarray, np.ndarray]:
    """The slopes :func:`start_heights` integrates: masked ones filled from their neighbours,
    perspective ones converted to the scan grid."""
    from .integrate import scan_grid_gradient

    gx = _fill_masked(np.asarray(gradient.dzdx, float), np.asarray(gradient.mask, bool))
    gy = _fill_masked(np.asarray(gradient.dzdy, float), np.asarray(gradient.mask, bool))
    if geometry.projection == "perspective":
        gx, gy = scan_grid_gradient(gx, gy, geometry.field_mm, geometry.work_distance_mm)
    return gx, gy


def start_heights(gradient, geometry) -> np.ndarray:
    """Heights on the scan grid from a gradient result (e.g. the model gradient): the slopes of
    :func:`start_gradient`, DCT integration, zero mean."""
    from .integrate import integrate_dct

    h = integrate_dct(*start_gradient(gradient, geometry), geometry.field_mm)
    return h - h.mean()


def start_resolution(gradient, geometry, h0) -> dict:
    """Whether a single-ray scan resolves the relief: :func:`.sampling_check.half_sampling` of the
    start's slopes against its heights ``h0``.

    With a single-ray beam (fwhm 0) each pixel's images depend on the surface at its centre only,
    so what the slopes' samples leave open between the centres the images leave open too: on the
    corrugated sheet at 256^2 (ridges and valleys 2.3 pixels apart) the start's heights and the
    inversion's, which fits the images to 0.05 %, are both off by 0.40 mm RMS against a relief of
    0.20 mm RMS. Returns ``half_sampling_mm``, ``relief_rms_mm`` and, where the test fails,
    ``warning`` and ``flag`` (:func:`.sampling_check.resolution_warning`; else None).
    """
    from .integrate import integrate_dct
    from .sampling_check import resolution

    gx, gy = start_gradient(gradient, geometry)
    return resolution(gx, gy, geometry.field_mm, h0, np.zeros(h0.shape, bool),
                      lambda x, y, f, m: (integrate_dct(x, y, f), np.zeros(x.shape, bool)))


def bowl_check(height, field_mm) -> tuple[dict | None, np.ndarray | None]:
    """Whether the heights hold a field-wide bowl (their best-fitting quadric) larger than the
    relief about it, the rule of ``reconstruct`` (:func:`.integrate.reconstruction_quality`):
    ``({"bowl_mm", "relief_mm", "warning", "flag"}, the quadric less its mean)`` if so, else
    ``(None, None)``.

    A bias of the start's slopes integrates to such a shape, and the images hold little against it
    where the model cannot fit them anyway: the corrugated sheet at 256^2 under a 0.27 mm beam (its
    ridges finer than the model's facets) came out of ``invert`` 1.17 mm RMS off, 0.082 mm less a
    quadric, with a height_error of 0.19 mm. A plate that is really warped has such a bowl too;
    the images cannot tell the two apart here, so the bowl enters ``height_error``.

    Examples
    --------
    >>> y, x = np.mgrid[-1:1:32j, -1:1:32j]
    >>> said, quad = bowl_check(2.0 * (x * x + y * y) + 0.01 * np.sin(9 * x), 80.0)
    >>> said["flag"], round(float(np.ptp(quad)), 2)
    ('bowl 4 mm > relief 0.023 mm', 4.0)
    >>> bowl_check(0.01 * np.sin(9 * x), 80.0)[0] is None
    True
    """
    h = np.asarray(height, float)
    quad, bowl, relief, _ = fit_quadric(h, np.ones(h.shape, bool))
    if quad is None or not bowl_exceeds(bowl, relief, max(pixel_size(h.shape, field_mm))):
        return None, None
    line = (f"the heights hold a field-wide bowl of {bowl:.3g} mm, larger than the relief of {relief:.3g} mm "
            "about it: a bias of the start's slopes integrates to that shape, and the images, which the model "
            "does not fit to their noise, hold little against it; height_error holds it (a plate that is "
            "really warped shows one too)")
    return ({"bowl_mm": round(bowl, 6), "relief_mm": round(relief, 6), "warning": line,
             "flag": f"bowl {bowl:.3g} mm > relief {relief:.3g} mm"}, quad - quad.mean())


def check_beam_and_start(geometry, fwhm_mm: float, heights=None, *, what: str = "start heights") -> None:
    """Refuse, before any work, a beam profile or starting heights that no scan can have.

    The beam's FWHM must be finite, >= 0 and below the scan field's larger side (the renderer's own
    rule, ``elo_beam``): a wider beam lights the whole field at every scan point, and its blur
    kernel would outgrow the images (--fwhm 1e30 ran out of memory, 1e6 crashed, 1000 ran for
    minutes on 32 x 32 pixels). The heights' relief (largest less smallest) must lie below the lowest
    detector's centre: a surface that reaches the detectors is not a build surface, and the model's
    tangent-plane geometry has no meaning there.

    Examples
    --------
    >>> from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    >>> geo = ScanGeometry.nominal((8, 8), 80.0, 272.0, 127.0)
    >>> check_beam_and_start(geo, 0.27, np.zeros((8, 8)))
    >>> check_beam_and_start(geo, 100.0)
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: beam FWHM 100 mm (--fwhm): must be below the scan field's 80 mm (a beam profile is a fraction of a millimetre)
    """
    field = max(geometry.field_mm)
    if not is_fwhm(fwhm_mm):
        raise EloInputError(f"beam FWHM {fwhm_mm!r} mm (--fwhm): must be {FWHM_RANGE}")
    if fwhm_mm >= field:
        raise EloInputError(f"beam FWHM {fwhm_mm:g} mm (--fwhm): must be below the scan field's {field:g} mm "
                            "(a beam profile is a fraction of a millimetre)")
    if heights is None:
        return
    h = np.asarray(heights, float)
    if not np.all(np.isfinite(h)):
        raise EloInputError(f"{what}: not finite everywhere")
    lowest = min(float(d.center[2]) for d in geometry.detectors.values())
    relief = float(np.ptp(h)) if h.size else 0.0
    if relief >= lowest:
        raise EloInputError(f"{what}: a relief of {relief:.4g} mm (largest less smallest height) reaches the "
                            f"detectors, the lowest at {lowest:g} mm above the plate; heights are in mm")


def invert_heights(images: Mapping, flats: Mapping, geometry, *, start=None, fwhm_mm: float = 0.0,
                   later: Mapping | None = None, flat_later: Mapping | None = None,
                   later_error: Mapping | None = None, flat_later_error: Mapping | None = None,
                   alpha: float | None = None,
                   noise: float | None = None, iterations: int = ITERATIONS, cg_iterations: int = CG_ITERATIONS,
                   tol: float = TOL, discrepancy: float = DISCREPANCY, time_budget_s: float | None = None,
                   shadows: bool = True, scales: int = SCALES, uncertainty_probes: int = UNCERTAINTY_PROBES,
                   nodes=NODES, progress: Callable[[dict], None] | None = None,
                   force: bool = False, super_resolution: int = 1, fixed_border: int = 0,
                   local: bool = True) -> InversionResult:
    """Four detector images -> the height map that the forward model maps onto them.

    Parameters
    ----------
    images, flats : mapping of str to ndarray (H, W)
        Object and flat-plate images of ``right``, ``left``, ``back``, ``front`` (same beam, field
        and detectors; gains cancel in their ratio).
    geometry : ScanGeometry
        Field, beam, detectors (e.g. from the header or a calibration), material.
    start : ndarray (H, W) or GradientResult, optional
        Starting heights (mm), or a gradient to integrate (:func:`start_heights`); default: the
        model gradient of the same images (a second pass on relief that needs it,
        :func:`~.model_gradient.model_gradient_refined`), integrated.
    fwhm_mm : float
        Beam profile FWHM (mm) of the scan (the header's ``beam_fwhm_mm``).
    later, flat_later : mapping of str to ndarray, optional
        Fixed images of the events >= 2 of the object and of the flat plate (units of the images).
    later_error, flat_later_error : mapping of str to ndarray, optional
        Standard errors of ``later`` and ``flat_later`` (a render's own estimate,
        :mod:`elo_mitsuba.error_estimate`): the Monte Carlo error of the held-fixed events, which
        the true surface's residual carries too (:data:`DISCREPANCY`).
    alpha : float, optional
        Weight of the curvature regulariser (module docstring); default
        :data:`ALPHA_PER_NOISE2` times the noise variance.
    noise : float, optional
        Noise level of the corrected images; default: :func:`estimate_noise`.
    iterations, cg_iterations : int
        Gauss-Newton steps at most; CG iterations per step.
    tol : float
        Stop when a step lowers the objective by less than this fraction.
    discrepancy : float
        Return the start as it is when its residual RMS is at most this factor times
        noise x sqrt(1 - 1/detectors), what the true surface would leave (:data:`DISCREPANCY`);
        0 turns it off.
    time_budget_s : float, optional
        Stop after the step that exceeds this wall time.
    shadows : bool
        Model the surface's shadowing of the detectors.
    scales : int
        Solve coarse to fine over this many scales, each half the previous resolution
        (:data:`SCALES`; those that divide the image and leave :data:`MIN_SCALE_PX` pixels,
        :func:`scale_factors`); 1 solves at full resolution only.
    uncertainty_probes : int
        Noise draws propagated through the solution for ``height_error``
        (:data:`UNCERTAINTY_PROBES`; 0 skips it).
    nodes : (int, int)
        Disc rule of the model (:func:`~.detector_model.unit_disc_rule`); its nodes also resolve a
        disc's partial shadowing: (1, 4) counts quarters, (2, 8) sixteenths.
    progress : callable, optional
        Called with each step's history entry.
    super_resolution : int
        Sub-pixels per scan pixel and axis of the model's surface (1: one facet per pixel;
        :class:`~.height_model.SuperResolvedModel`); the local refinement at defects uses 2.
    local : bool
        Refine, region by region, where the misfit exceeds the noise (:mod:`.local_inversion`),
        after the field's solve; each region's outcome in ``regions``; and take the correction's
        fine band only where the start's misfit exceeds the noise, its band finer than the beam
        only where the images demand it (:mod:`.fine_band`). False: the field's solve as it ends,
        everywhere.
    fixed_border : int
        Pixels along the image's edge whose heights stay at the start's (a window cut out of a larger
        height map, whose edge must join it); 0: all heights free, their mean held.
    force : bool
        Run even when the estimate (:func:`elo_mitsuba.budget.check_inversion`) says it takes longer
        than :data:`~elo_mitsuba.budget.REFUSE_SECONDS`; memory beyond what is available is refused always.

    Returns
    -------
    InversionResult
    """
    from ..arguments import flag, real_array, shown, whole_number

    if not hasattr(geometry, "detectors") or not hasattr(geometry, "field_mm"):
        raise EloInputError(f"geometry={shown(geometry)}: must be a ScanGeometry (analysis.scan_geometry)")
    for name, v, lo in (("iterations", iterations, 0), ("cg_iterations", cg_iterations, 1),
                        ("uncertainty_probes", uncertainty_probes, 0), ("scales", scales, 1),
                        ("super_resolution", super_resolution, 1), ("fixed_border", fixed_border, 0)):
        whole_number(name, v, lo, None)  # a border wider than half the image holds every height: the start
    shadows, local, force = flag("shadows", shadows), flag("local", local), flag("force", force)
    if time_budget_s is not None and not (isinstance(time_budget_s, (int, float)) and not isinstance(time_budget_s, bool)
                                          and np.isfinite(time_budget_s) and time_budget_s > 0):
        raise EloInputError(f"time_budget_s={shown(time_budget_s)}: must be a number of seconds > 0, or None")
    if alpha is not None and not (np.isfinite(alpha) and 0 <= alpha <= MAX_ALPHA):
        raise EloInputError(f"alpha={alpha!r}: must be a number from 0 to {MAX_ALPHA:g} (default 30 x noise^2)")
    if not (np.isfinite(tol) and tol >= 0):
        raise EloInputError(f"tol={tol!r}: must be a finite number >= 0")
    if not (np.isfinite(discrepancy) and discrepancy >= 0):
        raise EloInputError(f"discrepancy={discrepancy!r}: must be a finite number >= 0")
    if noise is not None:
        noise = check_noise(noise)
    check_beam_and_start(geometry, fwhm_mm)  # the start's heights once they are known, below
    shape = tuple(geometry.shape)
    for what, data in (("images", images), ("flats", flats)):
        data = check_images(data, what)
        for n in DETECTOR_NAMES:
            if np.shape(data[n]) != shape:
                raise EloInputError(f"{what}[{n!r}] is {np.shape(data[n])}, the scan geometry {shape}")
    check_inversion(shape, iterations, scales, uncertainty_probes, force=force)
    t0 = time.perf_counter()
    if start is None:
        from .model_gradient import model_gradient_refined

        start = model_gradient_refined(images, flats, geometry)
    h0 = start_heights(start, geometry) if hasattr(start, "dzdx") else real_array("start heights", start)
    if h0.shape != shape or not np.all(np.isfinite(h0)):
        raise EloInputError(f"start heights must be finite and {shape[1]}x{shape[0]} px")
    check_beam_and_start(geometry, fwhm_mm, h0)
    resolution = start_resolution(start, geometry, h0) if hasattr(start, "dzdx") and fwhm_mm == 0 else None
    data = ScaleData(images, flats, later, flat_later, later_error, flat_later_error)
    budget = None if time_budget_s is None else float(time_budget_s)
    pixel = pixel_size(shape, geometry.field_mm)
    result, full = solve_field(data, geometry, h0, fwhm_mm=fwhm_mm, alpha=alpha, noise=noise, shadows=shadows,
                               nodes=nodes, super_resolution=super_resolution, fixed_border=fixed_border,
                               scales=scales, iterations=iterations, cg_iterations=cg_iterations, tol=tol,
                               discrepancy=discrepancy, budget=budget, progress=progress, t0=t0,
                               uncertainty_probes=uncertainty_probes)
    # where the start fits to the noise, the solve's finest band is fitted noise (fine_band.py)
    def flagged(misfit):  # where a misfit is not noise, tapered as a region's heights are taken
        return band_weight(misfit, result.expected_misfit, len(geometry.detectors), fwhm_mm, pixel)

    fine = flagged(result.start_misfit) if local and len(result.history) > 1 else None

    def left():
        return None if budget is None else max(budget - (time.perf_counter() - t0), 0.0)

    def in_time():
        return budget is None or time.perf_counter() - t0 < budget

    if local:
        result.regions = refine_regions(result, images, flats, geometry, fwhm_mm=fwhm_mm, later=later,
                                        flat_later=flat_later, later_error=later_error,
                                        flat_later_error=flat_later_error, shadows=shadows, nodes=nodes,
                                        iterations=iterations, time_budget_s=left(), probes=uncertainty_probes)
        refined = sum(r.status.startswith("refined") for r in result.regions)
        if result.regions:
            result.stopped += f"; {len(result.regions)} region(s) above the noise, {refined} refined"
    limit = threshold(detectors=len(full.names))
    known = None
    if local and iterations > 0 and in_time():
        lifted, result.steps, known = search_offsets(result.height, result.misfit, result.expected_misfit, limit,
                                                     images, flats, geometry, fwhm_mm=fwhm_mm, noise=full.noise,
                                                     alpha=full.problem.alpha, later=later, flat_later=flat_later,
                                                     nodes=nodes, time_budget_s=left(),
                                                     noise_error=result.height_error)
        n_lifted = sum(p.status == "lifted" for p in result.steps)
        if n_lifted:
            take_heights(full, result, lifted)
            result.stopped += f"; {n_lifted} of {len(result.steps)} floating part(s) lifted to their shadows"

    def floating(tied=None):  # the local chi-square, the floating parts and their offsets, of the heights as they are now
        chi2 = local_chi2(result.misfit, max(result.expected_misfit, 1e-12))
        result.floating, offset = offset_errors(result.height, chi2, limit, known, pixel, tied=tied,
                                                noise_error=result.height_error)
        return chi2, offset

    chi2, offset = floating()
    band = result.floating & (chi2 > limit)
    if local and band.any() and iterations > 0 and in_time():
        cut_across(full, result, band, dict(cg_iterations=cg_iterations, tol=tol, discrepancy=0.0, progress=progress,
                                            iterations=iterations, budget=budget, t0=t0))
        chi2, offset = floating()
    if fine is not None:
        # the last word, on all that the steps above changed (fine_band.py): where the start fitted to
        # the noise the correction's long wavelengths only; elsewhere the correction as the beam sees
        # it, and whole only where that leaves a misfit above the noise
        sigma, beam = low_pass_px(fwhm_mm, pixel), beam_px(fwhm_mm, pixel)
        tied = ~result.floating  # a part the gating's misfit cuts off below was measured through these
        d = result.height - h0
        take_heights(full, result, h0 + gated(d, fine, sigma, beam))
        whole = fine * flagged(result.misfit)
        if beam > 0 and whole.any():
            take_heights(full, result, h0 + gated(d, fine, sigma, beam, whole))
        chi2, offset = floating(tied)
        result.stopped += (f"; the correction's wavelengths below {half_wavelength(sigma):.0f} px taken only where "
                           f"the start's misfit exceeds the noise ({100 * np.mean(fine):.0f} % of the field)"
                           + (f", those below {half_wavelength(beam):.0f} px only where the images demand them "
                              f"({100 * np.mean(whole):.0f} %)" if beam > 0 else ""))
    if result.height_error is not None:
        result.height_error_noise = result.height_error
        result.height_error_model = MODEL_SLOPE_GAIN * np.abs(result.height - np.mean(result.height))
        result.height_error = np.sqrt((result.height_error_noise ** 2) * np.maximum(chi2, 1.0) + offset ** 2
                                      + result.height_error_bias ** 2 + result.height_error_model ** 2)
    result.sampling = resolution
    if resolution is not None and resolution["warning"] and result.height_error is not None:
        # what the images leave open, everywhere alike
        result.height_error = np.sqrt(result.height_error ** 2 + resolution["half_sampling_mm"] ** 2)
    result.bowl, quad = bowl_check(result.height, geometry.field_mm)
    if quad is not None and result.height_error is not None:
        result.height_error = np.sqrt(result.height_error ** 2 + quad ** 2)
    if result.height_error is not None:
        result.height_error_rms = float(np.sqrt(np.mean(result.height_error ** 2)))
    return result
