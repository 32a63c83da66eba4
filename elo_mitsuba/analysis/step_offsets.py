"""Step heights from the shadows: the offset of a part that a cliff cuts off, searched in the images.

Integrating slopes across a cliff recovers only what the slopes hold, and at a wall they saturate:
on the stepped layer (400^2, 0.27 mm beam, 1 % noise) the inversion's Gauss-Newton steps recover
33-62 % of steps of 0.1-1 mm. The images hold more: the relief beyond the foot of a cliff lies in the
cliff's shadow for the detector behind it, over a length that grows with the step (h / tan(elevation),
and a penumbra as long again for a 50 mm disc). A Gauss-Newton step cannot use it, since shadowing
has no derivative (:mod:`.height_model`). Here the offset of each floating part is searched directly:

1. **The parts.** Bands of misfit above the noise that cut a component of trusted pixels off from
   the field's largest one (:func:`floating_parts`: the cliff around a raised part or a pit), and
   bands of steep slope that do, where the images disagree with them on part of the band
   (:func:`edge_parts`: a small cliff that the solve left as a ramp, its misfit too faint to close
   round the part).
2. **The step.** The part is its component and the band pixels whose height lies nearer the
   component's level than the surroundings'; its boundary is also tried :data:`BOUNDARY_MOVES`
   times :data:`BOUNDARY_MM` either way (the solve's ramp need not be centred on the cliff). Band
   pixels take the height of their own side's nearest trusted pixel (the ramp becomes a clean
   step) and the part is lifted as a whole: heights = background + s x part. Where that clean step
   at the solve's own height fits the window more than :data:`CLEAN_FIT` times worse than the
   solve's heights, the band is relief that no step describes (a melt square's rim) and the part
   is not searched.
3. **The search.** The objective is the inversion's Huber data term over a window of the scan
   around the part (:data:`MARGIN_MM` beyond its band, where its shadow falls), with the model's
   surface cut into facets of :data:`SEARCH_FACET_MM` so that the wall is one facet narrow (with one
   facet per 0.2 mm pixel the ramp of a cliff spans two pixels and casts too short a shadow: on the
   stepped layer's truth the best-fitting step is then 0.2 mm too high). s runs over a grid of
   :data:`COARSE_STEPS` values within :data:`SPAN` times the current step either way, for each
   boundary; the best is refined twice on facets of :data:`REFINE_FACET_MM`. Where the coarser
   facets find no better step (a shadow of about a pixel, which they blur), the grid is run once
   more on the finer facets with the boundary found. A part is lifted only if the best lift lowers
   the objective by more than :data:`MIN_GAIN` against the clean step at its current height: where
   the images say nothing more about the step, the solve's step stays.
4. **The wall.** Steps 2-3 run with two models of the cliff within a facet, each with its own
   boundary: the step interpolated with the rest of the surface (a ramp two facets wide with a lip
   of 1/16 of the step on top) and a sharp one (:func:`cliff_corners`: the top edge on the part's
   boundary, the wall one facet wide). The sharp wall is kept where it lowers the window's data
   term by more than :data:`MIN_GAIN` against the other, as a lift must. On the stepped layer's
   true heights the sharp wall fits better (1500^2: the best data term 22-28 % lower on every
   cliff of 0.2-1 mm) and puts the best step 0.02-0.035 mm too high against 0.04-0.065 mm; from the
   solve's heights it wins on the 0.5 and 1 mm cliffs and loses on the 0.2 mm ones, whose boundary
   the solve leaves less certain than a facet (measured 2026-12-05; docs/inversion.md).

Measured (validation/REPORT.md, row D2, and ``python -m validation.study_defects --only steps``):
steps of 0.2-1 mm come out within 10 % of the truth's (the 0.5 mm ones were 11 % high with the
interpolated wall alone, under every noise seed), against 33-62 % recovered by the slopes; the
0.1 mm steps (shadows of half a pixel at 0.2 mm pixels), found by their ramps and searched on the
grid's ENLARGED steps, within 1-5 % under six noise seeds (the slopes: 68 %).

A lifted step's uncertainty is how far the finer facets moved it, at least their width (halving
the facets halved the step's bias on the truth: about one facet's width is left) and at least the
two walls' difference; it replaces the floating part's 100 % uncertainty in ``height_error``
(:func:`offset_errors`).

What it cannot do: a step whose shadow falls on masked or unmeasured pixels, a part that neither a
band of misfit nor one of steep slope closes round (a cliff that runs out into a slope), shadows
shorter than half a pixel (not measured below that).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Mapping

import numpy as np

from ..grid import pixel_size
from .height_solver import NODES, data_term, upsample

#: Pixels a floating component's surroundings are searched in, beyond its band.
RING_PX = 12
#: A cliff the solve left as a ramp (:func:`edge_parts`): pixels whose slope exceeds this (at least)
#: and EDGE_SLOPE_FACTOR times the field's median slope form its band. On the stepped layer (400^2,
#: 0.27 mm beam, 1 % noise) the solve's ramps at the 0.1 mm cliffs reach 0.12-0.2 against a median
#: of 0.014 on the powder; on the rough layer (100 um RMS) the median is 0.059 and the bar 0.24.
EDGE_SLOPE = 0.06
EDGE_SLOPE_FACTOR = 4.0
#: ... and a part is taken only where the images disagree with the ramp: this share of its band's
#: pixels above the noise limit (the 0.1 mm cliffs' bands: 56-65 %; bands of steep slope on the
#: rough layer: 0-8 %).
EDGE_MISFIT_SHARE = 0.3
#: Components smaller than this (pixels) are part of the band around them.
MIN_COMPONENT_PX = 16
#: Parts smaller than this (mm^2) are not searched: on the steep hills at 1500^2, 17 islands of 16-203
#: pixels (0.05-0.6 mm^2) between bands of misfit on the slopes were searched for 155 s and all
#: kept; the parts lifted on the stepped layer cover 34-92 mm^2 (400^2) and 43-85 mm^2 (1500^2).
MIN_PART_MM2 = 1.0
#: Size (mm) of the facets of the surface the offsets are searched on, and refined on: each pixel is
#: cut into as many sub-pixels as this needs, so that a cliff's wall is one facet narrow. Measured
#: on the stepped layer's truth (0.2 mm pixels), the step that fits best is +0.2 mm too high with
#: facets of 0.2 mm, +0.1 mm with 0.1 mm; the search then lands within 1-9 % of steps of 0.5-1 mm
#: with 0.05 mm.
SEARCH_FACET_MM = 0.1
REFINE_FACET_MM = 0.05
#: The part's boundary is moved by up to BOUNDARY_MOVES steps of BOUNDARY_MM (at least a pixel)
#: either way.
BOUNDARY_MM = 0.2
BOUNDARY_MOVES = 2
#: The window of the search: the part and its band, and this much around them (mm; a 1 mm step's
#: shadow and penumbra reach 2.4 mm at 40 degrees of elevation). Steps whose shadow the margin
#: cannot hold (MARGIN_MM x tan(the lowest detector's elevation): 2.7 mm at 40 degrees, 0.86 mm at
#: 15) are not searched.
MARGIN_MM = 3.2
#: Half-width of the search grid: three times the current step either way (the solve recovers a
#: third of a 1 mm step), at least this (mm).
SPAN = 3.0
MIN_SPAN_MM = 0.3
#: Steps of the coarse grid (for each boundary), of each of the two refinements around the best
#: (each halving the spacing, then a parabola through the best and its neighbours).
COARSE_STEPS = 11
FINE_STEPS = 5
#: The coarse grid also holds these multiples of the solve's step: the solve leaves 33-68 % of a
#: cliff, and a small step's grid (spacing 0.06 mm within MIN_SPAN_MM) steps over the lift it needs
#: (a 0.1 mm cliff solved at 0.068 mm; stepped layer, 400^2).
ENLARGED = (1.25, 1.5, 1.75)
#: A moved boundary is tried only at the grid's steps within this many of the best so far.
NEAR_STEPS = 2
#: A lift is kept if it lowers the window's data term by more than this fraction.
MIN_GAIN = 0.05
#: A lift must keep the sign of the solve's step and shrink it by at most this fraction: at a cliff
#: the slopes only lose height (saturated at the wall, blurred, shadowed: the stepped layer's solve
#: holds 33-62 % of each step and every lift there enlarged it), so a smaller best step is the
#: model's misfit speaking, not the step. On the smooth hills at 256^2 (zeta25, single-ray beam,
#: no noise) bands of misfit on the steep flanks cut off two parts whose best "steps" were +1.85
#: and -1.38 mm against the solve's +3.01 and -1.99 mm; lifted, they were 0.46-0.77 mm off and
#: the map's error rose from 30 to 111 um RMS.
MAX_SHRINK = 0.1
#: A part is searched only if the clean step at the solve's height (:func:`_clean_step`) leaves at
#: most this many times the window's data term of the solve's own heights. On the stepped layer
#: (400^2, 1 % noise) the cliffs' clean steps leave 1.27-1.42 times the solve's; on the melt plate
#: without noise (512^2), whose melt squares' rims close bands of misfit, 11.5-25.7 times, and
#: there a lift of +0.028 mm over 2523 pixels raised the map's error from 0.64 to 3.2 um.
CLEAN_FIT = 4.0
#: At most this many facets per window: finer facets are given up first (a window of 100^2 pixels
#: of 0.2 mm at 0.05 mm facets holds 160 000).
MAX_FACETS = 160_000


@dataclasses.dataclass
class StepOffset:
    """One floating part of :func:`search_offsets`.

    Attributes
    ----------
    rows, cols : (int, int)
        The window searched (start, stop), in pixels.
    pixels : int
        Pixels of the part.
    step_before, step_after : float
        The part's median height less its surroundings' (mm), before and after.
    objective_before, objective_after : float
        The window's data term (Huber, corrected units squared) of the heights before and of the
        best lift (None: not searched).
    status : str
        ``lifted``, ``kept`` (no lift lowered the data term by :data:`MIN_GAIN`), ``kept (its best
        step ... would shrink the solve's: MAX_SHRINK)`` (:data:`MAX_SHRINK`), ``not searched
        (step beyond its window)`` (:data:`MARGIN_MM`), ``not searched (smaller than
        MIN_PART_MM2)``, ``not searched (no cliff: ...)`` (:data:`CLEAN_FIT`) or ``not searched
        (time budget)``.
    error : float or None
        A lifted step's uncertainty (mm): how far the finer facets moved it, at least their width
        (the bias a facet's width leaves), and at least the two walls' difference where both lift;
        a part whose band is no cliff, the band's own error (:func:`band_error`, given the noise
        part); the heights of a kept part keep the floating part's error
        (:func:`offset_errors`).
    seconds : float
    wall : str or None
        The wall model of a lifted step: ``sharp`` (:func:`cliff_corners`) where it fitted the
        window better by more than :data:`MIN_GAIN`, else ``interpolated``.
    """

    rows: tuple
    cols: tuple
    pixels: int
    step_before: float
    step_after: float
    objective_before: float | None
    objective_after: float | None
    status: str
    error: float | None = None
    seconds: float = 0.0
    wall: str | None = None

    def as_dict(self) -> dict:
        """The part as a plain dict (for a JSON report).

        Examples
        --------
        >>> StepOffset((0, 9), (0, 9), 20, 0.3, 1.0, 40.0, 15.0, "lifted").as_dict()["status"]
        'lifted'
        """
        return dataclasses.asdict(self)


def floating_parts(chi2, limit: float):
    """The parts of the field that bands of misfit above the noise (``chi2`` > ``limit``) cut off
    from its largest trusted part.

    Returns
    -------
    list of (component, band, ring)
        Boolean masks (H, W): the part's trusted pixels, the untrusted band its growth crosses
        before it reaches trusted pixels of another part, and those trusted pixels (up to
        :data:`RING_PX` layers).

    Examples
    --------
    >>> chi2 = np.ones((40, 40)); chi2[8:32, 8:32] = 9.0; chi2[12:28, 12:28] = 1.0
    >>> [(int(c.sum()), bool(r[7, 20]), bool(b[10, 10])) for c, b, r in floating_parts(chi2, 2.0)]
    [(256, True, True)]
    """
    from scipy.ndimage import binary_dilation, find_objects, label

    bad = np.asarray(chi2) > limit
    labels, n = label(~bad)
    if n < 2:
        return []
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    reference = int(np.argmax(sizes))
    grow = 4 * RING_PX
    out = []
    for k, box in enumerate(find_objects(labels), start=1):
        if k == reference or sizes[k] < MIN_COMPONENT_PX:
            continue
        # the growth reaches at most `grow` pixels: a box that much larger than the component holds
        # all of it (dilating the whole field instead took 47 s of a 1500^2 inversion)
        sub = tuple(slice(max(s.start - grow - 1, 0), min(s.stop + grow + 1, size))
                    for s, size in zip(box, bad.shape))
        bad_k, comp = bad[sub], labels[sub] == k
        grown, band, ring = comp, np.zeros_like(comp), np.zeros_like(comp)
        for _ in range(grow):
            nxt = binary_dilation(grown)
            new = nxt & ~grown
            band |= new & bad_k
            ring |= new & ~bad_k & ~comp
            grown = nxt
            if ring.sum() >= min(sizes[k], 4 * RING_PX * RING_PX):
                break
        if ring.any():
            masks = []
            for m in (comp, band, ring):
                full = np.zeros(bad.shape, bool)
                full[sub] = m
                masks.append(full)
            out.append(tuple(masks))
    return out


def edge_parts(height, chi2, limit: float, pixel_mm, known=None):
    """The parts of the field that a band of steep slope cuts off, where the band's misfit is
    above the noise: cliffs whose bands of misfit do not close all round.

    At a 0.1 mm cliff (stepped layer, 400^2, 0.27 mm beam, 1 % noise) the solve's ramp leaves a
    misfit of chi-square 1.7 (median over the wall) against a limit of 1.6, above it on 56-65 % of
    the wall: :func:`floating_parts` finds no closed band, and the solve's 68 % of the step stood.
    The ramp itself closes round the part: slopes of 0.12-0.2 against 0.014 on the powder.
    A band counts if its slope exceeds :data:`EDGE_SLOPE` and :data:`EDGE_SLOPE_FACTOR` times the
    field's median slope and :data:`EDGE_MISFIT_SHARE` of it lies above ``limit``; a part that
    overlaps one a band of misfit cuts off (by more than half of the smaller) is left to
    :func:`floating_parts`.

    Parameters
    ----------
    height, chi2 : ndarray (H, W)
        Heights (mm) and the local chi-square of their misfit.
    limit : float
    pixel_mm : (float, float)
        Pixel size along x (columns) and y (rows).
    known : list, optional
        ``floating_parts(chi2, limit)`` where the caller has it.

    Returns
    -------
    list of (component, band, ring)
        As :func:`floating_parts`.

    Examples
    --------
    >>> h = np.zeros((60, 60)); h[20:40, 20:40] = 0.07                     # a ramp-less 70 um step
    >>> chi2 = np.ones((60, 60)); chi2[19:41, 19:21] = chi2[19:41, 39:41] = 3.0  # misfit on 2 sides
    >>> [int(c.sum()) for c, b, r in floating_parts(chi2, 2.0)]
    []
    >>> [int(c.sum()) for c, b, r in edge_parts(h, chi2, 2.0, (0.2, 0.2))]
    [324]
    """
    height = np.asarray(height, float)
    chi2 = np.asarray(chi2, float)
    gy, gx = np.gradient(height, pixel_mm[1], pixel_mm[0])
    slope = np.hypot(gx, gy)
    bar = max(EDGE_SLOPE, EDGE_SLOPE_FACTOR * float(np.median(slope)))
    known = floating_parts(chi2, limit) if known is None else known
    out = []
    for comp, band, ring in floating_parts(np.where(slope > bar, 2.0, 0.0), 1.0):
        if not band.any() or np.mean(chi2[band] > limit) < EDGE_MISFIT_SHARE:
            continue
        if any(np.count_nonzero(comp & c) > 0.5 * min(np.count_nonzero(comp), np.count_nonzero(c))
               for c, _, _ in known):
            continue
        out.append((comp, band, ring))
    return out


def all_parts(height, chi2, limit: float, pixel_mm=None):
    """:func:`floating_parts` and, given ``pixel_mm``, :func:`edge_parts`."""
    out = floating_parts(chi2, limit)
    return out + (edge_parts(height, chi2, limit, pixel_mm, out) if pixel_mm is not None else [])


def band_error(noise_error, chi2, band) -> float:
    """The offset uncertainty (mm) of a part whose band of misfit is no cliff (:data:`CLEAN_FIT`):
    the band's own, the RMS over its pixels of the noise part ``noise_error`` scaled by the local
    chi-square where it exceeds 1 (as :func:`~.inversion.invert_heights` states a pixel's error
    where the images are not reproduced to their noise). Such a band is relief the solve's heights
    describe far better than a step would, so the part's offset is what those heights carry; the
    floating part's 100 % (the whole step, :func:`offset_errors`) stated 65 um RMS on the
    noise-free melt plate's squares (512^2), whose actual error was 1.3 um.

    Examples
    --------
    >>> band = np.zeros((4, 4), bool); band[1] = True
    >>> float(band_error(np.full((4, 4), 1e-3), np.full((4, 4), 4.0), band))   # 1 um x sqrt(4)
    0.002
    """
    b = np.asarray(band, bool)
    scaled = np.asarray(noise_error, float)[b] ** 2 * np.maximum(np.asarray(chi2, float)[b], 1.0)
    return float(np.sqrt(np.mean(scaled))) if scaled.size else 0.0


def offset_errors(height, chi2, limit: float, known=None, pixel_mm=None, *, tied=None,
                  noise_error=None) -> tuple[np.ndarray, np.ndarray]:
    """Where the height map floats, and by how much: the parts of the field that bands of misfit
    above the noise (``chi2`` > ``limit``, e.g. the cliff around a raised part) cut off from its
    largest part, whose offset to it no trusted pixel measures.

    A cliff's height comes from integrating slopes across it, and the slopes saturate at a wall:
    on the stepped layer (400^2, 1 % noise) the Gauss-Newton steps recover 33-62 % of steps of
    0.1-1 mm, so a plateau's pixels fit their images to the noise while their offset is wrong by up
    to 0.66 mm (the shadows then give the larger steps back, :mod:`.step_offsets`).
    Their error is taken as the offset as recovered (the median height inside less the median in a
    ring of :data:`~.step_offsets.RING_PX` beyond the band), a 100 % uncertainty of the step: the images bound it
    only from below; measured, it covers the true step's error within 1x on 5 of the 8 steps and
    within 2x on all. The band's own pixels get the same.

    ``known`` (H, W; NaN elsewhere): an offset uncertainty measured otherwise, e.g. a part whose
    step was searched in its shadows (:func:`~.step_offsets.search_offsets`); a part whose pixels
    mostly hold one takes it instead. Given ``pixel_mm`` (x, y), the parts that only a small
    cliff's ramp cuts off count too (:func:`edge_parts`).

    ``tied`` (H, W bool) and ``noise_error`` (H, W, mm; optional): the pixels that earlier heights
    of the same solve tied to the field's largest part, and those heights' noise part. A part whose
    pixels mostly lie there is cut off only by misfit that the later heights added, not by a cliff;
    its offset was measured through the pixels now in its band: it does not float, and its pixels
    and its band's take the band's own error (:func:`band_error`, as a band that is no cliff)
    instead of the whole step. On the melt plate (512^2, 0.27 mm beam) the correction's fine band,
    dropped where the start fitted (:mod:`.fine_band`), leaves misfit above the noise along the
    squares' rims: 7 % of the field (0.25 % noise) and 24 % (none) floated with 57 and 44 um RMS
    stated, against an actual error there of 1.6 and 1.1 um.

    Returns
    -------
    floating : ndarray of bool (H, W)
        Pixels cut off from the field's largest trusted part, and the bands around them.
    error : ndarray (H, W)
        The offset's uncertainty (mm), 0 elsewhere.

    Examples
    --------
    >>> h = np.zeros((40, 40)); h[10:30, 10:30] = 0.3                  # a raised square
    >>> chi2 = np.ones((40, 40)); chi2[8:32, 8:32] = 9.0; chi2[12:28, 12:28] = 1.0
    >>> floating, error = offset_errors(h, chi2, 2.0)
    >>> bool(floating[20, 20]), round(float(error[20, 20]), 3), bool(floating[2, 2])
    (True, 0.3, False)
    """
    floating = np.zeros(np.shape(chi2), bool)
    error = np.zeros(np.shape(chi2))
    for comp, band, ring in all_parts(height, chi2, limit, pixel_mm):
        measured = known is not None and np.mean(np.isfinite(known[comp])) > 0.5
        if not measured and tied is not None and np.mean(tied[comp]) > 0.5:
            # not floating: earlier heights measured its offset
            if noise_error is not None:
                error[comp | band] = np.maximum(error[comp | band], band_error(noise_error, chi2, band))
            continue
        step = (float(np.nanmedian(known[comp])) if measured
                else abs(float(np.median(height[comp]) - np.median(height[ring]))))
        sel = comp | band
        floating |= sel
        error[sel] = np.maximum(error[sel], step)
    return floating, error


def _side_heights(height, comp, band):
    """The height of each pixel's nearest pixel of the component, and of its nearest pixel outside
    the component and the band: what a band pixel takes on either side of the cliff."""
    from scipy.ndimage import distance_transform_edt

    _, (ia, ja) = distance_transform_edt(~comp, return_indices=True)
    _, (ib, jb) = distance_transform_edt(comp | band, return_indices=True)
    return height[ia, ja], height[ib, jb]


def _clean_step(height, band, part, sides):
    """``height`` with each band pixel replaced by its own side's nearest height outside the band
    (``sides``, :func:`_side_heights`; the part's side is the component's): the ramp of the solve
    becomes a clean step."""
    inner, outer = sides
    return np.where(band & part, inner, np.where(band & ~part, outer, height))


def _factor(pixel_mm: float, facet_mm: float) -> int:
    """Sub-pixels per pixel and axis for facets of about ``facet_mm``.

    Examples
    --------
    >>> _factor(0.2, 0.05), _factor(0.2, 0.1), _factor(0.053, 0.05)
    (4, 2, 1)
    """
    return max(1, int(round(pixel_mm / facet_mm)))


def _refine(objective, background, part, s, width):
    """Two refinements of the step ``s`` (each over FINE_STEPS values within ``width`` either way,
    then half of it), then the parabola through the best and its neighbours: (step, objective)."""
    for _ in range(2):
        grid = s + np.linspace(-1.0, 1.0, FINE_STEPS) * width
        values = [objective(background, part, v) for v in grid]
        j = int(np.argmin(values))
        s, best, width = float(grid[j]), values[j], width / 2.0
    if 0 < j < FINE_STEPS - 1:
        a, c = values[j - 1], values[j + 1]
        curvature = a - 2.0 * best + c
        if curvature > 0:
            shifted = s + 0.5 * (a - c) / curvature * (grid[1] - grid[0])
            value = objective(background, part, shifted)
            if value < best:
                s, best = float(shifted), value
    return s, float(best)


def cliff_corners(lift, *, raised: bool) -> np.ndarray:
    """Corner weights (H + 1, W + 1) of a lift given per facet (H, W): each corner takes the lift of
    the higher of its facets, so that a cliff's top edge lies on the part's boundary and its wall
    is one facet wide, on the lower side (``raised``: the part is the higher side).

    Interpolating the step with the rest of the surface (:func:`~.height_model.corners_from_pixels`)
    spreads a cliff over two facets with a lip of 1/16 of its height on top; on the stepped layer's
    true heights at 1500^2 such a wall fits the images worse than this one (the window's best data
    term 28-39 % higher on the cliffs of 0.2-1 mm) and puts the best step 0.04-0.065 mm too high
    against 0.02-0.035 mm.

    Examples
    --------
    >>> lift = np.zeros((3, 4)); lift[:, 2:] = 1.0
    >>> cliff_corners(lift, raised=True)[1]
    array([0., 0., 1., 1., 1.])
    >>> cliff_corners(lift, raised=False)[1]
    array([0., 0., 0., 1., 1.])
    """
    q = np.pad(np.asarray(lift, float), 1, mode="edge")
    four = (q[:-1, :-1], q[:-1, 1:], q[1:, :-1], q[1:, 1:])
    return np.maximum.reduce(four) if raised else np.minimum.reduce(four)


@dataclasses.dataclass
class _Wall:
    """One wall model's outcome of :func:`_settle`."""

    lifted: bool
    step: float
    coarse_step: float | None
    value: float
    before: float


def _settle(objective_at, sharp, background, part, s0, coarse, s_best, value, width, factors) -> _Wall:
    """The coarse search's best step refined with one wall model (``sharp``, :func:`cliff_corners`):
    on the search's facets, then on the refining ones (``factors``); where the search's facets find
    no lift and the refining ones are finer, the coarse grid once more on those. ``value`` is the
    coarse best's data term."""
    objective = objective_at(factors[0], sharp)
    before = objective(background, part, s0)  # the clean step at the solve's height
    finer = factors[1] != factors[0]
    s_coarse = None
    if value < (1.0 - MIN_GAIN) * before:
        # refined on the search's facets, then on facets of refine_facet_mm (a narrower wall casts a
        # truer shadow); what the finer facets moved the step by bounds what facets finer still
        # would (halving the facets halved the bias on the stepped layer's truth)
        s_coarse, value = _refine(objective, background, part, s_best, width)
        s_best = s_coarse
        if finer:
            objective = objective_at(factors[1], sharp)
            before = objective(background, part, s0)
            s_best, value = _refine(objective, background, part, s_coarse, width)
    elif finer:
        # a short shadow (a small step) the coarser facets blur: the coarse grid once more on the
        # finer facets, with the boundary found
        objective = objective_at(factors[1], sharp)
        before = objective(background, part, s0)
        values = [objective(background, part, v) for v in coarse]
        j = int(np.argmin(values))
        value = values[j]
        if value < (1.0 - MIN_GAIN) * before:
            s_coarse = float(coarse[j])
            s_best, value = _refine(objective, background, part, s_coarse, width)
    lifted = s_coarse is not None and value < (1.0 - MIN_GAIN) * before
    return _Wall(lifted, float(s_best), s_coarse, float(value), float(before))


def _part(height, comp, band, level_in, level_out):
    """The component and the band pixels whose height lies nearer the component's level than the
    surroundings' (on the stepped layer this put the boundary within 1-2 pixels of the cliff; the
    band's middle line put it further off)."""
    return comp | (band & (np.abs(height - level_in) < np.abs(height - level_out)))


def _moved(part, comp, band, b: int):
    """The part with its boundary moved ``b`` pixels outwards (inwards for b < 0), inside the band."""
    from scipy.ndimage import binary_dilation, binary_erosion

    if b > 0:
        moved = binary_dilation(part, iterations=b)
    elif b < 0:
        moved = binary_erosion(part, iterations=-b)
    else:
        moved = part
    return (moved & (comp | band)) | comp


def search_offsets(height, misfit, expected: float, limit: float, images: Mapping, flats: Mapping, geometry, *,
                   fwhm_mm: float, noise: float, alpha: float, later: Mapping | None = None,
                   flat_later: Mapping | None = None, nodes=None, facet_mm: float = SEARCH_FACET_MM,
                   refine_facet_mm: float = REFINE_FACET_MM, time_budget_s: float | None = None,
                   noise_error=None):
    """Lift each floating part to the step its images show (module docstring).

    Parameters
    ----------
    height : ndarray (H, W)
        The inversion's heights (mm); a copy is returned.
    misfit : ndarray (H, W)
        Their misfit per pixel (corrected units) and ``expected``, what the true surface leaves.
    limit : float
        The local chi-square above which a window's misfit is not noise
        (:func:`~.local_inversion.threshold`).
    images, flats, geometry, fwhm_mm, noise, alpha, later, flat_later, nodes
        As the inversion was given them (:func:`~.inversion.invert_heights`).
    facet_mm, refine_facet_mm : float
        Facet size of the searched and of the refining surface (:data:`SEARCH_FACET_MM`,
        :data:`REFINE_FACET_MM`).
    time_budget_s : float, optional
        No part is started after this much time.
    noise_error : ndarray (H, W), optional
        The heights' noise part (mm, ``height_error`` of the field's solve): with it, a part whose
        band is no cliff (:data:`CLEAN_FIT`) takes the band's own error as its offset's
        (:func:`band_error`) instead of the floating part's 100 %.

    Returns
    -------
    height : ndarray (H, W)
    parts : list of StepOffset
    error : ndarray (H, W)
        Each lifted part's step uncertainty (mm) on its pixels, a part's whose band is no cliff on
        its part and band (given ``noise_error``), NaN elsewhere.
    """
    from .height_model import corners_from_pixels
    from .noise import local_chi2

    t0 = time.perf_counter()
    h = np.array(height, float)
    names = tuple(geometry.detectors)
    chi2 = local_chi2(misfit, max(float(expected), 1e-12))
    error = np.full(h.shape, np.nan)
    pixel_xy = pixel_size(h.shape, geometry.field_mm)
    pixel = max(pixel_xy)
    area = float(np.prod(pixel_xy))  # mm^2 per pixel
    margin = int(np.ceil(MARGIN_MM / pixel))
    move = max(1, int(round(BOUNDARY_MM / pixel)))
    elevation = min(np.arctan2(d.center[2], np.hypot(d.center[0], d.center[1])) for d in geometry.detectors.values())
    max_step = MARGIN_MM * float(np.tan(elevation))
    parts = []
    for comp, band, ring in all_parts(h, chi2, limit, pixel_xy):
        t1 = time.perf_counter()
        rr, cc = np.nonzero(comp | band)
        rows = (max(int(rr.min()) - margin, 0), min(int(rr.max()) + 1 + margin, h.shape[0]))
        cols = (max(int(cc.min()) - margin, 0), min(int(cc.max()) + 1 + margin, h.shape[1]))
        level_in, level_out = float(np.median(h[comp])), float(np.median(h[ring]))
        s0 = level_in - level_out
        record = StepOffset(rows, cols, int(comp.sum()), s0, s0, None, None, "kept")
        if time_budget_s is not None and t1 - t0 > time_budget_s:
            record.status = "not searched (time budget)"
            parts.append(record)
            continue
        window = (rows[1] - rows[0]) * (cols[1] - cols[0])
        if comp.sum() * area < MIN_PART_MM2:
            record.status = "not searched (smaller than MIN_PART_MM2)"
            parts.append(record)
            continue
        if abs(s0) > max_step:  # e.g. a hill's top that masked slopes cut off, seen from 15 degrees
            record.status = "not searched (step beyond its window)"
            parts.append(record)
            continue
        sl = (slice(*rows), slice(*cols))
        sub = geometry.cropped(rows, cols)
        most = max(1, int(np.sqrt(MAX_FACETS / window)))

        def crop(d):
            return None if d is None else {n: np.asarray(d[n])[sl] for n in names}

        data = [crop(d) for d in (images, flats)]
        kw = dict(fwhm_mm=fwhm_mm, noise=noise, alpha=alpha, later=crop(later), flat_later=crop(flat_later),
                  nodes=NODES if nodes is None else nodes)

        def objective_at(f, sharp=False):
            """The window's data term of background + s x part on a surface f times finer; with
            ``sharp`` the cliff's top edge on the part's boundary (:func:`cliff_corners`), else the
            step interpolated with the rest of the surface."""
            term = data_term(*data, sub, factor=f, **kw)
            shape = (sub.shape[0] * f, sub.shape[1] * f)

            def objective(background, part, s):
                fine = upsample(background, f, shape) if f > 1 else background
                lift = np.kron(part, np.ones((f, f)))
                if sharp:
                    return term(corners_from_pixels(fine) + s * cliff_corners(lift, raised=s > 0))
                return term(corners_from_pixels(fine + s * lift))
            return objective

        factors = (min(_factor(pixel, facet_mm), most), min(_factor(pixel, refine_facet_mm), most))
        part0 = _part(h, comp, band, level_in, level_out)
        sides = _side_heights(h, comp, band)
        # the search lifts a clean step: where cutting the band into one at the solve's own height
        # already fits far worse than the solve, the band is relief that a step cannot describe
        first = objective_at(factors[0])
        solved = first(h[sl], np.zeros(h[sl].shape), 0.0)
        cleaned = first((_clean_step(h, band, part0, sides) - s0 * part0)[sl], part0[sl].astype(float), s0)
        if cleaned > CLEAN_FIT * solved:
            record.status = f"not searched (no cliff: a clean step fits {cleaned / max(solved, 1e-300):.0f}x worse " \
                            "than the solve; CLEAN_FIT)"
            if noise_error is not None:
                record.error = band_error(noise_error, chi2, band)
                error[comp | band] = record.error
            record.seconds = time.perf_counter() - t1
            parts.append(record)
            continue
        span = max(SPAN * abs(s0), MIN_SPAN_MM)
        grid = np.linspace(max(s0 - span, -max_step), min(s0 + span, max_step), COARSE_STEPS)
        spacing = grid[1] - grid[0]
        coarse = np.union1d(grid, np.clip(s0 * np.asarray(ENLARGED), -max_step, max_step))

        def coarse_search(objective, near=None):
            """The step and the part's boundary on the coarse grid: (data term, step, part,
            background, the part in the window, boundary move). ``near`` (step, move): only the
            steps within NEAR_STEPS of it, at that boundary and one move either way."""
            best = (np.inf, s0, part0, None, None, 0)
            moves = [0] + [move * v for a in range(1, BOUNDARY_MOVES + 1) for v in (-a, a)]
            if near is not None:
                moves = [near[1], near[1] - move, near[1] + move]
            for b in moves:
                if near is None and abs(b) > move and best[0] >= (1.0 - MIN_GAIN) * clean0:
                    break  # neither the boundary as found nor one move either way lifts it: kept
                part = _moved(part0, comp, band, b)
                background = (_clean_step(h, band, part, sides) - s0 * part)[sl]
                p = part[sl].astype(float)
                if b == moves[0] and near is None:
                    grid = coarse
                else:  # a moved boundary (or wall) shifts the best step by less than a grid spacing or two
                    j = int(np.argmin(np.abs(coarse - (best[1] if b != moves[0] else near[0]))))
                    grid = coarse[max(j - NEAR_STEPS, 0):j + NEAR_STEPS + 1]
                values = [objective(background, p, s) for s in grid]
                if b == moves[0] and near is None:  # only the full search stops early on it
                    clean0 = objective(background, p, s0)  # the clean step at the solve's height
                j = int(np.argmin(values))
                if values[j] < best[0]:
                    best = (values[j], float(grid[j]), part, background, p, b)
            return best

        # the sharp wall searches its own boundary and step, near the interpolated wall's: where the
        # top edge lies differs by about a facet
        walls, masks, near = {}, {}, None
        for sharp in (False, True):
            value, s_best, masks[sharp], background, p, b = coarse_search(
                objective_at(factors[0], True) if sharp else first, near)
            walls[sharp] = _settle(objective_at, sharp, background, p, s0, coarse, s_best, value,
                                   spacing, factors)
            near = (s_best, b)
        # the sharp wall is kept where it fits the window better by more than MIN_GAIN (as a lift must)
        cubic, crisp = walls[False], walls[True]
        use = crisp.lifted and crisp.value < (1.0 - MIN_GAIN) * (cubic.value if cubic.lifted else cubic.before)
        chosen = crisp if use else cubic
        record.objective_before, record.objective_after = chosen.before, chosen.value
        if chosen.lifted and not (chosen.step * s0 > 0 and abs(chosen.step) >= (1.0 - MAX_SHRINK) * abs(s0)):
            record.status = f"kept (its best step {chosen.step:+.3f} mm would shrink the solve's: MAX_SHRINK)"
        if not chosen.lifted or record.status != "kept":
            # the images say no more about the step than the solve did: kept
            record.seconds = time.perf_counter() - t1
            parts.append(record)
            continue
        s_best, s_coarse, part = chosen.step, chosen.coarse_step, masks[use]
        record.wall = "sharp" if use else "interpolated"
        # a facet of width w biased the step by about w (0.2 mm facets: +0.2 mm, 0.1 mm: +0.1 mm); the
        # two walls, where both lift, bracket the cliff's unresolved shape
        spread = abs(crisp.step - cubic.step) if crisp.lifted and cubic.lifted else 0.0
        record.error = max(abs(s_best - s_coarse), pixel / factors[1], spread)
        lifted = _clean_step(h, band, part, sides) + (s_best - s0) * part
        h[sl] = np.where(np.isfinite(lifted[sl]), lifted[sl], h[sl])
        error[part] = record.error
        record.step_after, record.status = s_best, "lifted"
        record.seconds = time.perf_counter() - t1
        parts.append(record)
    return h, parts, error
