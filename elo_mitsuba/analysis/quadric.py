"""The best-fitting quadric of a height map: a field-wide bowl, and the relief about it.

A bias of the slopes integrates to a quadric over the field (a constant slope error to a tilt, a
slope error growing across the field to a bowl), and so does a plate that is really warped; the
relief about the quadric is what neither leaves. ``reconstruct`` warns where the bowl exceeds that
relief (:func:`.integrate.reconstruction_quality`), ``invert`` too (:func:`.inversion.bowl_check`),
and the resolution test compares its half-sampling figure with the relief's RMS
(:func:`.sampling_check.resolution`).
"""

from __future__ import annotations

import numpy as np


def fit_quadric(height, where) -> tuple[np.ndarray | None, float, float, float]:
    """The best-fitting quadric of ``height`` over the pixels ``where`` (least squares in the
    pixel coordinates): its values on the whole map (None for fewer than 6 pixels), its range (the
    bowl, mm), and the range and RMS of the heights about it there (the relief).

    Examples
    --------
    >>> r, c = np.indices((20, 30)).astype(float)
    >>> bowl = 1e-3 * ((r - 9.5) ** 2 + (c - 14.5) ** 2)              # 0.3 mm deep
    >>> ripple = 0.01 * np.where((r + c) % 2, 1.0, -1.0)               # +-10 um, finer than a quadric
    >>> quad, depth, relief, rms = fit_quadric(bowl + ripple, np.ones(bowl.shape, bool))
    >>> round(depth, 3), round(relief, 3), round(rms, 3)
    (0.3, 0.02, 0.01)
    >>> fit_quadric(bowl, np.eye(20, 30, dtype=bool) & (r < 5))[0] is None   # five pixels
    True
    """
    z = np.asarray(height, dtype=float)
    rows, cols = np.nonzero(where)
    if rows.size < 6:
        return None, 0.0, 0.0, 0.0

    def basis(r, c):
        x = c / max(z.shape[1] - 1, 1) - 0.5
        y = r / max(z.shape[0] - 1, 1) - 0.5
        return np.stack([np.ones_like(x), x, y, x * x, y * y, x * y], axis=-1)

    step = max(1, rows.size // 250_000)  # a quadric needs few points; keep it fast
    coef, *_ = np.linalg.lstsq(basis(rows, cols)[::step], z[rows, cols][::step], rcond=None)
    quad = basis(*np.indices(z.shape).astype(float)) @ coef
    about = z[rows, cols] - quad[rows, cols]
    return quad, float(np.ptp(quad[rows, cols])), float(np.ptp(about)), float(np.std(about))


def bowl_exceeds(bowl_mm: float, relief_mm: float, pixel_mm: float) -> bool:
    """The rule of ``reconstruct`` and ``invert``: a quadric (``bowl_mm``, its range) larger than
    the relief about it (``relief_mm``, its range) and than a hundredth of a pixel, below which
    a flat map's rounding makes one.

    Examples
    --------
    >>> bowl_exceeds(0.3, 0.02, 0.2), bowl_exceeds(0.01, 0.02, 0.2), bowl_exceeds(1e-4, 0.0, 0.2)
    (True, False, False)
    """
    return bowl_mm > relief_mm and bowl_mm > 0.01 * pixel_mm
