"""Tests of elo_mitsuba.physics: Eqs. 10-14 of Renner et al. 2023 and the materials.

Every reference value is computed here independently of the module (the polynomial of Eq. 11
written out, Castaing's rule summed by hand, C(theta) by a 2-D quadrature over the hemisphere),
so that a wrong coefficient, exponent or normalisation in the module makes a test fail.
Run with ``pytest -s`` to see the measured numbers.
"""

from __future__ import annotations

import numpy as np
import pytest

from elo_mitsuba.errors import EloInputError
from elo_mitsuba.physics import (
    eta0_element,
    eta_castaing,
    eta_darlington,
    get_material,
    lobe_normalisation,
    lobe_normalisation_eq14_repaired,
    parse_composition,
)

B = 0.89  # Darlington's saturation value, Eq. 10


def eq11(z):
    """Reimer's Eq. 11 written out term by term (not Horner, not the module's constants)."""
    z = float(z)
    return -0.0254 + 0.016 * z - 1.86e-4 * z**2 + 8.3e-7 * z**3


def eq10(theta_deg, eta0):
    return B * (eta0 / B) ** np.cos(np.deg2rad(theta_deg))


# --- Eq. 11 / Eq. 10 / Eq. 12 ----------------------------------------------------------------------

@pytest.mark.parametrize("z", [6, 13, 22, 23, 26, 29, 42, 47, 74, 79])
def test_eta0_of_pure_elements_is_eq11(z):
    assert eta0_element(z) == pytest.approx(eq11(z), rel=1e-12, abs=1e-15)


def test_eta0_reference_values():
    # sanity of the reference itself against commonly quoted values: Al ~0.15, Cu ~0.30, Au ~0.50
    assert eq11(13) == pytest.approx(0.153, abs=0.005)
    assert eq11(29) == pytest.approx(0.304, abs=0.005)
    assert eq11(79) == pytest.approx(0.49, abs=0.02)


@pytest.mark.parametrize("z", [1, 2, 5, 80, 82, 92])
def test_eta0_refuses_z_outside_fit_range(z):
    with pytest.raises(EloInputError, match=f"Z={z}"):
        eta0_element(z)


@pytest.mark.parametrize("eta0", [0.153, 0.25, 0.304, 0.497])
def test_eta_darlington_limits(eta0):
    assert eta_darlington(0.0, eta0) == pytest.approx(eta0, rel=1e-14)
    assert eta_darlington(np.pi / 2, eta0) == pytest.approx(B, rel=1e-14)
    # approaches B continuously and monotonically as theta -> 90 deg
    th = np.deg2rad([80.0, 89.0, 89.9, 89.999])
    vals = eta_darlington(th, eta0)
    assert np.all(np.diff(vals) > 0)
    assert abs(vals[-1] - B) < 1e-4
    for t in [10.0, 45.0, 75.0]:
        assert eta_darlington(np.deg2rad(t), eta0) == pytest.approx(eq10(t, eta0), rel=1e-13)


def test_ti6al4v_eta0_by_castaing():
    """Eq. 12 with c = 0.90/0.06/0.04 and Eq. 11 per element, computed in the test."""
    mat = get_material("Ti-6Al-4V")
    expected = 0.90 * eq11(22) + 0.06 * eq11(13) + 0.04 * eq11(23)
    print(f"\nTi-6Al-4V eta0 (Eq. 12): module {mat.eta0:.6f}, reference {expected:.6f}")
    assert mat.eta0 == pytest.approx(expected, rel=1e-12)
    assert mat.eta_deg(0.0) == pytest.approx(expected, rel=1e-12)
    # eta(theta): Eq. 10 element by element, summed with the weight fractions (docs/paper-notes.md §5)
    for t in [0.0, 20.0, 45.0, 70.0, 85.0, 90.0]:
        ref = 0.90 * eq10(t, eq11(22)) + 0.06 * eq10(t, eq11(13)) + 0.04 * eq10(t, eq11(23))
        assert mat.eta_deg(t) == pytest.approx(ref, rel=1e-12)
    assert mat.eta_deg(90.0) == pytest.approx(B, rel=1e-12)


