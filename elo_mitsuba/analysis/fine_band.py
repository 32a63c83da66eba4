"""The finest band of ``invert``'s correction of the start, taken only where the start's misfit
demands it, and the band finer than the beam only where the images do.

The field's solve deconvolves the beam: near the Nyquist frequency the blur leaves a third to a half
of the signal, and the noise of the images comes back amplified there. Where the start already
reproduces the images to within their noise (its local chi-square, :func:`~.noise.local_chi2`,
below :func:`~.local_inversion.threshold`), that band of the solve's correction is fitted noise:
the start holds almost none (its heights are integrated slopes, whose noise falls as the square of
the frequency). So the correction d = solve - start is kept where the start's misfit is flagged,
and elsewhere only its low-pass G * d (a Gaussian of :data:`LOW_PASS_FWHM` beam widths).

Where it is kept, it is first kept as the beam sees it, B * d (a Gaussian of the beam's own
standard deviation, :func:`beam_px`): the band finer than the beam is what the images fix least,
and on renders it fits what the model lacks (the renderer's surface inside a pixel, its
penumbrae; row I1) as readily as relief. Only where the heights with B * d leave a misfit above the
noise (the same test as the start's) do the images demand that band, and d is taken whole there
(Morozov's discrepancy principle, per area: the smoothest correction that fits to the noise):

    heights = start + G * d + w (B * d - G * d) + w v (d - B * d)

with w the weight of :func:`~.local_inversion.taken_weight` on the pixels where the start's misfit
is flagged and v on those where B * d's is (the same rule by which a region's heights are taken:
less the chi-square window's reach, grown by the beam). It is the local inversion's rule (refine
where the misfit lies) applied to the field, and the pipeline's last step
(:func:`~.inversion.invert_heights`), on the correction that the regions, the step search and the
cut across cliffs made too; it costs one more evaluation of the model.

The error bars keep the solve's noise part: where the fine band is dropped, the images fix it only
to within that spread, and the start's fine band is one surface within it, not the truth's. Drawn
through the same operator instead, the noise part fell below the actual error: the stepped
layer's ``height_error`` covered 63 / 88 % of the pixels within 1x / 2x (74 / 95 % as kept).

Measured (2026-12-07; melt plate 512^2, 0.27 mm beam, zeta25, sixteen recordings averaged, i.e.
0.25 % noise, noise seeds 7 / 8 / 9): height error against the start's 0.77 / 0.79 / 0.89 with the
whole correction, 0.63 / 0.63 / 0.75 with the low-pass where the start fits, 0.59 / 0.59 / 0.71
with the band finer than the beam dropped where B * d fits (4 % of the field keeps it). Seed 7
by areas: the squares' walls (21 % of the pixels, the steepest 13 % grown by a pixel) 1.73 ->
1.54 um (B * d everywhere: 1.45), the rest 0.98 -> 0.95 um. Without noise 0.645 -> 0.646 ->
0.625 um; at 1 % noise the solve takes no step and nothing changes. B * d everywhere, without the
test, gave 0.57 / 0.57 / 0.70 on the melt plate but lost the edges where the model is exact: a
raised square with a rim and ripples (model images 128^2, 0.156 mm pixels, 0.25 % noise, seed 1)
0.74 -> 1.17 um, its edges 1.57 -> 2.59 um; with the test 0.736 -> 0.732 um, edges 1.574 -> 1.573
um (against the whole correction 0.80 um, edges 1.57, blank plate 0.47 -> 0.25 um). The same with
the beam 10 % wider or narrower than the model's, or the surface's walls finer than a pixel: no
change beyond 0.01 um. Stepped layer and hills (1 % noise, rows D2, D3, I3, I4): the same heights
to 0.01 um RMS. The low-pass width matters little: 1 / 2 / 3 beam widths gave 0.630 / 0.628 /
0.628 on the melt plate (seed 7, before B); a mask grown by 5 pixels 0.64. What it cannot do:
where the misfit is flagged the correction's noise stays (there it is not told apart from the
relief).
"""

from __future__ import annotations

import numpy as np

from ..schema import fwhm_to_sigma
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


def band_weight(misfit, expected: float, detectors: int, fwhm_mm: float, pixel_mm) -> np.ndarray:
    """Weight (0-1) of the correction's fine band: 1 where ``misfit`` (the start's, or that of
    the heights with the correction as the beam sees it; RMS over the detectors, per pixel) is not
    noise (local chi-square over ``expected`` above
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
    flagged = large_areas(local_chi2(misfit, max(float(expected), 1e-12)) > threshold(detectors=detectors))
    return taken_weight(flagged, *take_scale(fwhm_mm, pixel_mm))


def beam_px(fwhm_mm: float, pixel_mm) -> float:
    """The beam's standard deviation in pixels (0 without blur): the scale below which the correction
    is taken only where the images demand it (:func:`gated`'s ``whole``).

    Examples
    --------
    >>> round(beam_px(0.27, (0.15625, 0.15625)), 2), beam_px(0.0, (0.2, 0.2))
    (0.73, 0.0)
    """
    return float(fwhm_to_sigma(fwhm_mm) / float(np.mean(pixel_mm)))


def gated(correction, weight, sigma_px: float, beam_sigma_px: float = 0.0, whole=None) -> np.ndarray:
    """The ``correction``'s low-pass (Gaussian of ``sigma_px``) everywhere; times ``weight`` its
    remainder as the beam sees it (under a Gaussian of ``beam_sigma_px``; 0: as is); and times
    ``weight`` x ``whole`` (default 0) the rest, the correction's band finer than the beam.

    Examples
    --------
    A 2-pixel pattern (all fine band) on a plateau, taken only on the right half:

    >>> d = np.zeros((40, 40)); d[::2, ::2] = 1e-3; d += 0.01 - d.mean()
    >>> w = np.zeros((40, 40)); w[:, 20:] = 1.0
    >>> g = gated(d, w, 2.0)
    >>> bool(np.allclose(g[10:30, 8:12], 0.01, atol=1e-6)), bool(np.allclose(g[:, 20:], d[:, 20:]))
    (True, True)

    Seen through a beam of one pixel the pattern is all but gone; ``whole`` brings it back:

    >>> float(np.ptp(gated(d, w, 2.0, 1.0)[10:30, 28:32])) < 0.1 * float(np.ptp(d))
    True
    >>> bool(np.allclose(gated(d, w, 2.0, 1.0, np.ones((40, 40)))[:, 20:], d[:, 20:]))
    True
    """
    from scipy.ndimage import gaussian_filter

    d = np.asarray(correction, float)
    w = np.asarray(weight, float)
    low = gaussian_filter(d, sigma_px, mode="nearest")
    seen = gaussian_filter(d, beam_sigma_px, mode="nearest") if beam_sigma_px > 0 else d
    out = low + w * (seen - low)
    return out if whole is None else out + w * np.asarray(whole, float) * (d - seen)
