"""Geometry helpers of elo_mitsuba.analysis.layout against closed forms."""

import pytest


def test_disc_nodes_integrate_area_moments_and_on_axis_solid_angle():
    """Against closed forms: area pi R^2, polar moment pi R^4 / 2, nodes in the disc's plane,
    and the solid angle of a disc seen on its axis from h, 2 pi (1 - h / sqrt(h^2 + R^2))."""
    import numpy as np

    from elo_mitsuba.analysis.layout import disc_nodes

    centre, normal, radius, h = np.array([127.0, 0.0, 272.0]), np.array([-127.0, 0.0, -272.0]), 25.0, 300.0
    q, w = disc_nodes(centre, normal, radius, n_r=16, n_phi=48)
    n = normal / np.linalg.norm(normal)
    rel = q - centre
    assert np.allclose(rel @ n, 0.0, atol=1e-9)
    r2 = np.sum(rel * rel, axis=-1)
    assert np.all(r2 <= radius ** 2 * (1 + 1e-12))
    assert np.sum(w) == pytest.approx(np.pi * radius ** 2, rel=1e-12)
    assert np.sum(w * r2) == pytest.approx(np.pi * radius ** 4 / 2, rel=1e-12)
    eye = centre - h * n  # on the axis, in front of the disc
    d = q - eye
    dist2 = np.sum(d * d, axis=-1)
    omega = np.sum(w * (d @ n) / dist2 ** 1.5)
    assert omega == pytest.approx(2 * np.pi * (1 - h / np.hypot(h, radius)), rel=1e-10)
    q_z, _ = disc_nodes([0, 0, 5.0], [0, 0, 1.0], 1.0)  # normal along z: another tangent, same disc
    assert np.allclose(q_z[..., 2], 5.0) and np.max(np.hypot(q_z[..., 0], q_z[..., 1])) <= 1.0