def test_eta_castaing_matches_hand_sum():
    th = np.deg2rad(np.array([0.0, 30.0, 60.0]))
    got = eta_castaing(th, [0.5, 0.5], [eq11(13), eq11(29)])
    ref = 0.5 * eq10(np.rad2deg(th), eq11(13)) + 0.5 * eq10(np.rad2deg(th), eq11(29))
    np.testing.assert_allclose(got, ref, rtol=1e-13)


# --- C(theta): the lobe normalisation that replaces Eq. 14 ----------------------------------------

def _gauss(n, a, b):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (b - a) * (x + 1.0) + a, 0.5 * (b - a) * w


def c_reference(theta_deg: float, lobe_width_deg: float = 13.0, n: int = 96) -> float:
    """C(theta) by a 2-D quadrature in spherical coordinates (alpha, phi) about the NORMAL.

    C = int_{upper hemisphere} (k+1)/(2 pi) max(cos beta, 0)^k dOmega, lobe axis
    r = (-sin theta, 0, cos theta), so cos beta = cos theta cos alpha - sin theta sin alpha cos phi.
    On each ring alpha the lobe is positive for cos phi < cot theta cot alpha; the phi integral
    runs over that arc (nodes clustered at its end, where the integrand behaves like a power k),
    the alpha integral is split at alpha* = 90 deg - theta where the ring touches the lobe's edge.
    This is independent of the module's 1-D form (rings about the lobe axis cut by the horizon).
    """
    th = np.deg2rad(theta_deg)
    k = theta_deg / lobe_width_deg
    if th == 0.0:
        return 1.0
    st, ct = np.sin(th), np.cos(th)
    a_star = np.pi / 2 - th
    t, wt = _gauss(n, 0.0, 1.0)
    alpha = np.concatenate([a_star - a_star * t**2, a_star + (np.pi / 2 - a_star) * t**2])
    w_alpha = np.concatenate([wt * 2 * t * a_star, wt * 2 * t * (np.pi / 2 - a_star)])
    sa, ca = np.sin(alpha)[:, None], np.cos(alpha)[:, None]
    with np.errstate(divide="ignore"):
        c = np.where(sa > 0, ct * ca / (st * np.maximum(sa, 1e-300)), np.inf)
    full = c >= 1.0
    phi0 = np.where(full, 0.0, np.arccos(np.clip(c, -1.0, 1.0)))
    s, ws = _gauss(n, 0.0, 1.0)
    # full ring: plain Gauss on [0, pi]; partial: phi = phi0 + (pi - phi0) s^3
    phi_full, w_full = _gauss(n, 0.0, np.pi)
    phi = np.where(full, phi_full[None, :], phi0 + (np.pi - phi0) * s[None, :] ** 3)
    w_phi = np.where(full, w_full[None, :], ws[None, :] * 3 * s[None, :] ** 2 * (np.pi - phi0))
    cos_b = ct * ca - st * sa * np.cos(phi)
    lobe = np.where(cos_b > 0, np.power(np.maximum(cos_b, 0.0), k), 0.0)
    ring = 2.0 * np.sum(w_phi * lobe, axis=1)
    return float((k + 1.0) / (2.0 * np.pi) * np.sum(w_alpha * ring * sa[:, 0]))


def c_brute_force(theta_deg: float, lobe_width_deg: float = 13.0, n: int = 1200) -> float:
    """Midpoint rule on a plain (cos alpha, phi) grid: a check of c_reference itself (~1e-3)."""
    th = np.deg2rad(theta_deg)
    k = theta_deg / lobe_width_deg
    mu = (np.arange(n) + 0.5) / n
    phi = (np.arange(2 * n) + 0.5) * np.pi / n
    mu, phi = np.meshgrid(mu, phi, indexing="ij")
    cos_b = np.cos(th) * mu - np.sin(th) * np.sqrt(1 - mu**2) * np.cos(phi)
    f = np.where(cos_b > 0, np.power(np.maximum(cos_b, 0.0), k), 0.0)
    return float((k + 1) / (2 * np.pi) * f.sum() * (1.0 / n) * (np.pi / n))


def test_c_reference_agrees_with_brute_force():
    for t in [20.0, 60.0, 85.0]:
        assert c_reference(t) == pytest.approx(c_brute_force(t), abs=2e-3)


