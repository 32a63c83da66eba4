"""The film's channels as planes (elo_mitsuba.film) and the blocked combination of the halves
(elo_mitsuba.error_estimate.combine_halves), against independent computations.

* :func:`raw_planes` develops the raw film storage bit for bit as Mitsuba's own ``hdrfilm``
  develop does (value / weight), also where the weight is not 1 (several samples per pixel), in
  any order of the columns and for sizes that are not a multiple of the block;
* :func:`film_tensor` is the inverse move (planes -> H x W x C), with a first channel;
* the integrator's ``render`` (what ``mi.render`` returns) and ``render_planes`` give the same
  channels, and its 'Y' is the sum of the detectors' totals;
* :func:`combine_halves` gives bit for bit the mean and error of the whole-image formulas
  (``w a + (1 - w) b`` in float64, :func:`halves_error`) and their summary to rounding, in place,
  and reports identical halves as deterministic.
"""

from __future__ import annotations

import numpy as np
import pytest

import elo_mitsuba as em
from elo_mitsuba.error_estimate import (DETERMINISTIC, ESTIMATED, combine_halves, halves_error, percentile_99,
                                        same_result, summarise)
from elo_mitsuba.film import film_tensor, raw_planes

mi = em.ensure_variant()


@pytest.fixture(scope="module")
def rendered():
    """A scene with relief and events 2, 37 x 37 pixels (not a multiple of the block), 3 samples
    per pixel (weights 3), rendered without develop."""
    scene = em.load_scene("corrugated_chamber", res=37, field=20)
    film = scene.sensor.film()
    integ = scene.integrator
    integ.configure(integ.options.replace(detector_sampling="quadrature", bounce_filter=0.0, bounce_min=0.0))
    img = integ.render(scene.scene, 0, 5, 3, develop=False)
    del img
    return scene, integ, film


def test_raw_planes_are_mitsubas_develop_bit_for_bit(rendered):
    _, integ, film = rendered
    raw = film.develop(raw=True)
    developed = np.asarray(film.develop())  # Mitsuba's own: Y, then the AOVs
    aovs = integ.aov_names()
    first = int(raw.shape[2]) - len(aovs)
    weight = np.asarray(raw)[..., first - 1]
    assert np.all(weight == 3.0)  # the division is exercised
    order = list(range(len(aovs)))[::-1]  # any order of the columns
    planes, _ = raw_planes(raw, [first + k for k in order], weight_column=first - 1)
    assert planes.shape == (len(aovs), developed.shape[0], developed.shape[1])
    for i, k in enumerate(order):
        assert np.array_equal(planes[i], developed[..., 1 + k]), aovs[k]
    assert planes.flags.writeable


def test_planes_the_caller_fills_are_not_developed(rendered, monkeypatch):
    """A column None leaves its plane to the caller (the integrator's totals, which it sums again
    from the events): the other planes are developed as before, bit for bit, and the integrator's
    totals are its events' sums whether or not the film's totals were developed."""
    _, integ, film = rendered
    raw = film.develop(raw=True)
    aovs = integ.aov_names()
    first = int(raw.shape[2]) - len(aovs)
    full, _ = raw_planes(raw, [first + k for k in range(len(aovs))], weight_column=first - 1)
    columns = [None if k % 3 == 0 else first + k for k in range(len(aovs))]
    part, _ = raw_planes(raw, columns, weight_column=first - 1)
    assert part.shape == full.shape
    for k, col in enumerate(columns):
        if col is not None:
            assert np.array_equal(part[k], full[k]), aovs[k]
    import sys

    scene = em.load_scene("athene_flat", res=24, events=2)
    scene.set_quality("default")
    integ = scene.integrator
    assert integ._sums_totals()
    module = sys.modules[type(integ).__module__]
    skipped = []

    def spy(raw_, columns_, **kwargs):
        skipped.append([i for i, col in enumerate(columns_) if col is None])
        return raw_planes(raw_, columns_, **kwargs)

    monkeypatch.setattr(module, "raw_planes", spy)
    planes, _ = integ.render_planes(scene.scene, 0, 4, 1)
    names = integ.channel_names()
    assert skipped == [[names.index(d) for d in ("right", "left", "back", "front")]]
    for d in ("right", "left", "back", "front"):
        e1, e2 = planes[names.index(f"{d}.e1")], planes[names.index(f"{d}.e2")]
        assert np.array_equal(planes[names.index(d)], e1 + e2), d


