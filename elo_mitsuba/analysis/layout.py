"""The detector layout of Eq. 17 and the scan-field geometry shared by every analysis function.

Pixel positions follow the package's one image orientation, defined in :mod:`elo_mitsuba.grid`
(:func:`pixel_axes`, :func:`pixel_coordinates`, re-exported here).

Detectors (Eq. 17): right (+x), left (-x), back (+y), front (-y), each at height ``d_h`` above the
build plane and at distance ``d_w`` from the z-axis. Vectors are in p,q-form (scaled to z = 1,
Fig. 8b): the normal of Eq. 16 is n_S = [-dZ/dx, -dZ/dy, 1], the detector vector seen from the
surface point (x, y, 0) is d = [(d_w e_x - x)/d_h, (d_w e_y - y)/d_h, 1] with (e_x, e_y) the unit
direction of the detector (``constants.DETECTOR_DIRECTIONS``).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..constants import DETECTOR_DIRECTIONS, DETECTOR_NAMES
from ..errors import EloInputError
from ..grid import field_xy, pixel_axes, pixel_coordinates, pixel_size  # noqa: F401  (re-exported)

#: Relative tolerance on the agreement of the four detectors' d_h and d_w read from a header, and
#: on their lying along +x, -x, +y, -y (Eq. 17 assumes this symmetric layout).
GEOMETRY_RTOL = 1e-3


def check_detector_geometry(d_h, d_w) -> tuple[float, float]:
    """Validate the detector height ``d_h`` and distance ``d_w`` (mm, finite, > 0).

    Parameters
    ----------
    d_h, d_w : float
        Detector height above the build plane and distance from the z-axis (mm).

    Returns
    -------
    (float, float)
        ``(d_h, d_w)`` as floats.

    Raises
    ------
    EloInputError
        A value that is not finite and > 0.

    Examples
    --------
    >>> check_detector_geometry(272, 127)
    (272.0, 127.0)
    """
    out = []
    for name, val in (("d_h", d_h), ("d_w", d_w)):
        try:  # text and bools are not lengths, though float() would take them
            if isinstance(val, (str, bytes, bool, np.bool_)):
                raise TypeError
            v = float(val)
        except (TypeError, ValueError, OverflowError):
            raise EloInputError(f"{name}={val!r}: expected a length in mm") from None
        if not (np.isfinite(v) and v > 0):
            raise EloInputError(f"{name}={val!r} mm: must be finite and > 0")
        out.append(v)
    return out[0], out[1]


def detector_vectors(x, y, d_h, d_w, detectors=DETECTOR_NAMES) -> dict[str, np.ndarray]:
    """Detector vectors of Eq. 17 in p,q-form at the surface points (x, y, 0).

    Parameters
    ----------
    x, y : array_like
        Surface positions in mm (broadcast together), e.g. from :func:`pixel_coordinates`.
    d_h, d_w : float
        Detector height above the build plane and distance from the z-axis (mm).
    detectors : iterable of str
        Subset of ``right``, ``left``, ``back``, ``front``.

    Returns
    -------
    dict
        ``{name: d}`` with ``d`` of shape (..., 3): [(d_w e_x - x)/d_h, (d_w e_y - y)/d_h, 1].

    Examples
    --------
    >>> d = detector_vectors(0.0, 0.0, 272.0, 127.0, detectors=("right", "back"))
    >>> d["right"].round(4).tolist(), d["back"].round(4).tolist()
    ([0.4669, 0.0, 1.0], [0.0, 0.4669, 1.0])
    """
    d_h, d_w = check_detector_geometry(d_h, d_w)
    x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
    out = {}
    for name in detectors:
        if name not in DETECTOR_DIRECTIONS:
            raise EloInputError(f"detector {name!r}: choose from {', '.join(DETECTOR_NAMES)}")
        ex, ey = DETECTOR_DIRECTIONS[name]
        out[name] = np.stack([(d_w * ex - x) / d_h, (d_w * ey - y) / d_h, np.ones_like(x)], axis=-1)
    return out


def disc_nodes(centre, normal, radius, n_r=32, n_phi=96) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature nodes and area weights on a disc detector, for integrals such as Eq. 5 written
    over the detector area (int f dA = sum f(q) w): Gauss-Legendre in the radius, midpoint
    (spectrally accurate for periodic integrands) in the azimuth.

    Parameters
    ----------
    centre, normal : array_like (3,)
        Disc centre (mm) and normal (any length).
    radius : float
        Disc radius (mm).
    n_r, n_phi : int
        Nodes in the radius and the azimuth.

    Returns
    -------
    points : ndarray (n_r, n_phi, 3)
        Node positions (mm).
    weights : ndarray (n_r, n_phi)
        Area weights (mm^2), summing to pi radius^2.
    """
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.99 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    x, w = np.polynomial.legendre.leggauss(n_r)
    r = 0.5 * (x + 1.0) * radius
    wr = 0.5 * w * radius
    phi = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    rr, pp = np.meshgrid(r, phi, indexing="ij")
    weights = (wr[:, None] * rr) * (2.0 * np.pi / n_phi)
    points = (np.asarray(centre, float) + rr[..., None] * np.cos(pp)[..., None] * a
              + rr[..., None] * np.sin(pp)[..., None] * b)
    return points, weights


