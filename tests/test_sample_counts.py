"""Stratified beam sampling (the shipped scenes' ``multijitter``): exact pass counts, no bias,
and less noise where the signal changes inside the beam spot."""

from pathlib import Path

import numpy as np
import pytest

import elo_mitsuba as em
from elo_mitsuba.sample_counts import count_at_least, each_pass, pass_count, pass_sizes, takes
from elo_mitsuba.scene_files import scenes_dir


@pytest.fixture(scope="module")
def samplers():
    em.ensure_variant()
    import mitsuba as mi

    return {kind: mi.load_dict({"type": kind, "sample_count": 4}) for kind in ("independent", "multijitter")}


def test_passes_are_counts_the_sampler_takes(samplers):
    mj, ind = samplers["multijitter"], samplers["independent"]
    for total in range(1, 40):
        for per_pass in (1, 5, 7, 16, 1024):
            split = pass_sizes(mj, total, per_pass)
            sizes = list(each_pass(split))
            assert sum(sizes) == total and max(sizes) <= per_pass and pass_count(split) == len(sizes)
            for n in sizes:
                probe = mj.clone()
                probe.set_sample_count(n)
                assert probe.sample_count() == n
                assert n & (n - 1) == 0, sizes  # a power of two: a pixel's lanes stay in one Dr.Jit block
    assert not takes(mj, 7) and takes(mj, 6) and takes(mj, 8)  # 7 = 2 x 4 rounded: the premise
    assert not takes(mj, 32) and takes(ind, 32)  # 32 = 5 x 7 rounded
    assert list(each_pass(pass_sizes(mj, 40, 40))) == [16, 16, 8] and list(each_pass(pass_sizes(ind, 40, 40))) == [32, 8]
    assert pass_sizes(mj, 10**12, 1024) == (1024, 10**12 // 1024, [])  # no list of 1e9 passes
    assert count_at_least(mj, 17) == 64 and count_at_least(ind, 17) == 32 and count_at_least(ind, 7) == 8


def test_a_render_repeats_bit_for_bit():
    """The same scene, seed and sample count render the same bits again, also on several threads:
    with passes of 35 lanes per pixel (multijitter's 32) a pixel straddled two of Dr.Jit's blocks,
    two threads added to it in either order, and 8 of 8 re-renders differed in the last bits
    (athene_flat 64², 64 spp in halves of 32). Vacuous with one Dr.Jit thread."""
    scene = em.load_scene("athene_flat", res=64)
    scene.set_events(1)
    first = scene.render(quality="default", spp=64, seed=5, progress=False).channels
    for _ in range(4):
        again = scene.render(quality="default", spp=64, seed=5, progress=False).channels
        for name, image in first.items():
            assert np.array_equal(image, again[name]), name


def _scene(tmp_path, kind):
    """corrugated_sheet with the given sampler, a 1 mm beam over 4 mm ribs: the signal changes
    inside the spot (as at a pore's rim)."""
    src = scenes_dir()
    text = (src / "corrugated_sheet.xml").read_text().replace('sampler type="multijitter"', f'sampler type="{kind}"')
    for folder in ("layouts", "parts", "meshes"):
        text = text.replace(f'"{folder}/', f'"{(src / folder).as_posix()}/')
    path = Path(tmp_path) / f"corr_{kind}.xml"
    path.write_text(text)
    return em.load_scene(str(path), res=24, fwhm=1.0)


def test_stratified_beam_is_unbiased_and_less_noisy(tmp_path):
    seeds = range(6)
    out = {}
    for kind in ("independent", "multijitter"):
        scene = _scene(tmp_path, kind)
        out[kind] = np.stack([scene.render(spp=16, events=1, seed=s, progress=False).channels["right"]
                              for s in seeds])
        del scene
    ind, mj = out["independent"], out["multijitter"]
    # per-pixel noise: the spread over seeds, pooled over the pixels
    sd_ind = np.sqrt(np.mean(np.var(ind, axis=0, ddof=1)))
    sd_mj = np.sqrt(np.mean(np.var(mj, axis=0, ddof=1)))
    assert sd_mj < 0.75 * sd_ind, (sd_mj, sd_ind)  # measured 0.62x
    # no bias over the image: the totals of the seeds' images agree within 4 standard errors
    tot_ind, tot_mj = ind.sum(axis=(1, 2)), mj.sum(axis=(1, 2))
    z = (tot_mj.mean() - tot_ind.mean()) / np.sqrt(tot_mj.var(ddof=1) / len(seeds) + tot_ind.var(ddof=1) / len(seeds))
    assert abs(z) < 4.0, z
    # nor pixel by pixel: diff^2 over its estimated variance (5 + 5 degrees of freedom) averages
    # about 10/8 = 1.25 for unbiased estimators; 24^2 pixels put the mean's spread near 0.1
    diff = ind.mean(0) - mj.mean(0)
    var = ind.var(0, ddof=1) / len(seeds) + mj.var(0, ddof=1) / len(seeds)
    ok = var > 0
    chi2 = float(np.mean(diff[ok] ** 2 / var[ok]))
    assert chi2 < 1.6, chi2
