"""The finest band of ``invert``'s correction of the start, taken only where the start's misfit
demands it.

The field's solve deconvolves the beam: near the Nyquist frequency the blur leaves a third to a half
of the signal, and the noise of the images comes back amplified there. Where the start already
reproduces the images to within their noise (its local chi-square, :func:`~.noise.local_chi2`,
below :func:`~.local_inversion.threshold`), that band of the solve's correction is fitted noise:
the start holds almost none (its heights are integrated slopes, whose noise falls as the square of
the frequency). So the correction d = solve - start is kept in full where the start's misfit is
flagged, and elsewhere only its low-pass G * d (a Gaussian of :data:`LOW_PASS_FWHM` beam widths):

    heights = start + G * d + w (d - G * d)

with w the weight of :func:`~.local_inversion.taken_weight` on the flagged pixels (the same rule by
which a region's heights are taken: less the chi-square window's reach, grown by the beam). It is
the local inversion's rule (refine where the misfit lies) applied to the field, and the pipeline's
last step (:func:`~.inversion.invert_heights`), on the correction that the regions, the step
search and the cut across cliffs made too.

The error bars keep the solve's noise part: where the fine band is dropped, the images fix it only
to within that spread, and the start's fine band is one surface within it, not the truth's. Drawn
through the same operator instead, the noise part fell below the actual error: the stepped
layer's ``height_error`` covered 63 / 88 % of the pixels within 1x / 2x (74 / 95 % as kept).

Measured (2026-12-07; melt plate 512^2, 0.27 mm beam, zeta25, sixteen recordings averaged, i.e.
0.25 % noise, noise seeds 7 / 8 / 9): height error against the start's 0.77 / 0.79 / 0.89 with the
whole correction, 0.63 / 0.63 / 0.75 with this; on seed 7 the squares' edges (13 % of the pixels)
1.81 -> 1.79 um, the rest 1.38 -> 1.05 um. Without noise 0.645 -> 0.646 um (28 % of the field
flagged), at 1 % noise the solve takes no step and nothing changes. A raised square with a rim
and ripples (model images 128^2, 0.156 mm pixels, 0.25 % noise, seeds 1-3): 34 deg detectors
0.79-0.80 -> 0.73-0.74 um (its edges 1.57 -> 1.57 um, the blank plate 0.46-0.48 -> 0.21-0.26 um),
the melt plate's layout 1.37-1.41 -> 1.13-1.18 um (edges 1.95-1.98 um before and after); there
``height_error`` covers 76-79 / 94 % within 1x / 2x (64-66 / 91 % before): conservative where the
start's fine band happens to be right (a blank plate). Stepped layer and hills (1 % noise, rows D2,
D3): the same heights to 0.1 um RMS. The low-pass width matters little: 1 / 2 / 3 beam widths gave
0.630 / 0.628 / 0.628 on the melt plate (seed 7); a mask grown by 5 pixels 0.64. What it cannot
do: where the start's misfit is flagged the correction's noise stays (there it is not told apart
from the relief).
"""

from __future__ import annotations

import numpy as np

from .local_inversion import large_areas, take_scale, taken_weight, threshold
from .noise import local_chi2

#: Sigma of the low-pass kept everywhere, in beam FWHMs (at least one pixel).
LOW_PASS_FWHM = 2.0


def low_pass_px(fwhm_mm: float, pixel_mm) -> float:
    """Sigma (pixels) of the low-pass kept where the start fits: :data:`LOW_PASS_FWHM` beam widths,
    at least one pixel.

    Examples
    --------
    >>> round(low_pass_px(0.27, (0.15625, 0.15625)), 2), low_pass_px(0.0, (0.2, 0.2))
    (3.46, 1.0)
    """
    return max(1.0, LOW_PASS_FWHM * float(fwhm_mm) / float(np.mean(pixel_mm)))


def half_wavelength(sigma_px: float) -> float:
    """The wavelength (pixels) at which the fine band (1 - G, G a Gaussian of ``sigma_px``) passes
    half the amplitude: pi sigma sqrt(2 / ln 2); shorter ones pass nearly whole.

    Examples
    --------
    >>> round(half_wavelength(1.0), 2)
    5.34
    """
    return float(np.pi * sigma_px * np.sqrt(2.0 / np.log(2.0)))


def band_weight(start_misfit, expected: float, detectors: int, fwhm_mm: float, pixel_mm) -> np.ndarray:
    """Weight (0-1) of the correction's fine band: 1 where the start's misfit (RMS over the
    detectors, per pixel) is not noise (local chi-square over ``expected`` above
    :func:`~.local_inversion.threshold`, in areas of at least
    :data:`~.local_inversion.MIN_FLAGGED_PX` pixels), tapered as
    :func:`~.local_inversion.taken_weight`.

    Examples
    --------
    >>> m = np.full((30, 30), 0.01); m[10:20, 10:20] = 0.05
    >>> w = band_weight(m, 0.01, 4, 0.27, (0.2, 0.2))
    >>> float(w[15, 15]), float(w[0, 0])
    (1.0, 0.0)
    """
    flagged = large_areas(local_chi2(start_misfit, max(float(expected), 1e-12)) > threshold(detectors=detectors))
    return taken_weight(flagged, *take_scale(fwhm_mm, pixel_mm))


def gated(correction, weight, sigma_px: float) -> np.ndarray:
    """The ``correction``'s low-pass (Gaussian of ``sigma_px``) everywhere, its remainder times
    ``weight``.

    Examples
    --------
    A 2-pixel pattern (all fine band) on a plateau, taken only on the right half:

    >>> d = np.zeros((40, 40)); d[::2, ::2] = 1e-3; d += 0.01 - d.mean()
    >>> w = np.zeros((40, 40)); w[:, 20:] = 1.0
    >>> g = gated(d, w, 2.0)
    >>> bool(np.allclose(g[10:30, 8:12], 0.01, atol=1e-6)), bool(np.allclose(g[:, 20:], d[:, 20:]))
    (True, True)
    """
    from scipy.ndimage import gaussian_filter

    d = np.asarray(correction, float)
    low = gaussian_filter(d, sigma_px, mode="nearest")
    return low + np.asarray(weight, float) * (d - low)