def test_lobe_normalisation_against_2d_quadrature():
    thetas = [0.0, 0.01, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 40.0, 45.0, 50.0, 60.0, 70.0,
              75.0, 80.0, 85.0, 88.0, 89.0, 89.5, 89.9, 90.0]
    got = lobe_normalisation(np.array(thetas))
    ref = np.array([c_reference(t) for t in thetas])
    err = np.abs(got - ref)
    print(f"\nC(theta) vs 2-D quadrature: worst |error| = {err.max():.2e} at "
          f"theta = {thetas[int(err.argmax())]} deg")
    assert err.max() < 1e-4
    # also for other lobe widths (narrow and broad lobes)
    for width in (1.0, 5.0, 40.0):
        for t in (10.0, 60.0, 89.0):
            assert float(lobe_normalisation(t, width)) == pytest.approx(
                c_reference(t, width), abs=1e-4)


def test_lobe_normalisation_endpoints():
    assert float(lobe_normalisation(0.0)) == pytest.approx(1.0, abs=1e-12)
    assert float(lobe_normalisation(90.0)) == pytest.approx(0.5, abs=1e-9)
    # C(90) = 1/2 for every k (the horizon halves the lobe); the module's quadrature is ~1e-9
    # accurate at the paper's width and a few 1e-6 for k ~ 0.1 (width 1e3 deg), fine for 1e-4.
    for width in (0.5, 13.0, 1e3):
        assert float(lobe_normalisation(90.0, width)) == pytest.approx(0.5, abs=1e-5)
    c = lobe_normalisation(np.linspace(0, 90, 181))
    assert np.all(np.isfinite(c)) and np.all((c >= 0.5 - 1e-9) & (c <= 1.0 + 1e-12))


@pytest.mark.parametrize("theta", [1.0, 15.0, 30.0, 60.0, 89.0])
def test_lobe_normalisation_k0_closed_form(theta):
    """k -> 0 (huge lobe width): the lobe is uniform over its hemisphere, C = 1 - theta/pi."""
    assert float(lobe_normalisation(theta, 1e12)) == pytest.approx(1 - theta / 180.0, abs=1e-8)


def test_printed_eq14_is_negative():
    """The printed Eq. 14, C = 1.01 - 4.06 theta + 1.36e-5 theta^2 - 1.71e-6 theta^3, is negative
    for every theta above ~0.25 deg (docs/paper-notes.md §1): it cannot be what the authors used, and the
    package must not use it. Documented here with numbers."""
    th = np.array([0.25, 0.5, 1.0, 10.0, 45.0, 89.0])
    printed = 1.01 - 4.06 * th + 1.36e-5 * th**2 - 1.71e-6 * th**3
    print("\nprinted Eq. 14 at", th.tolist(), "deg:", np.round(printed, 3).tolist())
    assert np.all(printed[1:] < 0)
    assert printed[0] < 0.01
    with pytest.raises(EloInputError, match="4.06"):
        lobe_normalisation_eq14_repaired(10.0, repair="4.06")


@pytest.mark.parametrize("repair, a", [("4.06e-3", 4.06e-3), ("4.06e-4", 4.06e-4)])
def test_repaired_eq14_refuses_nonpositive_angles(repair, a):
    def poly(t):
        return 1.01 - a * t + 1.36e-5 * t**2 - 1.71e-6 * t**3

    # both repairs cross zero below 90 deg
    grid = np.linspace(0.0, 90.0, 9001)
    first_zero = grid[np.argmax(poly(grid) <= 0)]
    assert poly(90.0) < 0 and first_zero < 90.0
    # where it is accepted it returns the polynomial, and it is positive
    assert float(lobe_normalisation_eq14_repaired(10.0, repair)) == pytest.approx(poly(10.0))
    accepted = []
    for t in np.linspace(0.0, 90.0, 181):
        try:
            v = float(lobe_normalisation_eq14_repaired(t, repair))
        except EloInputError as exc:
            assert "\n" not in str(exc)
            continue
        accepted.append(t)
        assert v > 0, f"repaired Eq. 14 returned {v} at {t} deg"
    assert max(accepted) < first_zero
    for t in (first_zero, 89.0, 90.0):
        with pytest.raises(EloInputError):
            lobe_normalisation_eq14_repaired(t, repair)
    with pytest.raises(EloInputError):
        lobe_normalisation_eq14_repaired(np.array([5.0, 89.0]), repair)
    print(f"\nEq. 14 repair {repair}: first zero at {first_zero:.2f} deg, accepted up to "
          f"{max(accepted):.1f} deg")


