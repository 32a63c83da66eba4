"""Issue 25, steps: the robust (Cauchy) integration keeps cliffs and the relief beside them.

Analytic gradient fields with steps, noise and masks (1 mm pixels); no renders. Each case states
what least squares does with the same input, so that a robust solver that quietly fell back to
least squares would fail here.
"""

import numpy as np
import pytest

from elo_mitsuba.analysis.integrate import (
    height_gradient,
    integrate_dct,
    integrate_gradient,
    integrate_masked,
    integrate_robust,
    resolve_method,
)
from elo_mitsuba.errors import EloInputError

N = 64
FIELD = float(N)  # 1 mm pixels
H = 0.5  # the step (mm)
R0, R1, C0, C1 = 20, 44, 18, 46  # the raised patch: rows R0..R1-1, columns C0..C1-1


def _relief():
    """A gentle relief (tens of µm, wavelengths of tens of pixels) everywhere."""
    r, c = np.mgrid[0:N, 0:N].astype(float)
    return 0.03 * np.sin(c / 7.0) * np.cos(r / 9.0)


def _patch_surface(step=H):
    z = _relief()
    z[R0:R1, C0:C1] += step
    return z


def _rms(e, sel):
    v = e[sel] - e[sel].mean()
    return float(np.sqrt(np.mean(v ** 2)))


def _away_from_walls(margin=3):
    """Pixels at least ``margin`` from every wall of the patch, inside and outside."""
    r, c = np.mgrid[0:N, 0:N]
    inside = (r >= R0 + margin) & (r < R1 - margin) & (c >= C0 + margin) & (c < C1 - margin)
    outside = (r < R0 - margin) | (r >= R1 + margin) | (c < C0 - margin) | (c >= C1 + margin)
    return inside, outside


def _step(z, margin=3):
    """The step as a height map shows it, less what the relief alone gives the same measure."""
    inside, outside = _away_from_walls(margin)
    relief = _relief()
    return float(np.median((z - relief)[inside]) - np.median((z - relief)[outside]))


def test_a_step_in_one_pixel_column_is_recovered_in_full():
    # the gradient of a 1 mm cliff concentrated in column 30 of every row: its two pairs carry
    # half each, so the jump is whole (and pixel 30 sits half way)
    dzdx, dzdy = np.zeros((N, N)), np.zeros((N, N))
    dzdx[:, 30] = 1.0
    rng = np.random.default_rng(0)
    dzdx += 0.002 * rng.standard_normal(dzdx.shape)
    dzdy += 0.002 * rng.standard_normal(dzdy.shape)
    z, _ = integrate_robust(dzdx, dzdy, FIELD)
    jump = np.median(z[:, 32:]) - np.median(z[:, :29])
    assert jump == pytest.approx(1.0, abs=0.01)
    assert np.median(z[:, 30]) - np.median(z[:, :29]) == pytest.approx(0.5, abs=0.01)


def test_a_truncated_wall_stays_truncated():
    # what it cannot do: a wall whose slope is clipped on every side (beam blur, the model's fit
    # saturating) holds only part of the jump, and no integration puts the rest back
    dzdx, dzdy = height_gradient(_patch_surface(), FIELD)
    dzdx, dzdy = np.clip(dzdx, -0.1, 0.1), np.clip(dzdy, -0.1, 0.1)   # the wall's 0.25 -> 0.1
    z, _ = integrate_robust(dzdx, dzdy, FIELD)
    assert _step(z) == pytest.approx(0.4 * H, abs=0.02 * H)


def test_an_inconsistent_wall_is_given_up_instead_of_spread_over_the_flats():
    # three walls say H, the left wall's gradient is lost (0) over most of its length: least
    # squares spreads that disagreement over the relief inside and around the patch
    truth = _patch_surface()
    dzdx, dzdy = height_gradient(truth, FIELD)
    dzdx[R0 + 2:R1 - 2, C0 - 1:C0 + 1] = 0.0
    rng = np.random.default_rng(1)
    dzdx = dzdx + 0.001 * rng.standard_normal(dzdx.shape)
    dzdy = dzdy + 0.001 * rng.standard_normal(dzdy.shape)
    inside, outside = _away_from_walls()
    z = integrate_robust(dzdx, dzdy, FIELD)[0]
    z_ls = integrate_dct(dzdx, dzdy, FIELD)
    for sel in (inside, outside):  # the relief on either side of the cliff, each up to a constant
        assert _rms(z - truth, sel) < 0.1 * _rms(z_ls - truth, sel)
        assert _rms(z - truth, sel) < 0.01 * H
    assert _step(z) == pytest.approx(H, abs=0.02 * H)


