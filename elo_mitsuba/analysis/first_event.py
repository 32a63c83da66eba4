"""The 1st scattering event onto a disc detector by quadrature: the reference for Eq. 5.

N_1,d / N_0 = int_{Omega_d} g_BSE dOmega = int_disc g_BSE cos(psi) / r^2 dA  (Eq. 5 written over
the detector area), with Gauss-Legendre nodes in the radius and midpoint nodes in the azimuth
(:func:`~elo_mitsuba.analysis.layout.disc_nodes`). Independent of Mitsuba and of the
integrator's estimators (no sampling, no triangles, no Van Oosterom-Strackee): the tests,
the validation studies and the benchmarks hold the renderer's 1st event to it.
"""

from __future__ import annotations

import numpy as np

from ..physics import g_bse, get_material
from .layout import disc_nodes


def disc_integral(point, beam_dir, normal, centre, disc_normal, radius, material, n_r=64, n_phi=256,
                  lobe=True, collector=None) -> float:
    """N_d/N_0 of the 1st event at one surface point onto one disc (Eq. 5 by quadrature).

    Parameters
    ----------
    point : array_like (3,)
        Where the beam hits the surface (mm).
    beam_dir : array_like (3,)
        Direction of travel of the beam electrons (any length).
    normal : array_like (3,)
        Surface normal at ``point`` (any length).
    centre, disc_normal : array_like (3,)
        Disc centre (mm) and its front normal (towards the surface); the back collects nothing.
    radius : float
        Disc radius (mm).
    material : Material or str
        Target material (:func:`elo_mitsuba.physics.get_material`).
    n_r, n_phi : int
        Nodes in the radius and the azimuth.
    lobe : bool
        Include the specular lobe of Eq. 13 (False: Lambert part only).
    collector : Material or str, optional
        The plate's material if it backscatters: it keeps 1 - eta(theta_d) of what arrives at
        angle theta_d to its normal (Eqs. 10-12); None: it keeps everything.
    """
    material = get_material(material)
    disc_normal = np.asarray(disc_normal, float) / np.linalg.norm(disc_normal)
    q, area = disc_nodes(centre, disc_normal, radius, n_r, n_phi)
    d = q - np.asarray(point, float)
    dist2 = np.sum(d * d, axis=-1)
    dirs = d / np.sqrt(dist2)[..., None]
    cos_d = np.clip(-np.sum(dirs * disc_normal, axis=-1), 0.0, None)
    g = g_bse(np.broadcast_to(normal, dirs.shape), np.broadcast_to(beam_dir, dirs.shape), dirs,
              material, lobe=lobe)
    if collector is not None:
        g = g * (1.0 - get_material(collector).eta(np.arccos(np.clip(cos_d, 0.0, 1.0))))
    return float(np.sum(g * cos_d / dist2 * area))


def flat_plate_signal(points_xy, wd, centre, radius, material, n_r=32, n_phi=96) -> np.ndarray:
    """:func:`disc_integral` on a flat plate (normal +z) for beam targets ``points_xy`` (N, 2)
    on z = 0, the beam from the pivot (0, 0, ``wd``), the disc facing the origin."""
    centre = np.asarray(centre, float)
    pivot = np.array([0.0, 0.0, float(wd)])
    out = np.empty(len(points_xy))
    for i, (x, y) in enumerate(np.asarray(points_xy, float)):
        p = np.array([x, y, 0.0])
        out[i] = disc_integral(p, p - pivot, [0.0, 0.0, 1.0], centre, -centre, radius, material, n_r, n_phi)
    return out