def masking_condition(p, q, d_x, d_y, margin=0.0):
    """Geometric masking test of Sec. 4.3: ``p d_x + q d_y + 1 <= margin``.

    ``n_S = [p, q, 1]`` (p = n_Sx = -dZ/dx, q = n_Sy = -dZ/dy) and ``d = [d_x, d_y, 1]`` in
    p,q-form; the condition means n_S . d <= 0, i.e. the detector lies at or below the local
    tangent plane (alpha >= 90 deg) and no electron of the 1st scattering event reaches it.
    A positive ``margin`` also flags grazing directions. Returns a boolean array.

    Parameters
    ----------
    p, q : array_like
        n_Sx = -dZ/dx and n_Sy = -dZ/dy (mm/mm).
    d_x, d_y : array_like
        Detector vector in p,q-form (:func:`detector_vectors`; unitless).
    margin : float
        0: masked exactly at and behind the tangent plane.

    Returns
    -------
    ndarray of bool
        True = masked (the detector does not see the surface element).

    Examples
    --------
    >>> import numpy as np
    >>> masking_condition(np.array([0.0, -2.0, -3.0]), 0.0, 127 / 272, 0.0).tolist()
    [False, False, True]
    """
    return np.asarray(p) * d_x + np.asarray(q) * d_y + 1.0 <= margin


def zeta_deg(d_h, d_w) -> float:
    """Detector inclination zeta = atan(d_w / d_h) in degrees (Table 1).

    Parameters
    ----------
    d_h, d_w : float
        Detector height and distance from the z-axis (mm).

    Returns
    -------
    float
        zeta in degrees.

    Examples
    --------
    >>> round(zeta_deg(272, 127), 2)
    25.03
    """
    d_h, d_w = check_detector_geometry(d_h, d_w)
    return float(np.degrees(np.arctan2(d_w, d_h)))


def symmetric_layout(header, *, d_h=None, d_w=None) -> dict:
    """The Eq. 17 layout a header's detectors form (header read by
    :func:`~elo_mitsuba.schema.read_geometry`).

    ``d_h`` is the z of each detector centre and ``d_w`` the distance of the centre from the
    z-axis. The four detectors must agree (relative tolerance :data:`GEOMETRY_RTOL`) and lie along
    +x, -x, +y, -y, otherwise Eq. 17 (and therefore Eq. 26) does not describe the set-up and an
    :class:`EloInputError` says so. Explicit ``d_h``, ``d_w`` override the header (then the
    detector block may be missing).

    Parameters
    ----------
    header : HeaderGeometry
        The header's geometry.
    d_h, d_w : float, optional
        Detector height and distance from the z-axis (mm) overriding the header's.

    Returns
    -------
    dict
        ``{"field_mm": (fx, fy), "d_h": float, "d_w": float, "resolution": (W, H) or None}``.

    Examples
    --------
    >>> from elo_mitsuba.schema import read_geometry
    >>> header = read_geometry({"field_mm": 80, "resolution": [4, 4]})
    >>> symmetric_layout(header, d_h=272, d_w=127)
    {'field_mm': (80.0, 80.0), 'd_h': 272.0, 'd_w': 127.0, 'resolution': (4, 4)}
    """
    source = header.source
    if d_h is None or d_w is None:
        dets = header.detectors
        if not isinstance(dets, Mapping) or not all(n in dets for n in DETECTOR_NAMES):
            raise EloInputError(
                f"{source}: header lacks detector centres for {', '.join(DETECTOR_NAMES)}; "
                "pass --dh and --dw (mm)"
            )
        hs, ws = {}, {}
        for name in DETECTOR_NAMES:
            try:
                c = np.asarray(dets[name]["center"], dtype=float).reshape(3)
            except (KeyError, TypeError, ValueError):
                raise EloInputError(f"{source}: detector {name!r} has no valid 'center' [x, y, z]") from None
            hs[name] = c[2]
            ws[name] = float(np.hypot(c[0], c[1]))
            ex, ey = DETECTOR_DIRECTIONS[name]
            if np.hypot(c[0] - ws[name] * ex, c[1] - ws[name] * ey) > GEOMETRY_RTOL * max(ws[name], 1.0):
                raise EloInputError(
                    f"{source}: detector {name!r} centre {c.tolist()} does not lie along "
                    f"({ex:+g}, {ey:+g}); Eq. 26 needs right/left/back/front on +x/-x/+y/-y"
                )
        for label, vals, given in (("height d_h (centre z)", hs, d_h), ("distance d_w (from the z-axis)", ws, d_w)):
            if given is not None:
                continue  # overridden: the header's value does not matter
            v = np.array(list(vals.values()))
            if np.ptp(v) > GEOMETRY_RTOL * np.max(np.abs(v)):
                listing = ", ".join(f"{k}={val:.4g}" for k, val in vals.items())
                raise EloInputError(
                    f"{source}: the four detectors differ in {label}: {listing} mm; Eq. 26 needs "
                    "one symmetric layout (pass --dh/--dw to override)"
                )
        d_h = float(np.mean(list(hs.values()))) if d_h is None else d_h
        d_w = float(np.mean(list(ws.values()))) if d_w is None else d_w
    d_h, d_w = check_detector_geometry(d_h, d_w)
    return {"field_mm": header.field_mm, "d_h": d_h, "d_w": d_w, "resolution": header.resolution}
