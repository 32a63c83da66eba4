"""Design tools for detector layouts: reflectance maps, normal histograms, image statistics.

* :func:`reflectance_map` — g_BSE (Eq. 13) over the (p, q) plane of surface normals
  n_S = [p, q, 1] = [n_Sx, n_Sy, 1] for one detector vector d = [d_x, d_y, 1] and beam direction,
  with the masked region p d_x + q d_y + 1 <= 0 (Sec. 4.3, Figs. 12-13).
* :func:`normal_histogram` — 2-D histogram of the normals of a height map in p,q-form (Fig. 14a);
  :func:`masking_lines` gives the lines p d_x + q d_y + 1 = 0 of detector layouts (Table 1).
* :func:`image_statistics` — masked-pixel fraction, mean and spread of a rendered image
  (Fig. 14b, Fig. 15).

Maps over the (p, q) plane follow the image convention of the package: row 0 holds the largest q,
columns run towards larger p (so p plays x and q plays y).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..constants import DETECTOR_NAMES, LOBE_WIDTH_DEG, TABLE1_LAYOUTS
from ..errors import EloInputError
from ..physics import g_bse, get_material
from .layout import check_detector_geometry, detector_vectors, masking_condition
from .gradient import detector_masking
from .integrate import height_gradient


def detector_pq(d_h, d_w, detector="right", x=0.0, y=0.0) -> tuple[float, float]:
    """p,q-form (d_x, d_y) of a detector vector seen from (x, y, 0) (Eq. 17); mm in, unitless out.

    Parameters
    ----------
    d_h, d_w : float
        Detector height and distance from the z-axis (mm).
    detector : {"right", "left", "back", "front"}
    x, y : float
        Surface position in mm.

    Returns
    -------
    (float, float)
        ``(d_x, d_y)``, unitless.

    Examples
    --------
    >>> [round(v, 4) for v in detector_pq(272, 127)]
    [0.4669, 0.0]
    >>> [round(v, 4) for v in detector_pq(272, 127, "front", x=10.0)]
    [-0.0368, -0.4669]
    """
    d = detector_vectors(np.asarray(x, float), np.asarray(y, float), d_h, d_w, (detector,))[detector]
    return float(d[..., 0]), float(d[..., 1])


#: The largest |p| or |q| a map samples: a facet 89.94 degrees from level. Beyond it a map shows
#: nothing new, and 1e300 overflowed the normals' squared length.
MAX_PQ = 1e3


def pq_grid(p_range=(-3.0, 3.0), q_range=(-3.0, 3.0), n=301):
    """Sample the (p, q) plane: returns ``(P, Q)`` of shape (n_q, n_p), row 0 = largest q.

    Parameters
    ----------
    p_range, q_range : (float, float)
        Sampled window of p = n_Sx and q = n_Sy (unitless).
    n : int or (int, int)
        Number of samples (n_p, n_q).

    Returns
    -------
    P, Q : ndarray (n_q, n_p)

    Examples
    --------
    >>> P, Q = pq_grid((-1.0, 1.0), (-1.0, 1.0), n=3)
    >>> P[0].tolist(), Q[:, 0].tolist()
    ([-1.0, 0.0, 1.0], [1.0, 0.0, -1.0])
    """
    for name, (lo, hi) in (("p_range", p_range), ("q_range", q_range)):
        if not all(np.isfinite([lo, hi])) or max(abs(float(lo)), abs(float(hi))) > MAX_PQ or not lo < hi:
            raise EloInputError(f"{name}=({lo!r}, {hi!r}): must be lo < hi within +-{MAX_PQ:g} "
                                "(a gradient component; e.g. --range 3)")
    n_p, n_q = (n, n) if np.isscalar(n) else n
    if int(n_p) < 2 or int(n_q) < 2:
        raise EloInputError(f"n={n!r}: need at least 2 samples along p and q")
    p = np.linspace(float(p_range[0]), float(p_range[1]), int(n_p))
    q = np.linspace(float(q_range[1]), float(q_range[0]), int(n_q))
    return np.meshgrid(p, q)


def reflectance_map(d_pq, *, beam_dir=(0.0, 0.0, -1.0), material=None, lobe=True,
                    lobe_width_deg=LOBE_WIDTH_DEG, p_range=(-3.0, 3.0), q_range=(-3.0, 3.0), n=301):
    """Reflectance map: g_BSE (Eq. 13, 1/sr) as a function of the surface normal in p,q-form.

    Every normal is placed at the origin and seen by a point detector in the direction
    d = [d_x, d_y, 1] (Sec. 4.3).

    Parameters
    ----------
    d_pq : (float, float)
        Detector vector (d_x, d_y) in p,q-form, e.g. ``detector_pq(272, 127)`` = (127/272, 0).
    beam_dir : (float, float, float)
        Beam direction of travel p_E (vertical [0, 0, -1] in the paper).
    material : str, mapping or Material, optional
        Default Ti-6Al-4V.
    lobe : bool
        True: full g_BSE (left halves of Figs. 12-13); False: the diffuse part only (right halves).
    p_range, q_range, n :
        Sampled (p, q) window and number of samples (scalar or (n_p, n_q)).

    Returns
    -------
    p, q : ndarray (n_q, n_p)
        n_Sx and n_Sy of every sample (row 0 = largest q).
    g : ndarray (n_q, n_p)
        g_BSE per steradian; 0 in the masked region.
    masked : ndarray of bool (n_q, n_p)
        p d_x + q d_y + 1 <= 0: the detector is behind the tangent plane (geometric masking).

    Examples
    --------
    >>> p, q, g, masked = reflectance_map(detector_pq(272, 127), n=5)
    >>> g.shape, bool(masked[2, 0]), bool(masked[2, 2])    # p = -3: masked; the flat normal: not
    ((5, 5), True, False)
    >>> round(float(g[2, 2]), 4)                            # g_BSE of a flat plate (1/sr)
    0.0693
    """
    d_x, d_y = (float(v) for v in d_pq)
    p, q = pq_grid(p_range, q_range, n)
    normal = np.stack([p, q, np.ones_like(p)], axis=-1)
    d = np.array([d_x, d_y, 1.0])
    g = g_bse(normal, np.asarray(beam_dir, dtype=float), d, get_material(material), lobe=lobe,
              lobe_width_deg=lobe_width_deg)
    return p, q, g, masking_condition(p, q, d_x, d_y)


def masking_lines(layouts: Mapping | None = None, detectors=DETECTOR_NAMES) -> dict:
    """Detector vectors (at the field centre) whose masking lines p d_x + q d_y + 1 = 0 bound the
    masked normals, for each layout.

    Parameters
    ----------
    layouts : mapping, optional
        ``{label: (d_h, d_w)}`` in mm; default Table 1 keyed by zeta in degrees.

    Returns
    -------
    dict
        ``{label: {detector: (d_x, d_y)}}``. For the right detector the line is p = -d_h/d_w.

    Examples
    --------
    >>> lines = masking_lines({"zeta25": (272.0, 127.0)}, detectors=("right",))
    >>> [round(v, 4) for v in lines["zeta25"]["right"]]
    [0.4669, 0.0]
    """
    layouts = TABLE1_LAYOUTS if layouts is None else layouts
    return {label: {det: detector_pq(dh, dw, det) for det in detectors} for label, (dh, dw) in layouts.items()}


def normal_histogram(height, field_mm, *, bins=201, p_range=(-2.0, 2.0), q_range=(-2.0, 2.0),
                     mask=None, density=False):
    """2-D histogram of the surface normals n_S = [p, q, 1] of a height map (Fig. 14a).

    Slopes by central differences (:func:`~.integrate.height_gradient`), p = -dZ/dx, q = -dZ/dy.

    Parameters
    ----------
    height : ndarray (H, W)
        Height map in mm, package orientation.
    field_mm : float or (float, float)
        Scan field in mm.
    bins : int or (int, int)
        Number of bins along p and q.
    mask : ndarray of bool, optional
        True = leave the pixel out.
    density : bool
        Normalise to a probability density over (p, q).

    Returns
    -------
    hist : ndarray (n_q, n_p)
        Counts, row 0 = largest q (image convention: show with ``origin="upper"`` and
        ``extent=(p0, p1, q0, q1)``).
    p_edges, q_edges : ndarray
        Bin edges (ascending).

    Examples
    --------
    >>> import numpy as np
    >>> height = np.tile(np.arange(4.0), (3, 1))      # a ramp, dZ/dx = 1 mm/mm (1 mm pixels)
    >>> hist, p_edges, q_edges = normal_histogram(height, (4.0, 3.0), bins=4)
    >>> hist.shape, int(hist.sum()), int(hist[:, 1].sum())    # every normal at p = -1
    ((4, 4), 12, 12)
    """
    dzdx, dzdy = height_gradient(height, field_mm)
    p, q = -dzdx, -dzdy
    keep = np.isfinite(p) & np.isfinite(q)
    if mask is not None:
        keep &= ~np.asarray(mask, dtype=bool)
    nb = (bins, bins) if np.isscalar(bins) else tuple(bins)
    hist, p_edges, q_edges = np.histogram2d(p[keep], q[keep], bins=nb, range=(p_range, q_range), density=density)
    return hist.T[::-1], p_edges, q_edges


def masked_normal_fraction(dzdx, dzdy, field_mm, d_h, d_w, *, detectors=DETECTOR_NAMES,
                           mask=None) -> dict[str, float]:
    """Fraction of pixels geometrically masked for each detector and for any of them (Sec. 4.4).

    Uses the detector vector at each pixel's position (Eq. 17), so it is the position-exact
    version of counting the normals of :func:`normal_histogram` beyond a masking line.

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Surface gradient (mm/mm), package orientation.
    field_mm : float or (float, float)
        Scan field in mm.
    d_h, d_w : float
        Detector height and distance from the z-axis (mm).
    detectors : iterable of str
    mask : ndarray of bool, optional
        True = leave the pixel out.

    Returns
    -------
    dict of str to float
        ``{detector: fraction, ..., "any": fraction}`` (0..1) of the pixels counted.

    Examples
    --------
    >>> import numpy as np
    >>> dzdx = np.array([[0.0, 3.0]])           # a flat pixel and a steep one facing -x
    >>> fractions = masked_normal_fraction(dzdx, np.zeros_like(dzdx), (20.0, 10.0), 272, 127)
    >>> {k: round(v, 4) for k, v in fractions.items()}
    {'right': 0.5, 'left': 0.0, 'back': 0.0, 'front': 0.0, 'any': 0.5}
    """
    masks = detector_masking(dzdx, dzdy, field_mm, d_h, d_w, detectors=detectors)
    keep = np.ones(np.shape(dzdx), dtype=bool) if mask is None else ~np.asarray(mask, dtype=bool)
    n = max(int(keep.sum()), 1)
    out = {k: float((m & keep).sum() / n) for k, m in masks.items()}
    any_m = np.zeros(np.shape(dzdx), dtype=bool)
    for m in masks.values():
        any_m |= m
    out["any"] = float((any_m & keep).sum() / n)
    return out


def image_statistics(image, *, mask=None, zero_threshold=0.0, bins=100, value_range=None) -> dict:
    """Statistics of a rendered detector image for layout comparisons (Fig. 14b, Fig. 15).

    Parameters
    ----------
    image : ndarray (H, W)
        Intensities >= 0 (N_d/N_0; for machine voltages pass the magnitude). Use the 1st-event
        channel (e.g. ``right.e1``) to see geometric masking alone.
    mask : ndarray of bool, optional
        True = leave the pixel out of every statistic.
    zero_threshold : float
        Pixels at or below it count as masked (no electrons reach the detector: green in Fig. 14b).
    bins, value_range :
        Histogram of the unmasked-by-``mask`` pixels (Fig. 15).

    Returns
    -------
    dict
        ``masked_fraction``, ``masked`` (bool image), ``mean``, ``std``, ``cv`` (std/mean),
        ``min``, ``max``, ``p05``, ``p50``, ``p95``, ``hist``, ``bin_edges``. Statistics use all
        finite pixels not excluded by ``mask`` (masked pixels included, as in Fig. 15).

    Examples
    --------
    >>> import numpy as np
    >>> image = np.array([[0.0, 0.1], [0.2, 0.3]])
    >>> s = image_statistics(image, bins=3)
    >>> s["masked_fraction"], round(s["mean"], 4), round(s["max"], 4), s["hist"].tolist()
    (0.25, 0.15, 0.3, [1, 1, 2])
    """
    img = np.asarray(image, dtype=float)
    if img.ndim != 2:
        raise EloInputError(f"image of shape {img.shape}: expected a 2-D image")
    keep = np.isfinite(img)
    if mask is not None:
        keep &= ~np.asarray(mask, dtype=bool)
    vals = img[keep]
    if vals.size == 0:
        raise EloInputError("image_statistics: no finite pixel left to measure")
    masked = keep & (np.where(keep, img, np.inf) <= zero_threshold)
    mean = float(vals.mean())
    std = float(vals.std())
    hist, edges = np.histogram(vals, bins=bins, range=value_range)
    p05, p50, p95 = np.percentile(vals, [5, 50, 95])
    return {
        "masked_fraction": float(masked.sum() / vals.size), "masked": masked,
        "mean": mean, "std": std, "cv": std / mean if mean != 0 else float("inf"),
        "min": float(vals.min()), "max": float(vals.max()),
        "p05": float(p05), "p50": float(p50), "p95": float(p95),
        "hist": hist, "bin_edges": edges,
    }


def layout_geometry(zeta=None, d_h=None, d_w=None) -> tuple[float, float]:
    """(d_h, d_w) in mm from a Table 1 inclination ``zeta`` (deg) or explicit lengths.

    Parameters
    ----------
    zeta : float, optional
        Table 1 inclination in degrees (25, 50 or 75 ...).
    d_h, d_w : float, optional
        Detector height and distance from the z-axis (mm), instead of ``zeta``.

    Returns
    -------
    (float, float)
        ``(d_h, d_w)`` in mm.

    Examples
    --------
    >>> layout_geometry(zeta=50)
    (192.7, 229.6)
    >>> layout_geometry(d_h=272, d_w=127)
    (272.0, 127.0)
    """
    if zeta is not None:
        key = int(round(float(zeta)))
        if key not in TABLE1_LAYOUTS or abs(float(zeta) - key) > 1e-9:
            raise EloInputError(f"zeta={zeta!r}: Table 1 has {', '.join(map(str, TABLE1_LAYOUTS))} deg")
        return TABLE1_LAYOUTS[key]
    if d_h is None or d_w is None:
        raise EloInputError("give the detector layout as zeta (Table 1) or both d_h and d_w (mm)")
    return check_detector_geometry(d_h, d_w)
