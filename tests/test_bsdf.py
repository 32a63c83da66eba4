"""Tests of the BSDF ``elo_bse`` (plugins/bsdf_elo_bse.py): g_BSE of Eq. 13 through Mitsuba.

Conventions (local frame, normal +z): ``si.wi`` points back to where the electron came from
(-p_E), ``eval`` is g_BSE per steradian including the cosine of alpha, so its integral over the
upper hemisphere is eta(theta) (Eq. 2 with Eqs. 10/12). Sampling is a mixture of a cosine lobe and
a Phong lobe about the mirror direction; ``pdf`` is the density of that sampling.

The references are independent of the plugin and live in :mod:`elo_mitsuba.testing`
(shared with validation/bsdf_report.py): eta(theta) from Eqs. 10-12, the hemisphere integral by a
2-D Gauss product rule in a frame adapted to the lobe (no C table), and the calls of the plugin in
its local frame. ``pytest -s`` prints the measured numbers; validation/bsdf_report.py prints them
as a table.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elo_mitsuba.testing import (
    CHI2_SAMPLES,
    MATERIALS,
    THETAS_CHI2,
    THETAS_ENERGY,
    binomial_se,
    bsdf_eval,
    bsdf_pdf,
    bsdf_sample,
    chi2_run,
    energy,
    eta0_ref,
    eta_ref,
    hemisphere_nodes,
    wi_of,
)

PLUGIN_FILE = Path(__file__).resolve().parents[1] / "plugins" / "bsdf_elo_bse.py"
pytestmark = pytest.mark.skipif(not PLUGIN_FILE.exists(), reason="plugins/bsdf_elo_bse.py missing")


def test_quadrature_self_check():
    """The reference quadrature integrates 1 to 2 pi and cos(alpha) to pi at every theta."""
    for t in (0.0, 45.0, 89.9, 90.0):
        for width in (13.0, 1e-3, 1e6):
            wo, w = hemisphere_nodes(t, width)
            assert np.all(wo[:, 2] > -1e-12)
            assert w.sum() == pytest.approx(2 * np.pi, rel=1e-9)
            assert (w * wo[:, 2]).sum() == pytest.approx(np.pi, rel=1e-9)


@pytest.mark.parametrize("material", MATERIALS)
def test_energy_equals_eta(mi, make_bsdf, material):
    """Hemisphere integral of eval = eta(theta) (Eqs. 10/12) within 0.2%, theta = 0..89.9 deg."""
    bsdf = make_bsdf(material)
    errors = []
    for t in THETAS_ENERGY:
        errors.append(energy(mi, bsdf, t) / eta_ref(material, t) - 1.0)
    errors = np.array(errors)
    print(f"\n{material}: relative energy error vs theta "
          + ", ".join(f"{t:g}:{e:+.1e}" for t, e in zip(THETAS_ENERGY, errors))
          + f"; worst {np.abs(errors).max():.2e}")
    assert np.all(np.abs(errors) < 2e-3), errors


@pytest.mark.parametrize("width", [0.5, 2.0, 1e4])
def test_energy_other_lobe_widths(mi, make_bsdf, width):
    """Narrow lobes (k up to 180) and k -> 0 also integrate to eta."""
    bsdf = make_bsdf("Ti-6Al-4V", lobe_width=width)
    errs = [energy(mi, bsdf, t, width) / eta_ref("Ti-6Al-4V", t) - 1 for t in (20.0, 60.0, 85.0, 89.5)]
    print(f"\nlobe_width {width:g} deg: worst energy error {np.abs(errs).max():.2e}")
    assert np.all(np.abs(errs) < 2e-3), errs


@pytest.mark.parametrize("material", ["Ti-6Al-4V", "Cu"])
def test_diffuse_only_integrates_to_eta0(mi, make_bsdf, material):
    bsdf = make_bsdf(material, lobe=False)
    for t in (0.0, 40.0, 80.0, 89.0):
        assert energy(mi, bsdf, t) == pytest.approx(eta0_ref(material), rel=1e-4)
        wo = hemisphere_nodes(t)[0][:500]
        np.testing.assert_allclose(bsdf_eval(mi, bsdf, wi_of(t), wo),
                                   eta0_ref(material) / np.pi * wo[:, 2], rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(bsdf_pdf(mi, bsdf, wi_of(t), wo), wo[:, 2] / np.pi,
                                   rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("material", MATERIALS)
def test_eval_equals_physics_g_bse_local(mi, make_bsdf, material):
    from elo_mitsuba.physics import g_bse_local, get_material

    rng = np.random.default_rng(1)
    wi = rng.normal(size=(4000, 3))
    wo = rng.normal(size=(4000, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wo[:, 2] = np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    # plus directions in and near the lobe, where g is largest
    theta = rng.uniform(0, 89.9, 2000)
    wi2 = np.stack([np.sin(np.deg2rad(theta)), np.zeros_like(theta), np.cos(np.deg2rad(theta))], 1)
    wo2 = np.stack([-wi2[:, 0], wi2[:, 1], wi2[:, 2]], 1) + rng.normal(scale=0.1, size=(2000, 3))
    wo2[:, 2] = np.abs(wo2[:, 2]) + 1e-3
    wo2 /= np.linalg.norm(wo2, axis=1, keepdims=True)
    wi, wo = np.concatenate([wi, wi2]), np.concatenate([wo, wo2])
    bsdf = make_bsdf(material)
    got = bsdf_eval(mi, bsdf, wi, wo)
    ref = g_bse_local(wi, wo, get_material(material))
    rel = np.abs(got / ref - 1)
    print(f"\n{material}: eval vs g_bse_local worst relative difference {rel.max():.2e}")
    assert rel.max() < 1e-5


@pytest.mark.parametrize("theta", THETAS_CHI2)
def test_chi2_sampling_matches_pdf(mi, theta):
    """chi2 accepts, and the histogram mass equals the pdf mass (chi2 alone would accept a pdf
    scaled by a constant): against the chi2 tabulation (binomial s.e. + its 1e-4 quadrature error)
    and against an accurate hemisphere integral of pdf (binomial s.e. only)."""
    ok, p, hist_mass, pdf_mass, _ = chi2_run(mi, theta)
    bsdf = mi.load_dict({"type": "elo_bse", "material": "Ti-6Al-4V"})
    wo, w = hemisphere_nodes(theta)
    pdf_mass_exact = float(np.sum(w * bsdf_pdf(mi, bsdf, wi_of(theta), wo)))
    se = binomial_se(hist_mass, CHI2_SAMPLES)
    print(f"\ntheta {theta:g}: p = {p:.3f}, histogram mass {hist_mass:.6f}, pdf mass "
          f"{pdf_mass:.6f} (tabulated) {pdf_mass_exact:.6f} (quadrature), s.e. {se:.1e}")
    assert ok, f"chi2 rejected at theta={theta}: p={p}"
    assert abs(hist_mass - pdf_mass) < 4.5 * se + 1e-4
    assert abs(hist_mass - pdf_mass_exact) < 4.5 * se
    assert pdf_mass_exact <= 1.0 + 1e-6


def test_chi2_other_material_and_narrow_lobe(mi):
    extra = '<string name="material" value="Cu"/><float name="lobe_width" value="3"/>'
    for theta in (45.0, 80.0):
        ok, p, hist_mass, pdf_mass, _ = chi2_run(mi, theta, extra, sample_count=500_000, test_count=2)
        print(f"\nCu, lobe_width 3, theta {theta:g}: p = {p:.3f}, masses {hist_mass:.5f} / {pdf_mass:.5f}")
        assert ok
        assert abs(hist_mass - pdf_mass) < 4.5 * binomial_se(hist_mass, 500_000) + 1e-4


@pytest.mark.parametrize("material", ["Ti-6Al-4V", "316L"])
@pytest.mark.parametrize("theta", [0.0, 30.0, 60.0, 85.0, 89.0, 89.9])
def test_sample_weight_is_eval_over_pdf(mi, make_bsdf, material, theta):
    """For sampled directions: weight = eval/pdf, bs.pdf = pdf(wo); rejected samples are below
    the surface; the mean weight (including zeros) is an unbiased estimate of eta(theta)."""
    bsdf = make_bsdf(material)
    wi = wi_of(theta, 37.0)
    n = 100_000
    wo, weight, spdf = bsdf_sample(mi, bsdf, wi, n, seed=int(theta * 10))
    ev = bsdf_eval(mi, bsdf, wi, wo)
    pd = bsdf_pdf(mi, bsdf, wi, wo)
    assert np.all(np.isfinite(weight)) and np.all(weight >= 0)
    ok = weight > 0
    assert ok.mean() > 0.5
    np.testing.assert_allclose(weight[ok], ev[ok] / pd[ok], rtol=1e-4)
    np.testing.assert_allclose(spdf[ok], pd[ok], rtol=1e-4)
    # a zero weight only where the direction carries no g_BSE (below the surface)
    assert np.all((ev[~ok] == 0) | (wo[~ok, 2] <= 1e-6))
    mean, se = weight.mean(), weight.std() / np.sqrt(n)
    eta = eta_ref(material, theta)
    print(f"\n{material} theta {theta:g}: MC energy {mean:.5f} +- {se:.1e} vs eta {eta:.5f}")
    assert abs(mean - eta) < 5 * se + 1e-5


EDGE_WI = {
    "theta->0": np.array([1e-7, 0.0, 1.0]),
    "theta->90": np.array([1.0, 0.0, 1e-7]),
    "normal": np.array([0.0, 0.0, 1.0]),
    "grazing-exact": np.array([1.0, 0.0, 0.0]),
    "below": np.array([0.3, 0.2, -0.5]),
}


@pytest.mark.parametrize("width", [13.0, 1e9, 1e-3])
@pytest.mark.parametrize("case", list(EDGE_WI))
def test_no_nan_inf_at_edges(mi, make_bsdf, case, width):
    """Finite eval/pdf/sample for theta -> 0 and 90, k -> 0 (huge width), k ~ 9e4 (1e-3 deg);
    exactly 0 for wo at/below the horizon and for wi below the surface."""
    bsdf = make_bsdf("Ti-6Al-4V", lobe_width=width)
    wi = EDGE_WI[case] / np.linalg.norm(EDGE_WI[case])
    rng = np.random.default_rng(3)
    wo = rng.normal(size=(3000, 3))
    wo[:1000, 2] = np.abs(wo[:1000, 2]) * 1e-6          # grazing, above and below
    wo[1000:1100, 2] = 0.0                              # exactly on the horizon
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    mirror = np.array([-wi[0], -wi[1], wi[2]])
    wo = np.concatenate([wo, mirror[None, :], [[0.0, 0.0, 1.0]], [[0.0, 0.0, -1.0]]])
    ev, pd = bsdf_eval(mi, bsdf, wi, wo), bsdf_pdf(mi, bsdf, wi, wo)
    assert np.all(np.isfinite(ev)) and np.all(np.isfinite(pd))
    assert np.all(ev >= 0) and np.all(pd >= 0)
    below = (wo[:, 2] <= 0) | (wi[2] <= 0)
    assert np.all(ev[below] == 0) and np.all(pd[below] == 0)
    swo, sw, spdf = bsdf_sample(mi, bsdf, wi, 20000, seed=5)
    assert np.all(np.isfinite(swo)) and np.all(np.isfinite(sw)) and np.all(np.isfinite(spdf))
    if wi[2] <= 0:
        assert np.all(sw == 0) and np.all(spdf == 0)
    else:
        assert np.all(sw[swo[:, 2] <= 0] == 0)
        assert np.any(sw > 0)


def test_hypothesis_random_directions_and_widths(mi):
    """Property test: for random wi, wo, material and lobe width, eval and pdf are finite and
    non-negative, zero exactly when a direction is at/below the surface, eval agrees with the
    numpy g_BSE (tolerance grows with k: float32 cos(beta)^k), and sampling gives weight = eval/pdf."""
    pytest.importorskip("hypothesis")
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from elo_mitsuba.physics import g_bse_local, get_material

    cache = {}

    def bsdf_for(material, width):
        key = (material, width)
        if key not in cache:
            cache[key] = mi.load_dict({"type": "elo_bse", "material": material, "lobe_width": width})
        return cache[key]

    @settings(max_examples=40, deadline=None, derandomize=True)
    @given(
        material=st.sampled_from(["Ti-6Al-4V", "Cu", "316L", "Inconel 718", "Ti:0.5,Cu:0.5"]),
        log_width=st.floats(min_value=-3.0, max_value=6.0),
        seed=st.integers(min_value=0, max_value=2**31 - 1),
    )
    def check(material, log_width, seed):
        width = float(10.0 ** log_width)
        bsdf = bsdf_for(material, width)
        rng = np.random.default_rng(seed)
        n = 256
        wi = rng.normal(size=(n, 3))
        wo = rng.normal(size=(n, 3))
        wi[: n // 2, 2] = np.abs(wi[: n // 2, 2])
        wi /= np.linalg.norm(wi, axis=1, keepdims=True)
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        ev, pd = bsdf_eval(mi, bsdf, wi, wo), bsdf_pdf(mi, bsdf, wi, wo)
        assert np.all(np.isfinite(ev)) and np.all(np.isfinite(pd))
        assert np.all(ev >= 0) and np.all(pd >= 0)
        inside = (wi[:, 2] > 1e-6) & (wo[:, 2] > 1e-6)
        outside = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
        assert np.all(ev[outside] == 0) and np.all(pd[outside] == 0)
        assert np.all(ev[inside] > 0) and np.all(pd[inside] > 0)
        ref = g_bse_local(wi, wo, get_material(material), lobe_width_deg=width)
        k = np.degrees(np.arccos(np.clip(wi[:, 2], 0, 1))) / width
        tol = 1e-5 + 3e-7 * k
        assert np.all(np.abs(ev - ref) <= tol * ref + 1e-12)
        wi1 = wi[0] if wi[0, 2] > 1e-3 else np.array([0.0, 0.0, 1.0])
        swo, sw, spdf = bsdf_sample(mi, bsdf, wi1, 512, seed=seed)
        assert np.all(np.isfinite(sw)) and np.all(sw >= 0)
        ok = sw > 0
        sev = bsdf_eval(mi, bsdf, wi1, swo[ok])
        spd = bsdf_pdf(mi, bsdf, wi1, swo[ok])
        np.testing.assert_allclose(sw[ok], sev / spd, rtol=1e-3)

    check()