def test_film_tensor_is_the_inverse_move(rendered):
    _, integ, film = rendered
    raw = film.develop(raw=True)
    first = int(raw.shape[2]) - len(integ.aov_names())
    planes, buffer = raw_planes(raw, list(range(first, first + 4)), weight_column=first - 1)
    head = np.arange(planes[0].size, dtype=np.float32).reshape(planes[0].shape)
    tensor = np.asarray(film_tensor(buffer, 4, *planes.shape[1:], first=head))
    assert tensor.shape == planes.shape[1:] + (5,)
    assert np.array_equal(tensor[..., 0], head)
    for i in range(4):
        assert np.array_equal(tensor[..., 1 + i], planes[i])
    plain = np.asarray(film_tensor(buffer, 4, *planes.shape[1:]))
    assert np.array_equal(plain, np.moveaxis(planes, 0, -1))


def test_render_and_render_planes_agree():
    scene = em.load_scene("athene_flat", res=24, events=2)
    integ = scene.integrator
    scene.set_quality("default")
    img = np.asarray(mi.render(scene.scene, spp=4, seed=9))
    planes, _ = integ.render_planes(scene.scene, 0, 9, 4)
    names = integ.channel_names()
    assert img.shape[2] == 1 + len(names) == 1 + planes.shape[0]
    for i, name in enumerate(names):
        assert np.array_equal(img[..., 1 + i], planes[i]), name
    total = planes[names.index("right")].copy()
    for name in ("left", "back", "front"):
        total = total + planes[names.index(name)]
    assert np.array_equal(img[..., 0], total)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_combine_halves_is_the_whole_image_formulas(dtype):
    rng = np.random.default_rng(4)
    shape = (301, 233)  # 70133 pixels: one full block and a partial one
    a = (1.0 + rng.random(shape)).astype(dtype)
    b = (a * (1.0 + 0.01 * rng.standard_normal(shape))).astype(dtype)
    a[:3] = 0.0  # dark pixels: the floor of the relative error
    b[:3] = 0.0
    share = 2.0 / 3.0
    mean_ref = (share * a.astype(np.float64) + (1.0 - share) * b.astype(np.float64)).astype(np.float32)
    err_ref = halves_error(a, b, share)
    summary_ref = summarise(mean_ref, err_ref, ESTIMATED)
    assert not same_result(a, b)
    mean, err, summary = combine_halves(a.copy(), b.copy(), share)
    assert mean.dtype == np.float32 and err.dtype == np.float32
    assert np.array_equal(mean, mean_ref)
    assert np.array_equal(err, err_ref)
    assert summary["status"] == ESTIMATED
    for key in ("rms_rel", "p99_rel", "rms_abs"):
        assert summary[key] == pytest.approx(summary_ref[key], rel=1e-12), key
    if dtype is np.float32:  # in place: the mean in a, the error in b
        a2, b2 = a.copy(), b.copy()
        mean, err, _ = combine_halves(a2, b2, share)
        assert mean is a2 and err is b2


def test_combine_halves_reports_identical_halves_as_deterministic():
    a = np.linspace(0.0, 1.0, 5000, dtype=np.float32).reshape(50, 100)
    b = a.copy()
    b[7, 7] += 1e-7  # float32 rounding of another summation order
    _, err, summary = combine_halves(a.copy(), b.copy(), 0.5)
    assert err is None and summary["status"] == DETERMINISTIC
    assert same_result(a, b)


def test_percentile_99_is_numpys():
    """The 99th percentile found among the values above a sampled threshold is numpy's (linear
    interpolation) also where the stride sample misleads: mostly zeros, heavy ties, values sorted
    so that every 64th is the largest of its run, every 64th far above the rest, heavy tails, and
    sizes around the cut-over."""
    rng = np.random.default_rng(0)
    for trial in range(200):
        n = int(rng.integers(1, 200000)) if trial > 4 else (1, 4095, 4096, 4097, 64 * 70)[trial]
        x = rng.random(n)
        kind = trial % 6
        if kind == 5:
            x[::64] += 10.0  # the sample holds only the largest: its threshold lies above the 99 %
        elif kind == 1:
            x[rng.random(n) < 0.99] = 0.0
        elif kind == 2:
            x = np.round(x * 3) / 3
        elif kind == 3:
            x = np.sort(x)[::-1].copy()
        elif kind == 4:
            x = rng.standard_cauchy(n) ** 2
        assert percentile_99(x) == pytest.approx(np.percentile(x, 99), rel=1e-12, abs=0.0), (trial, n)
