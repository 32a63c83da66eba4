"""Noise of detector images: its level in the STSA-corrected images, each recording's own
relative noise, and how the corrected images' noise divides between the object and the flat plate.

The corrected images C = I / F carry sigma_C^2 = sigma_object^2 + sigma_flat^2 (relative noise of
each); the mean of N flat recordings (:func:`~.stsa.mean_flat`) divides sigma_flat^2 by N. The
inversion and the model gradient weight their misfits by :func:`estimate_noise`; the commands
report :func:`noise_shares`.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..constants import DETECTOR_NAMES
from ..arguments import shown
from ..errors import EloInputError

#: A level below this fraction of its images' median gives the pixel no weight (a flat plate's
#: value in the inversion, a smoothed image's in :func:`relative_noise`).
MIN_FLAT = 1e-3
#: The flat's share of the noise variance from which the summary suggests more recordings of it.
FLAT_SHARE_ADVICE = 0.1
#: Relative noise of the corrected images below which the summary says the noise is negligible
#: and suggests nothing (a recording has 0.5-1 %; noise-free renders leave ~1e-7 of float32 and
#: Monte Carlo residue, where "repeat --flat" would be advice about nothing).
NEGLIGIBLE_NOISE = 1e-4


#: The directions of the second differences (row step, column step): along rows, along columns
#: and both diagonals. Noise is the same in each; relief with straight features (ridges, melt
#: tracks, grooves) adds to all but the one along them.
DIRECTIONS = ((0, 1), (1, 0), (1, 1), (1, -1))

#: The largest noise level (standard deviation of the corrected images, whose level is about 1)
#: a user may give: 100 %. Above it the images hold no signal, and 1e300 overflowed its square.
MAX_NOISE = 1.0
#: The smallest noise level a user may give. Float32 images about 1 resolve 6e-8, so a level far
#: below it says nothing about the images, and 1e-300 overflowed the misfit's chi^2 (a warning, then
#: uncertainties of 0).
MIN_NOISE_GIVEN = 1e-9
#: How messages state :func:`is_noise_level`'s range.
NOISE_RANGE = (f"a number from {MIN_NOISE_GIVEN:g} to {MAX_NOISE:g} (corrected units: a standard deviation of "
               "images about 1")


def is_noise_level(level: float) -> bool:
    """Whether a float is a noise level a user may give (:data:`MIN_NOISE_GIVEN` to
    :data:`MAX_NOISE`): the one test of :func:`check_noise` and the command line's ``--noise``.

    >>> is_noise_level(0.01), is_noise_level(1e-300), is_noise_level(2.0), is_noise_level(float("nan"))
    (True, False, False, False)
    """
    return bool(np.isfinite(level)) and MIN_NOISE_GIVEN <= level <= MAX_NOISE


def check_noise(noise, what: str = "noise") -> float:
    """``noise`` as a float, if it is a noise level of the corrected images: finite, from
    :data:`MIN_NOISE_GIVEN` to :data:`MAX_NOISE`.

    Examples
    --------
    >>> check_noise(0.01)
    0.01
    >>> check_noise(1e300)
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: noise=1e+300: must be a number from 1e-09 to 1 (corrected units: a standard deviation of images about 1)
    """
    try:
        level = float(noise)
    except (TypeError, ValueError):
        level = float("nan")
    if not is_noise_level(level) or isinstance(noise, bool):
        raise EloInputError(f"{what}={shown(noise)}: must be {NOISE_RANGE})")
    return level


def _shifted(a, dr, dc, k):
    """``a`` shifted by k steps of (dr, dc) over the window where all three of the second
    difference's samples (k = 0, 1, 2) exist."""
    h, w = a.shape[-2:]
    r0 = k * dr
    c0 = k * dc if dc >= 0 else (2 + k * dc) * -dc
    return a[..., r0:h - 2 * dr + r0, c0:w - 2 * abs(dc) + c0]


def estimate_noise(corrected, weights) -> float:
    """Noise level of the corrected images from their second differences (1.4826 MAD / sqrt(6)).

    Per image the smallest level over four directions (:data:`DIRECTIONS`: rows, columns and both
    diagonals), then the median over the images. White noise gives every direction the same
    level; an image's own structure adds to it, little in a median where it is sparse (edges, the
    blurred relief), but where it is dense and straight (the corrugated sheet's ridges 2.3 pixels
    apart, melt tracks a few pixels apart) it fills the median of the directions across it, and
    the level along it is the noise's. Measured on noise-free renders of the corrugated sheet at
    256^2 (zeta25): 2.65 % when the directions were only rows and columns and the median taken over
    both, 0.0000 % now; with 1 % noise on object and flat (1.41 % in the ratio) 3.2 % then, 0.92 %
    now (the ratio's noise is relative, and the sheet's flanks facing away hold less signal). On
    the melt plate, hills, rough and stepped layers with that noise the two agree within 4 %. On
    white noise the minimum reads low: 0.995 of the noise at 256^2, 0.961 at 32^2 (mean of 40 and
    200 draws of four images).
    """
    out = []
    for c, w in zip(corrected, weights):
        c, w = np.asarray(c, float), np.asarray(w, float)
        if min(c.shape) < 3:
            continue
        levels = []
        for dr, dc in DIRECTIONS:
            d2 = _shifted(c, dr, dc, 0) - 2.0 * _shifted(c, dr, dc, 1) + _shifted(c, dr, dc, 2)
            ok = (_shifted(w, dr, dc, 0) * _shifted(w, dr, dc, 1) * _shifted(w, dr, dc, 2)) > 0
            if ok.any():
                levels.append(1.4826 * float(np.median(np.abs(d2[ok]))) / np.sqrt(6.0))
        if levels:
            out.append(min(levels))
    return float(np.median(out)) if out else 0.0


