"""The simplified point-detector model of Sec. 4.1 (Eqs. 17-24) as a fast forward model.

Each detector is a point at (d_w e_x, d_w e_y, d_h) (Eq. 17); the surface element at pixel
(x, y) has the normal n_S = [-dZ/dx, -dZ/dy, 1] (Eq. 16) and is assumed to lie in the plane z = 0
(heights small against d_h, as Eq. 17 assumes). Only the 1st scattering event is modelled and
nothing shadows anything except the element's own tangent plane. The image of detector k is

    I_k(x, y) = g(n_S, p_E, d_k) [ * Omega_k(x, y) ]

with one of three scattering laws g:

* ``"lambert"`` — Eq. 19: eta(theta)/pi cos(alpha), eta of Eqs. 10/12 at the incidence angle;
* ``"diffuse"`` — the diffuse part of Eq. 13 only: eta0/pi cos(alpha);
* ``"g_bse"`` — the full Eq. 13 (diffuse + specular lobe), :func:`elo_mitsuba.physics.g_bse`.

Eq. 26 inverts the ``lambert`` (and ``diffuse``) images exactly, for any beam direction, since
their beam-dependent factor is common to the four detectors of a pixel. The paper's derivation
uses a vertical beam; ``beam="pivot"`` instead deflects the beam from a pivot at height
``work_distance_mm`` above the origin (Fig. 1a), which matters for ``g_bse``.

The optional solid-angle factor Omega_k = pi r^2 cos(psi) / |P - D_k|^2 of a small disc of radius r
facing the origin turns the per-steradian value into N_d/N_0; it cancels in the STSA correction.
"""

from __future__ import annotations

import numpy as np

from ..constants import DETECTOR_DIRECTIONS, LOBE_WIDTH_DEG, WORK_DISTANCE_MM
from ..errors import EloInputError
from ..physics import g_bse, get_material
from .layout import check_detector_geometry, detector_vectors, pixel_coordinates

MODELS = ("lambert", "diffuse", "g_bse")
BEAMS = ("vertical", "pivot")


def beam_directions(x, y, beam="vertical", work_distance_mm=WORK_DISTANCE_MM) -> np.ndarray:
    """Beam direction of travel p_E at the surface points (x, y, 0), shape (..., 3), unnormalised.

    ``"vertical"``: [0, 0, -1] everywhere (Sec. 4.3). ``"pivot"``: from the gun pivot
    (0, 0, w_d) to (x, y, 0), i.e. [x, y, -w_d].

    Parameters
    ----------
    x, y : array_like
        Surface positions in mm (broadcast together).
    beam : {"vertical", "pivot"}
    work_distance_mm : float
        Height of the gun pivot above the build plane (mm), for ``"pivot"``.

    Returns
    -------
    ndarray (..., 3)
        p_E (mm for ``"pivot"``; unitless for ``"vertical"``).

    Examples
    --------
    >>> beam_directions(10.0, 0.0).tolist()
    [0.0, 0.0, -1.0]
    >>> beam_directions(10.0, -5.0, beam="pivot").tolist()
    [10.0, -5.0, -400.0]
    """
    x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
    if beam == "vertical":
        return np.stack([np.zeros_like(x), np.zeros_like(x), -np.ones_like(x)], axis=-1)
    if beam == "pivot":
        wd = float(work_distance_mm)
        if not (np.isfinite(wd) and wd > 0):
            raise EloInputError(f"work_distance_mm={work_distance_mm!r}: must be finite and > 0")
        return np.stack([x, y, np.full_like(x, -wd)], axis=-1)
    raise EloInputError(f"beam={beam!r}: choose one of {', '.join(BEAMS)}")


def point_detector_images(dzdx, dzdy, field_mm, d_h, d_w, *, model="lambert", material=None,
                          beam="vertical", work_distance_mm=WORK_DISTANCE_MM,
                          lobe_width_deg=LOBE_WIDTH_DEG, detector_radius_mm=None) -> dict[str, np.ndarray]:
    """Images R, L, B, F of the point-detector model for a gradient field.

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Surface gradient dZ/dx, dZ/dy (mm/mm), package orientation (row 0 = +y edge).
    field_mm : float or (float, float)
        Scan field in mm.
    d_h, d_w : float
        Detector height and distance from the z-axis (mm, Eq. 17).
    model : {"lambert", "diffuse", "g_bse"}
        Scattering law (module docstring).
    material : str, mapping or Material, optional
        Target material (default Ti-6Al-4V) for eta, eta0 and the lobe.
    beam : {"vertical", "pivot"}
        Beam direction model; ``work_distance_mm`` is the pivot height for ``"pivot"``.
    detector_radius_mm : float, optional
        If given, multiply by the small-disc solid angle (images in N_d/N_0); otherwise the
        images are per steradian (1/sr).

    Returns
    -------
    dict of str to ndarray (H, W)
        ``{"right": R, "left": L, "back": B, "front": F}``, >= 0 (0 where a detector is
        geometrically masked, n_S . d <= 0, or the beam meets the element from behind).

    Examples
    --------
    >>> import numpy as np
    >>> dzdx = np.full((2, 2), -0.1)                     # rising towards -x: faces the right detector
    >>> images = point_detector_images(dzdx, np.zeros((2, 2)), 20.0, 272.0, 127.0, model="lambert")
    >>> bool(np.all(images["right"] > images["left"])), images["back"].shape
    (True, (2, 2))
    """
    if model not in MODELS:
        raise EloInputError(f"model={model!r}: choose one of {', '.join(MODELS)}")
    d_h, d_w = check_detector_geometry(d_h, d_w)
    dzdx = np.asarray(dzdx, dtype=float)
    dzdy = np.asarray(dzdy, dtype=float)
    if dzdx.shape != dzdy.shape or dzdx.ndim != 2:
        raise EloInputError(f"dzdx {dzdx.shape} and dzdy {dzdy.shape}: expected two 2-D arrays of one shape")
    mat = get_material(material)
    x, y = pixel_coordinates(dzdx.shape, field_mm)
    normal = np.stack([-dzdx, -dzdy, np.ones_like(dzdx)], axis=-1)
    beam_dir = beam_directions(x, y, beam, work_distance_mm)
    n_hat = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    cos_t = -np.sum(n_hat * beam_dir, axis=-1) / np.linalg.norm(beam_dir, axis=-1)
    images = {}
    for name, d in detector_vectors(x, y, d_h, d_w).items():
        if model == "lambert":
            cos_a = np.sum(n_hat * d, axis=-1) / np.linalg.norm(d, axis=-1)
            theta = np.arccos(np.clip(cos_t, 0.0, 1.0))
            g = np.where((cos_t > 0) & (cos_a > 0), mat.eta(theta) / np.pi * cos_a, 0.0)
        else:
            g = g_bse(normal, beam_dir, d, mat, lobe=(model == "g_bse"), lobe_width_deg=lobe_width_deg)
        if detector_radius_mm is not None:
            g = g * point_solid_angle(x, y, name, d_h, d_w, detector_radius_mm)
        images[name] = g
    return images


