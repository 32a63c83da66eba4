"""Surface gradient from four detector images (Eqs. 15, 24-26) and the masks of untrusted pixels.

Sign convention (Eq. 16): n_S = [n_Sx, n_Sy, 1] = [-dZ/dx, -dZ/dy, 1]. A surface rising towards +x
(dZ/dx > 0) tilts its normal towards -x, away from the right detector: R drops, M_x < 0.

Eq. 26, n_Sx = M_x d_h / (d_w + x M_x + y M_y) and n_Sy = M_y d_h / (d_w + x M_x + y M_y), is
*exact* for the simplified point-detector model with Lambert's cosine law (Eqs. 17-24) — in
particular for a vertical beam, for which the paper derives it. (With a Lambert law the
beam-dependent factor eta(theta)/eta_C is common to the four detectors of a pixel and cancels, so
a tilted beam keeps it exact too.) With the full g_BSE of Eq. 13 the specular lobe makes the
intensity non-linear in n_S and Eq. 26 is an approximation; the tests measure how far.

Mask semantic everywhere: ``mask`` True (1) = *untrusted* pixel; its gradient values are 0.
``reasons`` is a bit field (:data:`MASK_BITS`) telling why.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from ..constants import DETECTOR_NAMES
from .layout import check_detector_geometry, detector_vectors, masking_condition, pixel_coordinates
from .stsa import MIN_FLAT_FRACTION, MIN_SUM, check_images, normalised_differences, stsa_correct, sum_images

#: Why a pixel is untrusted (bits of ``GradientResult.reasons``).
MASK_BITS = {
    "invalid_input": 1,      # an object/flat pixel is NaN/Inf or the flat is ~0 (STSA impossible)
    "detector_dark": 2,      # a corrected image <= min_corrected: that detector is (nearly) masked
    "sum_small": 4,          # R^C + L^C or B^C + F^C below min_sum (Eq. 15 undefined)
    "denominator_small": 8,  # d_w + x M_x + y M_y <= min_denominator * d_w (Eq. 26 blows up)
    "geometric": 16,         # recovered n_S . d <= margin for some detector (Sec. 4.3 masking)
    "model_residual": 32,    # model method: the 1st-event model cannot explain the four values
    "not_solved": 64,        # model method: no finite, bounded solution (singular or > 80 deg)
}

#: A corrected image below this (flat plate: 1) means no direct electrons reach that detector.
MIN_CORRECTED = 0.02
#: Eq. 26's denominator must exceed this fraction of d_w. In the Lambert model it equals
#: d_h d_w / (d_h - n_Sx x - n_Sy y) > 0, so small or negative values only come from masked or
#: inconsistent data.
MIN_DENOMINATOR = 0.05


def eq26_denominator(mx, my, x, y, d_w):
    """The denominator of Eq. 26, d_w + x M_x + y M_y (mm).

    Parameters
    ----------
    mx, my : ndarray (H, W)
        Normalised differences (Eq. 15, dimensionless).
    x, y : ndarray (H, W)
        Pixel positions in mm (:func:`pixel_coordinates`).
    d_w : float
        Detector distance from the z-axis (mm).

    Returns
    -------
    ndarray (H, W)
        d_w + x M_x + y M_y in mm.

    Examples
    --------
    >>> float(eq26_denominator(0.1, 0.2, 10.0, -5.0, 127.0))
    127.0
    """
    return d_w + np.asarray(x) * mx + np.asarray(y) * my


def gradient_from_differences(mx, my, field_mm, d_h, d_w, *, min_denominator: float = MIN_DENOMINATOR):
    """Surface gradient by Eq. 26 from the normalised difference images M_x, M_y.

    -dZ/dx = n_Sx = M_x d_h / (d_w + x M_x + y M_y),   -dZ/dy = n_Sy = M_y d_h / (d_w + x M_x + y M_y)

    Parameters
    ----------
    mx, my : ndarray (H, W)
        Normalised difference images (Eq. 15), package orientation.
    field_mm : float or (float, float)
        Scan field in mm; pixel positions (x, y) come from :func:`~.geometry.pixel_coordinates`.
    d_h, d_w : float
        Detector height and distance from the z-axis (mm, Eq. 17).
    min_denominator : float
        Pixels whose denominator is <= ``min_denominator * d_w`` (or not finite) are masked.

    Returns
    -------
    dzdx, dzdy : ndarray (H, W)
        dZ/dx and dZ/dy (dimensionless, mm/mm); 0 at masked pixels.
    mask : ndarray of bool (H, W)
        True = untrusted.

    Examples
    --------
    >>> import numpy as np
    >>> mx = np.full((2, 2), -0.0467)          # Eq. 24 of dZ/dx = 0.1 at the field centre (d_w/d_h = 0.467)
    >>> dzdx, dzdy, mask = gradient_from_differences(mx, np.zeros((2, 2)), 0.01, 272.0, 127.0)
    >>> round(float(dzdx.mean()), 3), float(np.abs(dzdy).max()), bool(mask.any())
    (0.1, 0.0, False)
    """
    d_h, d_w = check_detector_geometry(d_h, d_w)
    mx = np.asarray(mx, dtype=float)
    my = np.asarray(my, dtype=float)
    x, y = pixel_coordinates(mx.shape, field_mm)
    den = eq26_denominator(mx, my, x, y, d_w)
    ok = np.isfinite(den) & np.isfinite(mx) & np.isfinite(my) & (den > min_denominator * d_w)
    dzdx = np.zeros(mx.shape)
    dzdy = np.zeros(mx.shape)
    # n_S = -grad Z (Eq. 16): the minus sign turns Eq. 26's normal components into the gradient.
    np.divide(-mx * d_h, den, out=dzdx, where=ok)
    np.divide(-my * d_h, den, out=dzdy, where=ok)
    return dzdx, dzdy, ~ok


def raw_gradient(mx, my, d_h=None, d_w=None):
    """The "M as gradient" estimate of earlier work, for comparison with Eq. 26.

    Without ``d_h``, ``d_w``: dZ/dx ~ -M_x, dZ/dy ~ -M_y, which by Eq. 24 underestimates the slope
    by about d_w/d_h and depends on the position (x, y). With both: the first-order rescaling
    -M d_h/d_w, exact only at x = y = 0. Non-finite M gives 0.

    Parameters
    ----------
    mx, my : ndarray (H, W)
        Normalised differences (Eq. 15, dimensionless).
    d_h, d_w : float, optional
        Detector height and distance from the z-axis (mm), both or neither.

    Returns
    -------
    dzdx, dzdy : ndarray (H, W)
        Estimated gradient (mm/mm).

    Examples
    --------
    >>> import numpy as np
    >>> mx = np.array([[-0.0467]])
    >>> [round(float(g[0, 0]), 4) + 0.0 for g in raw_gradient(mx, np.zeros((1, 1)))]
    [0.0467, 0.0]
    >>> round(float(raw_gradient(mx, np.zeros((1, 1)), 272.0, 127.0)[0][0, 0]), 3)
    0.1
    """
    scale = 1.0
    if d_h is not None or d_w is not None:
        d_h, d_w = check_detector_geometry(d_h, d_w)
        scale = d_h / d_w
    gx = np.nan_to_num(-scale * np.asarray(mx, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)
    gy = np.nan_to_num(-scale * np.asarray(my, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)
    return gx, gy


def detector_masking(dzdx, dzdy, field_mm, d_h, d_w, *, margin: float = 0.0,
                     detectors=DETECTOR_NAMES) -> dict[str, np.ndarray]:
    """Geometric masking of each detector for a gradient field (Sec. 4.3 with Eq. 17).

    A pixel is masked for detector k when n_S . d_k <= margin, i.e.
    n_Sx d_x + n_Sy d_y + 1 <= margin with n_S = [-dZ/dx, -dZ/dy, 1] and d_k the p,q-form detector
    vector *at that pixel's position* (Eq. 17).

    Returns
    -------
    dict of str to ndarray of bool (H, W)
        True where the detector sees the surface element at or behind its tangent plane.

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Surface gradient (mm/mm), package orientation.
    field_mm : float or (float, float)
        Scan field in mm.
    d_h, d_w : float
        Detector height and distance from the z-axis (mm).
    margin : float
        0: masked at and behind the tangent plane; > 0 also flags grazing directions.
    detectors : iterable of str

    Examples
    --------
    >>> import numpy as np
    >>> dzdx = np.array([[0.0, 3.0]])       # flat, and steep rising towards +x (faces away from right)
    >>> masks = detector_masking(dzdx, np.zeros_like(dzdx), (20.0, 10.0), 272.0, 127.0)
    >>> masks["right"].tolist(), masks["left"].tolist()
    ([[False, True]], [[False, False]])
    """
    dzdx = np.asarray(dzdx, dtype=float)
    x, y = pixel_coordinates(dzdx.shape, field_mm)
    dvec = detector_vectors(x, y, d_h, d_w, detectors)
    return {n: masking_condition(-dzdx, -np.asarray(dzdy, dtype=float), d[..., 0], d[..., 1], margin)
            for n, d in dvec.items()}


@dataclass
class GradientResult:
    """Everything :func:`surface_gradient` computes; arrays of shape (H, W), package orientation.

    Attributes
    ----------
    dzdx, dzdy : ndarray
        Surface gradient by Eq. 26 (mm/mm); 0 where ``mask``.
    mx, my : ndarray
        Normalised differences of Eq. 15 (dimensionless); 0 where they are undefined.
    sum_x, sum_y : ndarray
        Sum images R^C + L^C and B^C + F^C (Eq. 23, material contrast).
    mask : ndarray of bool
        True (1) = untrusted pixel.
    reasons : ndarray of uint8
        OR of :data:`MASK_BITS`.
    corrected : dict
        STSA-corrected images R^C, L^C, B^C, F^C.

    Examples
    --------
    >>> import numpy as np
    >>> from elo_mitsuba.analysis import flat_plate_images, point_detector_images
    >>> flats = flat_plate_images((4, 4), 20.0, 272.0, 127.0)
    >>> images = point_detector_images(np.full((4, 4), 0.1), np.zeros((4, 4)), 20.0, 272.0, 127.0)
    >>> result = surface_gradient(images, flats, 20.0, 272.0, 127.0)
    >>> type(result).__name__, result.dzdx.shape, sorted(result.corrected)
    ('GradientResult', (4, 4), ['back', 'front', 'left', 'right'])
    """

    dzdx: np.ndarray
    dzdy: np.ndarray
    mx: np.ndarray
    my: np.ndarray
    sum_x: np.ndarray
    sum_y: np.ndarray
    mask: np.ndarray
    reasons: np.ndarray
    corrected: dict = field(default_factory=dict)

    def reason_fraction(self) -> dict[str, float]:
        """Fraction of pixels flagged by each reason (a pixel can have several)."""
        return {k: float(np.mean((self.reasons & b) != 0)) for k, b in MASK_BITS.items()}


def surface_gradient(images: Mapping, flats: Mapping | None, field_mm, d_h, d_w, *,
                     min_flat_fraction: float = MIN_FLAT_FRACTION,
                     min_corrected: float = MIN_CORRECTED,
                     min_sum: float = MIN_SUM,
                     min_denominator: float = MIN_DENOMINATOR,
                     geometric_margin: float = 0.0) -> GradientResult:
    """Four detector images -> STSA correction -> M_x, M_y -> gradient (Eqs. 15, 26) + mask.

    Parameters
    ----------
    images : mapping of str to ndarray (H, W)
        R, L, B, F of the object (keys ``right``, ``left``, ``back``, ``front``).
    flats : mapping or None
        Flat-plate images for the STSA correction; None if ``images`` are already corrected.
    field_mm, d_h, d_w :
        Scan field and detector geometry in mm.
    min_flat_fraction, min_corrected, min_sum, min_denominator : float
        Thresholds of the mask (see :data:`MASK_BITS` and the module constants).
    geometric_margin : float
        A pixel whose *recovered* normal has n_S . d_k <= margin for some detector is flagged
        ``geometric``: Eq. 26 assumed all four detectors see it.

    Returns
    -------
    GradientResult

    Examples
    --------
    A tilted plane dZ/dx = 0.1 seen by point detectors (Lambert model, for which Eq. 26 is exact):

    >>> import numpy as np
    >>> from elo_mitsuba.analysis import flat_plate_images, point_detector_images
    >>> shape, field, d_h, d_w = (4, 4), 20.0, 272.0, 127.0
    >>> flats = flat_plate_images(shape, field, d_h, d_w, model="lambert")
    >>> images = point_detector_images(np.full(shape, 0.1), np.zeros(shape), field, d_h, d_w, model="lambert")
    >>> result = surface_gradient(images, flats, field, d_h, d_w)
    >>> round(float(result.dzdx.mean()), 4), round(float(np.abs(result.dzdy).max()), 4), bool(result.mask.any())
    (0.1, 0.0, False)
    """
    from ..arguments import fraction

    for name, value in (("min_flat_fraction", min_flat_fraction), ("min_corrected", min_corrected),
                        ("min_denominator", min_denominator)):
        fraction(name, value)
    fraction("min_sum", min_sum, 0.0, 2.0)  # R^C + L^C is 2 on a flat plate
    fraction("geometric_margin", geometric_margin)  # a cosine: 0 flags normals that face a detector edge-on
    if flats is None:
        corrected = check_images(images, "corrected images")
        bad_in = np.zeros(next(iter(corrected.values())).shape, dtype=bool)
        for n in DETECTOR_NAMES:
            bad_in |= ~np.isfinite(corrected[n])
            corrected[n] = np.where(np.isfinite(corrected[n]), corrected[n], 0.0)
    else:
        corrected, bad_in = stsa_correct(images, flats, min_flat_fraction=min_flat_fraction)
    shape = bad_in.shape
    dark = np.zeros(shape, dtype=bool)
    for n in DETECTOR_NAMES:
        dark |= corrected[n] <= min_corrected
    mx, my, bad_sum = normalised_differences(corrected, min_sum=min_sum)
    sum_x, sum_y = sum_images(corrected)
    dzdx, dzdy, bad_den = gradient_from_differences(mx, my, field_mm, d_h, d_w, min_denominator=min_denominator)
    geo = np.zeros(shape, dtype=bool)
    for m in detector_masking(dzdx, dzdy, field_mm, d_h, d_w, margin=geometric_margin).values():
        geo |= m
    reasons = (MASK_BITS["invalid_input"] * bad_in + MASK_BITS["detector_dark"] * dark
               + MASK_BITS["sum_small"] * bad_sum + MASK_BITS["denominator_small"] * bad_den
               + MASK_BITS["geometric"] * geo).astype(np.uint8)
    mask = reasons != 0
    dzdx = np.where(mask, 0.0, dzdx)
    dzdy = np.where(mask, 0.0, dzdy)
    return GradientResult(dzdx, dzdy, mx, my, sum_x, sum_y, mask, reasons, corrected)