def test_masked_pixels_at_the_foot_of_a_wall_do_not_pull_the_relief_beside_it():
    # the foot of the right wall shadowed: three columns masked, their gradient garbage
    truth = _patch_surface()
    dzdx, dzdy = height_gradient(truth, FIELD)
    mask = np.zeros((N, N), bool)
    mask[R0:R1, C1:C1 + 3] = True
    rng = np.random.default_rng(2)
    bad_x, bad_y = dzdx.copy(), dzdy.copy()
    bad_x[mask] = rng.uniform(-5, 5, mask.sum())
    bad_y[mask] = rng.uniform(-5, 5, mask.sum())
    z, m = integrate_robust(bad_x, bad_y, FIELD, mask)
    assert (m == mask).all()
    # what lies under the mask does not matter at all
    z0, _ = integrate_robust(dzdx, dzdy, FIELD, mask)
    np.testing.assert_allclose(z, z0, atol=1e-12)
    beside = np.zeros((N, N), bool)
    beside[R0 + 3:R1 - 3, C1 + 3:C1 + 8] = True   # the powder beside the masked foot
    top = np.zeros((N, N), bool)
    top[R0 + 3:R1 - 3, C1 - 6:C1 - 1] = True      # the part's top next to the wall (off its corners)
    ok = ~mask
    e = z - truth - np.mean((z - truth)[ok])
    assert np.abs(e[beside]).max() < 0.01 * H and np.abs(e[top]).max() < 0.02 * H
    # the DCT solver takes the masked gradient as flat and pulls both sides towards each other
    z_dct, _ = integrate_gradient(bad_x, bad_y, FIELD, method="dct", mask=mask)
    e_dct = z_dct - truth - np.mean((z_dct - truth)[ok])
    assert np.abs(e_dct[beside]).max() > 5 * np.abs(e[beside]).max()


def test_on_a_smooth_field_it_is_least_squares():
    # an exactly integrable ramp: any weights give least squares' heights
    dzdx, dzdy = np.full((N, N), 0.3), np.full((N, N), -0.1)
    np.testing.assert_allclose(integrate_robust(dzdx, dzdy, FIELD)[0], integrate_masked(dzdx, dzdy, FIELD)[0],
                               atol=1e-9)
    # a smooth relief (central differences: nearly integrable), then with noise: the Cauchy weights
    # stay near 1 and the heights within a fraction of least squares' own error of it
    truth = _relief() * 10.0
    everywhere = np.ones((N, N), bool)
    rng = np.random.default_rng(3)
    for noise in (0.0, 0.01):
        dzdx, dzdy = height_gradient(truth, FIELD)
        dzdx, dzdy = dzdx + noise * rng.standard_normal(dzdx.shape), dzdy + noise * rng.standard_normal(dzdy.shape)
        z_ls, _ = integrate_masked(dzdx, dzdy, FIELD)
        z, _, (wc, wr) = integrate_robust(dzdx, dzdy, FIELD, return_weights=True)
        ls_error = _rms(z_ls - truth, everywhere)
        assert _rms(z - z_ls, everywhere) < 0.35 * ls_error
        assert _rms(z - truth, everywhere) < 1.1 * ls_error
        assert np.median(np.concatenate([wc.ravel(), wr.ravel()])) > 0.9


def test_the_conjugate_gradient_path_agrees_with_the_direct_one():
    truth = _patch_surface()
    dzdx, dzdy = height_gradient(truth, FIELD)
    dzdx[R0 + 2:R1 - 2, C0 - 1:C0 + 1] = 0.0
    mask = np.zeros((N, N), bool)
    mask[R0:R1, C1:C1 + 3] = True
    z_direct, _ = integrate_robust(dzdx, dzdy, FIELD, mask)
    z_cg, _ = integrate_robust(dzdx, dzdy, FIELD, mask, direct_limit=0)
    assert np.abs(z_cg - z_direct).max() < 0.01 * H