def relative_noise(images: Mapping, smoothing_px: float = 4.0) -> float:
    """Relative noise level (std / signal) of one set of detector images (or of any images given by
    name), e.g. the object's or the flat plate's alone: :func:`estimate_noise` of each image over its own Gaussian-smoothed
    version (``smoothing_px``), which divides out the slowly varying level (the detectors' solid
    angles, the material). Where the corrected images carry sigma_C^2 = sigma_object^2 +
    sigma_flat^2, this tells the two shares apart: how much a mean of more flat recordings
    (:func:`~.stsa.mean_flat`) would gain."""
    from scipy.ndimage import gaussian_filter

    ratios, weights = [], []
    for n in [n for n in DETECTOR_NAMES if n in images] or list(images):  # a set of four, or any images
        a = np.asarray(images[n], float)
        smooth = gaussian_filter(np.where(np.isfinite(a), a, 0.0), smoothing_px, mode="nearest")
        ok = np.isfinite(a) & (np.abs(smooth) > MIN_FLAT * np.median(np.abs(smooth)))
        ratios.append(np.where(ok, a / np.where(ok, smooth, 1.0), 0.0))
        weights.append(ok.astype(float))
    return estimate_noise(np.stack(ratios), np.stack(weights))


def noise_shares(images: Mapping, flats: Mapping | None, flat_count: int) -> tuple[dict, str]:
    """The object's and the flat's relative noise (:func:`relative_noise`) for a header, and a
    line saying how much of the corrected images' noise the flat holds and what four times as many
    recordings of it would leave ("" without a flat or without a finite estimate).

    Parameters
    ----------
    images, flats : mapping of str to ndarray
        The object's and the (mean) flat plate's detector images; ``flats`` None: no flat.
    flat_count : int
        How many flat recordings ``flats`` is the mean of.

    Returns
    -------
    shares : dict
        ``noise_object``, ``noise_flat`` (relative, std / signal) and ``flat_recordings``; empty
        without a flat.
    line : str
        The summary line for the user.
    """
    if flats is None:
        return {}, ""
    so, sf = relative_noise(images), relative_noise(flats)
    if not (np.isfinite(so) and np.isfinite(sf)):
        return {}, ""
    n = flat_count
    what = "1 recording" if n == 1 else f"the mean of {n} recordings"
    line = f"image noise: object {100 * so:.2g} %, flat plate {100 * sf:.2g} % ({what}): "
    shares = {"noise_object": so, "noise_flat": sf, "flat_recordings": n}
    if np.hypot(so, sf) < NEGLIGIBLE_NOISE:
        return shares, line + "negligible (images without noise, e.g. renders)"
    share = sf ** 2 / (so ** 2 + sf ** 2)
    more = sf ** 2 / 4 / (so ** 2 + sf ** 2 / 4)
    line += f"the flat holds {100 * share:.0f} % of the corrected images' noise variance"
    if share >= FLAT_SHARE_ADVICE:
        line += f"; the mean of {4 * n} flat recordings would hold {100 * more:.0f} % (repeat --flat)"
    return shares, line


#: Window (pixels per side) over which a pixel's squared misfit is averaged (:func:`local_chi2`):
#: 49 pixels x 3 degrees of freedom give the mean's noise a standard deviation of 0.12.
CHI2_WINDOW_PX = 7


def local_chi2(misfit, expected, window: int = CHI2_WINDOW_PX) -> np.ndarray:
    """(misfit / expected)^2 averaged over ``window`` x ``window`` pixels: a chi-square per datum
    whose mean is 1 where the misfit is noise, and far above where a model does not reproduce the
    images (a defect finer than the model, a step). Its square root scales a noise-only error bar
    to one that covers the misfit too (Birge's ratio, taken locally).

    Examples
    --------
    >>> m = np.full((20, 20), 0.01); m[10, 10] = 0.1
    >>> c = local_chi2(m, 0.01, 5)
    >>> round(float(c[0, 0]), 3), round(float(c[10, 10]), 3)
    (1.0, 4.96)
    """
    from scipy.ndimage import uniform_filter

    return uniform_filter((np.asarray(misfit, float) / expected) ** 2, window, mode="nearest")
