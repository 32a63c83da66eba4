"""Does the scan resolve the relief? Heights integrated from every other pixel, against all of them.

Normal integration takes the height difference of two neighbouring pixels from their two slopes
(the mean of the pair, :mod:`.integrate`). That is exact to second order where the surface is
smooth between the pixel centres, and wrong by up to half a pixel times the slope's jump where it
bends between them: a ridge, a valley, a cliff's edge, roughness finer than two pixels. The
slopes' samples then do not fix the height, nothing in the gradient says so (the field stays
integrable: the corrugated sheet's integrability residual is 0.000), and where the bends run on
without closing (ridges along a whole row) their errors add up over the field. The corrugated
sheet (1.41 mm period, 45-degree flanks, 0.20 mm RMS relief) rendered at 256^2 and integrated comes
out with 0.48 mm RMS height error, 0.058 mm at 1024^2 (RMS about the mean).

This module measures it from the gradient alone: the same solver integrates the gradient of the
two diagonal sub-lattices of every other pixel (pixels (2i, 2j) and (2i+1, 2j+1): twice the
pitch), and each result is compared with the full-resolution heights at its pixels (each
connected region of the full map with its own mean, as the heights are relative per region). The
RMS difference, :func:`half_sampling`, is about what halving the sampling costs. Measured on
orthographic renders without noise (the map's actual error less a best-fitting quadric):

* where the relief is resolved, the pair rule's error grows with the square of the pitch, and the
  difference overstates the map's own error: the melt plate at 256^2 20 um against 6.8 um, at
  1024^2 5.0 against 3.0 um (about the mean); the rough layer of :mod:`elo_mitsuba.objects.rough_layer` at 256^2
  6.2 against 1.3 um, at 1024^2 0.28 against 0.2 um;
* where bends fall between pixels it is about the map's error: the corrugated sheet at 256^2
  0.42 mm against 0.48 mm, at 1500^2 0.080 against 0.112 mm; the stepped layer's cliffs at 256^2
  0.20 against 0.17 mm. Regular ridges can beat with the sampling: at 1024^2 the sheet's
  difference is 0.435 mm against an error of 0.058 mm (about the mean; every other pixel falls on a nearly
  commensurate pitch, whose errors add up coherently), an overstatement, not a miss.

It does not see errors both samplings share (a bias of the slopes, the beam's blur, a step none
of the slopes holds, pixels masked for shadows: the hills at 256^2 under layout zeta50, 1 % masked, err by 12.7 um
where it says 7.1 um). ``reconstruct`` reports it (header ``quality``,
``half_sampling_mm``) and warns when it exceeds :data:`MAX_HALF_SAMPLING` of the relief's RMS.
"""

from __future__ import annotations

import numpy as np

from ..grid import pixel_size
from .quadric import fit_quadric

#: ``reconstruct`` warns when heights from every other pixel differ from the full map's by more
#: than this fraction of the relief's RMS (the heights less their best-fitting quadric). Measured
#: (orthographic renders, no noise; actual error less a quadric): the corrugated sheet at 1500^2
#: errs by 0.112 mm RMS, 48 % of its map's relief RMS, with a difference of 0.080 mm (0.35 of it);
#: the melt plate at 1024^2 by 3.0 um (about the mean) with 5.0 um (0.29); at 256^2 by 6.8 um with 20 um (1.1).
#: The smooth hills and the rough layer at 256^2 stay far below (0.005, 0.07).
MAX_HALF_SAMPLING = 0.25
#: Fewest pixels per side for the test (each sub-lattice has half of them).
MIN_SIDE = 8


#: The two diagonal sub-lattices of every other pixel: (2i, 2j) and (2i + 1, 2j + 1).
SUB_LATTICES = tuple((slice(o, None, 2), slice(o, None, 2)) for o in (0, 1))


def half_sampling(dzdx, dzdy, field_mm, height, mask_out, integrate) -> float | None:
    """RMS difference (mm) between heights integrated from every other pixel and ``height``.

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        The gradient that was integrated (mm/mm); untrusted pixels as the solver saw them.
    field_mm : float or (float, float)
        Scan field in mm (the sub-lattices keep it: their pixels are twice as large).
    height, mask_out : ndarray (H, W)
        The full-resolution result (``mask_out`` True: no height).
    integrate : callable
        ``integrate(dzdx, dzdy, field_mm, mask) -> (height, mask_out)``: the solver that made
        ``height``, with its options.

    Returns
    -------
    float or None
        RMS over both sub-lattices' trusted pixels of the difference, each connected region of
        the full map's trusted pixels with its own mean removed; None for fewer than
        :data:`MIN_SIDE` pixels per side or no common trusted pixel.
    """
    from scipy import ndimage

    if min(np.shape(height)) < MIN_SIDE:
        return None
    masked = np.asarray(mask_out, dtype=bool)
    trusted = ~masked
    labels, n = ndimage.label(trusted)
    height = np.asarray(height, float)
    total = count = 0.0
    for sl in SUB_LATTICES:
        h_sub, m_sub = integrate(dzdx[sl], dzdy[sl], field_mm, masked[sl])
        common = trusted[sl] & ~np.asarray(m_sub, dtype=bool)
        if not common.any():
            continue
        diff = (np.asarray(h_sub, float) - height[sl])[common]
        lab = labels[sl][common]
        sums = np.bincount(lab, weights=diff, minlength=n + 1)
        counts = np.bincount(lab, minlength=n + 1)
        diff = diff - sums[lab] / counts[lab]
        total += float(np.sum(diff ** 2))
        count += diff.size
    return float(np.sqrt(total / count)) if count else None


def resolution(dzdx, dzdy, field_mm, height, mask_out, integrate) -> dict:
    """Whether the scan resolves the relief of ``height`` (integrated from ``dzdx``, ``dzdy`` by
    ``integrate``, as for :func:`half_sampling`): ``half_sampling_mm``, ``relief_rms_mm`` (the RMS
    about the best-fitting quadric of the pixels with a height) and, where
    :func:`resolution_warning` fires, its ``warning`` and ``flag`` (else None)."""
    height = np.asarray(height, float)
    half = half_sampling(dzdx, dzdy, field_mm, height, mask_out, integrate)
    relief_rms = round(fit_quadric(height, ~np.asarray(mask_out, dtype=bool))[3], 6)
    said = resolution_warning(half, relief_rms, max(pixel_size(height.shape, field_mm))) or (None, None)
    return {"half_sampling_mm": half, "relief_rms_mm": relief_rms, "warning": said[0], "flag": said[1]}


def resolution_warning(half_sampling_mm, relief_rms_mm, pixel_mm):
    """The warning (without advice: the command adds its own) and its few words (a preview's
    title) when :func:`half_sampling` exceeds :data:`MAX_HALF_SAMPLING` of the relief's RMS, else
    None."""
    if half_sampling_mm is None or not (half_sampling_mm > MAX_HALF_SAMPLING * relief_rms_mm
                                        and half_sampling_mm > 1e-3 * pixel_mm):
        return None
    line = (f"heights integrated from every other pixel differ from these by {half_sampling_mm:.3g} mm RMS, "
            f"{half_sampling_mm / max(relief_rms_mm, 1e-300):.2g}x the relief's RMS of {relief_rms_mm:.3g} mm: the "
            "scan does not resolve the relief (ridges, edges, cliffs or roughness of a few pixels: the slopes' "
            "samples do not fix the height between them), and the heights' error may be as large")
    return line, f"relief not resolved (every other pixel: {half_sampling_mm:.3g} mm RMS)"
