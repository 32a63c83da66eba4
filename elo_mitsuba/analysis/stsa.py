"""STSA contrast correction, sum images and normalised difference images (Sec. 2.1.4, Eqs. 15, 23).

All functions take and return images in the package orientation (:mod:`elo_mitsuba.grid`: row 0 = +y edge, columns
towards +x; see :mod:`elo_mitsuba.analysis.layout`). Detector images are given as a mapping
``{"right": R, "left": L, "back": B, "front": F}`` in any consistent unit (N_d/N_0 from the
forward model, or volts from a machine); the STSA correction divides the unit out.

Every function returns a boolean ``mask`` alongside its images: ``True`` (1) means *untrusted*.
Untrusted pixels hold 0 in the returned images, never NaN or Inf.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ..arguments import real_array
from ..constants import DETECTOR_NAMES
from ..errors import EloInputError

#: A flat-plate pixel is unusable below this fraction of the median |flat| of its detector.
MIN_FLAT_FRACTION = 1e-3
#: Eq. 15 divides by R^C + L^C (B^C + F^C): below this (flat plate: 2) the ratio is noise.
MIN_SUM = 0.05
#: A pixel above this many times its image's median (over the pixels that are not 0) is no
#: detector signal but a saturated or glitched one: the brightest pixel of the validation surfaces
#: (steep hills, 0.1-1 mm steps, rough layer; detectors 15 or 65 deg up; beam 0 or 0.27 mm; 1st
#: event, 128^2) is at most 9 times its image's median. A single 1e30 pixel otherwise drove the
#: inversion's per-pixel scale and misfit to 1e32, its heights to 2 m and its error bars to 1e16 um.
SPIKE = 1000.0
#: ... the median taken over at most this many pixels (evenly strided): the bound is 100x coarser
#: than the contrast it allows.
SPIKE_SAMPLE = 1 << 16


def spike_bound(image) -> float:
    """:data:`SPIKE` times the median |value| of ``image``'s finite pixels that are not 0 (inf
    when there are none): a pixel above it is no detector signal.

    Examples
    --------
    >>> import numpy as np
    >>> img = np.ones((4, 4)); img[1, 2] = 1e30
    >>> spike_bound(img), bool(np.sum(np.abs(img) > spike_bound(img)) == 1)
    (1000.0, True)
    """
    image = np.asarray(image, float)
    sample = np.abs(image.ravel()[::max(1, image.size // SPIKE_SAMPLE)])
    lit = sample[(sample > 0) & np.isfinite(sample)]
    if not lit.size:  # every sampled pixel dark: the whole image decides
        mag = np.abs(image)
        lit = mag[(mag > 0) & np.isfinite(mag)]
    return SPIKE * float(np.median(lit)) if lit.size else float("inf")


def check_images(images: Mapping, what: str = "images", names=DETECTOR_NAMES) -> dict:
    """Return ``{name: float64 array}`` for the four detectors, all 2-D and of one shape."""
    if not isinstance(images, Mapping):
        raise EloInputError(f"{what}: expected a mapping {{detector: image}}, got {type(images).__name__}")
    missing = [n for n in names if n not in images]
    if missing:
        raise EloInputError(f"{what}: missing detector image(s) {', '.join(missing)}; need {', '.join(names)}")
    out = {n: real_array(f"{what}: {n}", images[n], ndim=None) for n in names}
    shapes = {a.shape for a in out.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise EloInputError(f"{what}: detector images must be 2-D and of one shape, got {sorted(shapes)}")
    return out


def mean_flat(recordings: Sequence[Mapping], what: str = "flat-plate images") -> dict:
    """The mean of several recordings of the flat plate, per detector.

    The flat divides every object pixel (Eq. 15), so its noise enters the corrected images as
    much as the object's own: averaging N recordings (same detectors, beam and field) divides its
    share of the variance by N. On the melt plate at 1 % noise the flat's noise is about half of
    the integrated height error (validation/REPORT.md, row I6). A recording may differ from the
    others by a constant factor (beam current): the mean is still the image of a flat plate.

    Parameters
    ----------
    recordings : sequence of mappings of str to ndarray (H, W)
        One mapping ``{detector: image}`` per recording, all of one shape and one unit.
    what : str
        How messages name them.

    Returns
    -------
    dict of str to ndarray (H, W)
        The mean image of each detector (float64).

    Examples
    --------
    >>> import numpy as np
    >>> names = ("right", "left", "back", "front")
    >>> first = {d: np.full((2, 2), 1.0) for d in names}
    >>> second = {d: np.full((2, 2), 3.0) for d in names}      # a beam current 3 times the first's
    >>> flat = mean_flat([first, second])
    >>> sorted(flat), flat["right"].tolist()
    (['back', 'front', 'left', 'right'], [[2.0, 2.0], [2.0, 2.0]])
    """
    sets = [check_images(r, f"{what} (recording {i + 1})" if len(recordings) > 1 else what)
            for i, r in enumerate(recordings)]
    if not sets:
        raise EloInputError(f"{what}: no recordings given")
    shapes = [next(iter(s.values())).shape for s in sets]
    if len(set(shapes)) != 1:
        raise EloInputError(f"{what}: the recordings differ in shape "
                            f"({', '.join(f'{i + 1}: {w}x{h}' for i, (h, w) in enumerate(shapes))} px); "
                            "record every flat with the object's resolution")
    return {n: np.mean([s[n] for s in sets], axis=0) for n in DETECTOR_NAMES}


def stsa_correct(images: Mapping, flats: Mapping, *, min_flat_fraction: float = MIN_FLAT_FRACTION):
    """Surface tilt and solid angle (STSA) correction: object image / flat-plate image (Sec. 2.1.4).

    Parameters
    ----------
    images : mapping of str to ndarray (H, W)
        Object images R, L, B, F of the four detectors.
    flats : mapping of str to ndarray (H, W)
        Images of a plane plate (n_C = [0, 0, 1], Eq. 18) recorded with the same detectors, beam
        and field, in the same unit.
    min_flat_fraction : float
        A flat pixel whose magnitude is below this fraction of the median magnitude of that
        detector's flat image (or not finite) cannot normalise anything and is masked.

    Returns
    -------
    corrected : dict of str to ndarray (H, W)
        R^C = R / C_R etc. (dimensionless; 1 for the flat plate itself, Eq. 21).
    mask : ndarray of bool (H, W)
        True where any detector's flat or object pixel is not usable; corrected images hold 0 there.

    Examples
    --------
    >>> import numpy as np
    >>> flats = {d: np.full((2, 2), 0.002) for d in ("right", "left", "back", "front")}
    >>> images = {d: 1.5 * f for d, f in flats.items()}
    >>> corrected, mask = stsa_correct(images, flats)
    >>> corrected["right"].round(4).tolist(), bool(mask.any())
    ([[1.5, 1.5], [1.5, 1.5]], False)
    """
    img = check_images(images, "object images")
    flat = check_images(flats, "flat-plate images")
    shape = next(iter(img.values())).shape
    if next(iter(flat.values())).shape != shape:
        raise EloInputError(
            f"flat-plate images have shape {next(iter(flat.values())).shape}, object images {shape}; "
            "record both with the same resolution"
        )
    mask = np.zeros(shape, dtype=bool)
    for n in DETECTOR_NAMES:
        f = flat[n]
        finite = np.isfinite(f)
        ref = np.median(np.abs(f[finite])) if finite.any() else 0.0
        if not ref > 0:
            raise EloInputError(f"flat-plate image of detector {n!r} is zero everywhere; cannot correct")
        mask |= ~finite | (np.abs(np.where(finite, f, 0.0)) <= min_flat_fraction * ref) | ~np.isfinite(img[n])
    corrected = {}
    safe = ~mask
    for n in DETECTOR_NAMES:
        out = np.zeros(shape)
        np.divide(img[n], flat[n], out=out, where=safe)
        corrected[n] = out
    return corrected, mask


def sum_images(corrected: Mapping) -> tuple[np.ndarray, np.ndarray]:
    """Material-contrast sum images R^C + L^C and B^C + F^C (Eq. 23).

    In the point-detector Lambert model both equal ``(eta/eta_C) 2/|n_S| [1 - (n_Sx x + n_Sy y)/d_h]``.
    Non-finite inputs give 0 (callers use the masks of :func:`stsa_correct` /
    :func:`normalised_differences`).

    Parameters
    ----------
    corrected : mapping of str to ndarray (H, W)
        STSA-corrected images (:func:`stsa_correct`), dimensionless.

    Returns
    -------
    sum_x, sum_y : ndarray (H, W)
        R^C + L^C and B^C + F^C (2 on the flat plate).

    Examples
    --------
    >>> import numpy as np
    >>> corrected = {"right": np.array([[1.2]]), "left": np.array([[0.8]]),
    ...              "back": np.array([[1.1]]), "front": np.array([[np.nan]])}
    >>> sx, sy = sum_images(corrected)
    >>> round(float(sx[0, 0]), 4), float(sy[0, 0])
    (2.0, 0.0)
    """
    c = check_images(corrected, "corrected images")
    s_x = np.nan_to_num(c["right"] + c["left"], nan=0.0, posinf=0.0, neginf=0.0)
    s_y = np.nan_to_num(c["back"] + c["front"], nan=0.0, posinf=0.0, neginf=0.0)
    return s_x, s_y


def normalised_differences(corrected: Mapping, *, min_sum: float = MIN_SUM):
    """Normalised difference images of Eq. 15.

    M_x = (R^C - L^C) / (R^C + L^C),   M_y = (B^C - F^C) / (B^C + F^C)   (dimensionless).

    Parameters
    ----------
    corrected : mapping of str to ndarray (H, W)
        STSA-corrected images (:func:`stsa_correct`).
    min_sum : float
        Pixels where a sum image is below this (the flat plate gives 2) are masked: the ratio is
        undefined at 0 and dominated by noise near it.

    Returns
    -------
    mx, my : ndarray (H, W)
        In [-1, 1] wherever both corrected images are >= 0; 0 at masked pixels.
    mask : ndarray of bool (H, W)
        True where either sum is below ``min_sum`` or not finite.

    Examples
    --------
    >>> import numpy as np
    >>> corrected = {"right": np.array([[1.2]]), "left": np.array([[0.8]]),
    ...              "back": np.array([[1.0]]), "front": np.array([[1.0]])}
    >>> mx, my, mask = normalised_differences(corrected)
    >>> round(float(mx[0, 0]), 4), round(float(my[0, 0]), 4), bool(mask[0, 0])
    (0.2, 0.0, False)
    """
    c = check_images(corrected, "corrected images")
    d_x = c["right"] - c["left"]
    d_y = c["back"] - c["front"]
    s_x = c["right"] + c["left"]
    s_y = c["back"] + c["front"]
    ok = np.isfinite(d_x) & np.isfinite(d_y) & np.isfinite(s_x) & np.isfinite(s_y)
    ok &= (s_x >= min_sum) & (s_y >= min_sum)
    mx = np.zeros(s_x.shape)
    my = np.zeros(s_x.shape)
    np.divide(d_x, s_x, out=mx, where=ok)
    np.divide(d_y, s_y, out=my, where=ok)
    return mx, my, ~ok


# American spelling alias (scikit-image style is British/American mixed; offer both).
normalized_differences = normalised_differences