def test_progress_reports_each_reweighted_solve_and_the_energy_never_rises():
    """What ``reconstruct --method robust`` prints at 1500² (about 2 s a solve): one report per
    reweighted solve, and the Cauchy energy falls at each (IRLS majorises it), on both solve paths."""
    truth = _patch_surface()
    dzdx, dzdy = height_gradient(truth, FIELD)
    dzdx[R0 + 2:R1 - 2, C0 - 1:C0 + 1] = 0.0
    for limit in (40_000, 0):  # sparse LU, then conjugate gradients with the DCT preconditioner
        steps = []
        z, _ = integrate_robust(dzdx, dzdy, FIELD, direct_limit=limit, progress=steps.append)
        assert [s["iteration"] for s in steps] == list(range(1, len(steps) + 1)) and 2 <= len(steps) <= 30
        assert all(s["iterations"] == 30 for s in steps)
        energy = [s["energy"] for s in steps]
        assert all(b <= a * (1 + 1e-9) for a, b in zip(energy, energy[1:])), energy
        assert all(b["seconds"] >= a["seconds"] for a, b in zip(steps, steps[1:]))
        assert np.array_equal(z, integrate_robust(dzdx, dzdy, FIELD, direct_limit=limit)[0])  # reporting changes nothing


@pytest.mark.parametrize("case", ["all masked", "constant", "nan", "all nan", "one row", "single pixels"])
def test_degenerate_inputs_give_finite_heights(case):
    dzdx, dzdy = np.full((12, 16), 0.25), np.zeros((12, 16))
    mask = None
    if case == "all masked":
        mask = np.ones(dzdx.shape, bool)
    elif case == "nan":
        dzdx[3:5, 4:9] = np.nan
    elif case == "all nan":
        dzdx[:] = np.nan
    elif case == "one row":
        dzdx, dzdy = dzdx[:1], dzdy[:1]
    elif case == "single pixels":
        mask = (np.add.outer(np.arange(12), np.arange(16)) % 2).astype(bool)  # a chessboard
    z, m = integrate_robust(dzdx, dzdy, (dzdx.shape[1], dzdx.shape[0]), mask)
    assert np.isfinite(z).all() and (z[m] == 0).all()
    if case == "constant":  # the ramp of 0.25 mm per 1 mm pixel, exactly
        np.testing.assert_allclose(np.diff(z, axis=1), 0.25, atol=1e-9)
    if case in ("all masked", "all nan"):
        assert m.all()


def test_bad_arguments_are_refused_in_one_line():
    with pytest.raises(EloInputError, match="scale_mm"):
        integrate_robust(np.zeros((4, 4)), np.zeros((4, 4)), 4.0, scale_mm=-1.0)
    with pytest.raises(EloInputError, match="mask shape"):
        integrate_robust(np.zeros((4, 4)), np.zeros((4, 4)), 4.0, np.zeros((3, 4), bool))
    with pytest.raises(EloInputError, match="robust"):
        resolve_method("cauchy", np.zeros((4, 4)), np.zeros((4, 4)))


def test_the_pipeline_and_the_command_run_it(tmp_path, capsys):
    from elo_mitsuba.analysis.chain import heights
    from elo_mitsuba.cli import main
    from elo_mitsuba.exr import read_exr, write_exr

    dzdx, dzdy = height_gradient(_patch_surface(), FIELD)
    out = heights(dzdx, dzdy, FIELD, method="robust")
    assert out["method"] == "robust" and _step(out["height"]) == pytest.approx(H, abs=0.02 * H)
    write_exr(tmp_path / "g.exr", {"dzdx": dzdx, "dzdy": dzdy}, {"field_mm": [FIELD, FIELD]})
    assert main(["reconstruct", str(tmp_path / "g.exr"), "-o", str(tmp_path / "h.exr"), "--method", "robust"]) == 0
    assert "method robust" in capsys.readouterr().out
    channels, meta = read_exr(tmp_path / "h.exr")
    assert meta["method"] == "robust" and _step(channels["height"]) == pytest.approx(H, abs=0.02 * H)