# --- materials -------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["316L", "Inconel 718", "Cu", "Ti", "Ti-6Al-4V"])
def test_presets_load_and_sum_to_one(name):
    mat = get_material(name)
    assert sum(mat.composition.values()) == pytest.approx(1.0, abs=1e-9)
    ref = sum(c * eq11(_Z[s]) for s, c in mat.composition.items())
    assert mat.eta0 == pytest.approx(ref, rel=1e-12)
    assert 0.1 < mat.eta0 < 0.5


_Z = {"Al": 13, "Si": 14, "Ti": 22, "V": 23, "Cr": 24, "Mn": 25, "Fe": 26, "Ni": 28, "Cu": 29,
      "Nb": 41, "Mo": 42}


def test_composition_string_equals_preset():
    a = get_material("Ti:0.9,Al:0.06,V:0.04")
    b = get_material("Ti-6Al-4V")
    assert a.eta0 == pytest.approx(b.eta0, rel=1e-14)
    assert parse_composition("Ti:0.9, Al:0.06, V:0.04") == {"Ti": 0.9, "Al": 0.06, "V": 0.04}
    # within the 1e-6 tolerance on the sum
    get_material("Ti:0.9,Al:0.06,V:0.0400005")


@pytest.mark.parametrize(
    "spec, named",
    [
        ("Xx:1", "Xx"),                          # unknown symbol
        ("Ti:0.9,Qq:0.1", "Qq"),
        ("Ti:0,Al:1", "Ti"),                     # fraction 0
        ("Ti:1.5", "1.5"),                       # fraction > 1
        ("Ti:-0.1,Al:1.1", "Ti"),                # negative fraction
        ("Ti:0.9,Al:0.06", "0.96"),              # sum != 1
        ("Ti:0.9,Al:0.06,V:0.042", "1.002"),  # sum off by 2e-3 (> 1e-3: not a rounded measurement)
        ("H:1", "H"),                            # Z below the range of Eq. 11
        ("Pb:1", "Pb"),                          # Z above it
        ("Ti0.9,Al0.1", "Ti0.9"),                # malformed
        ("Ti:abc", "abc"),
        ("Ti:0.5,Ti:0.5", "Ti"),
        ("Ti:nan", "nan"),
        ("Unobtainium", "Unobtainium"),          # unknown preset
        ("Ti-6Al-5V", "Ti-6Al-5V"),
    ],
)
def test_bad_material_gives_one_line_error_naming_the_value(spec, named):
    with pytest.raises(EloInputError) as info:
        get_material(spec)
    msg = str(info.value)
    print(f"\n{spec!r}: {msg}")
    assert named in msg, msg
    assert "\n" not in msg and msg.strip()


@pytest.mark.parametrize("mapping, named", [({"Zz": 1.0}, "Zz"), ({"Ti": 2.0}, "2.0"), ({}, "empty")])
def test_bad_mapping_composition(mapping, named):
    with pytest.raises(EloInputError, match=named):
        get_material(mapping)


def test_g_bse_integrates_to_eta_in_numpy():
    """g_bse_local (pure numpy) over the hemisphere equals eta(theta) (Eq. 2) on a fine grid."""
    from elo_mitsuba.physics import g_bse_local

    mat = get_material("Ti-6Al-4V")
    n = 800
    mu = (np.arange(n) + 0.5) / n
    phi = (np.arange(2 * n) + 0.5) * np.pi / n
    mu, phi = np.meshgrid(mu, phi, indexing="ij")
    st = np.sqrt(1 - mu**2)
    wo = np.stack([st * np.cos(phi), st * np.sin(phi), mu], axis=-1)
    worst = 0.0
    for t in (0.0, 30.0, 60.0, 80.0):
        th = np.deg2rad(t)
        wi = np.array([np.sin(th), 0.0, np.cos(th)])
        total = g_bse_local(wi, wo, mat).sum() * (1.0 / n) * (np.pi / n)
        ref = 0.90 * eq10(t, eq11(22)) + 0.06 * eq10(t, eq11(13)) + 0.04 * eq10(t, eq11(23))
        worst = max(worst, abs(total / ref - 1))
    print(f"\nnumpy g_BSE hemisphere integral: worst relative error {worst:.1e}")
    assert worst < 2e-3