def flat_plate_images(shape, field_mm, d_h, d_w, **kwargs) -> dict[str, np.ndarray]:
    """STSA correction images (Eq. 20): :func:`point_detector_images` of a plane plate (n_C = e_z).

    Parameters
    ----------
    shape : (int, int)
        Image shape (H, W).
    field_mm : float or (float, float)
        Scan field in mm.
    d_h, d_w : float
        Detector height and distance from the z-axis (mm).
    **kwargs
        As :func:`point_detector_images` (``model``, ``material``, ``beam``, ...).

    Returns
    -------
    dict of str to ndarray (H, W)
        ``{"right": C_R, "left": C_L, "back": C_B, "front": C_F}`` (1/sr, or N_d/N_0 with
        ``detector_radius_mm``).

    Examples
    --------
    >>> flats = flat_plate_images((3, 3), 20.0, 272.0, 127.0)
    >>> sorted(flats), flats["right"].shape
    (['back', 'front', 'left', 'right'], (3, 3))
    >>> bool(flats["right"][1, 2] > flats["right"][1, 0])  # brighter on the right detector's side
    True
    """
    zeros = np.zeros(tuple(shape)[:2])
    return point_detector_images(zeros, zeros, field_mm, d_h, d_w, **kwargs)


def point_solid_angle(x, y, detector, d_h, d_w, radius_mm):
    """Solid angle (sr) of a small disc of radius ``radius_mm`` at Eq. 17's detector position,
    its normal pointing at the origin (Sec. 2.2), seen from (x, y, 0): pi r^2 cos(psi) / dist^2.

    Parameters
    ----------
    x, y : array_like
        Surface position in mm.
    detector : {"right", "left", "back", "front"}
    d_h, d_w : float
        Detector height and distance from the z-axis (mm).
    radius_mm : float
        Disc radius in mm.

    Returns
    -------
    ndarray
        Solid angle in sr.

    Examples
    --------
    >>> round(float(point_solid_angle(0.0, 0.0, "right", 272.0, 127.0, 25.0)), 5)
    0.02179
    """
    r = float(radius_mm)
    if not (np.isfinite(r) and r > 0):
        raise EloInputError(f"detector_radius_mm={radius_mm!r}: must be finite and > 0")
    ex, ey = DETECTOR_DIRECTIONS[detector]
    centre = np.array([d_w * ex, d_w * ey, d_h])
    axis = -centre / np.linalg.norm(centre)
    v = np.stack(np.broadcast_arrays(np.asarray(x, float) - centre[0], np.asarray(y, float) - centre[1],
                                     np.full(np.shape(x), -centre[2])), axis=-1)
    dist2 = np.sum(v * v, axis=-1)
    cos_psi = np.sum(v * axis, axis=-1) / np.sqrt(dist2)
    return np.pi * r * r * np.maximum(cos_psi, 0.0) / dist2


def eq24_differences(n_sx, n_sy, x, y, d_h, d_w):
    """Normalised differences predicted by Eq. 24 for the Lambert point-detector model.

    M_x = n_Sx d_w / (d_h - (n_Sx x + n_Sy y)),   M_y = n_Sy d_w / (d_h - (n_Sx x + n_Sy y)).
    All inputs broadcast; lengths in mm.

    Parameters
    ----------
    n_sx, n_sy : array_like
        Surface normal components -dZ/dx, -dZ/dy (mm/mm).
    x, y : array_like
        Surface position in mm.
    d_h, d_w : float
        Detector height and distance from the z-axis (mm).

    Returns
    -------
    mx, my : ndarray
        M_x, M_y (dimensionless).

    Examples
    --------
    >>> mx, my = eq24_differences(0.1, 0.0, 0.0, 0.0, 272.0, 127.0)
    >>> round(float(mx), 4), round(float(my), 4)
    (0.0467, 0.0)
    """
    d_h, d_w = check_detector_geometry(d_h, d_w)
    den = d_h - (np.asarray(n_sx) * x + np.asarray(n_sy) * y)
    return np.asarray(n_sx) * d_w / den, np.asarray(n_sy) * d_w / den


__all__ = ["BEAMS", "MODELS", "beam_directions", "eq24_differences", "flat_plate_images",
           "point_detector_images", "point_solid_angle"]
