"""``elo-mitsuba optimize`` (issue 27): refusals before any work, a run's store, a killed run
resumed without evaluating a design twice, evaluations as Dask tasks, the results."""

import json
import os
import re
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from elo_mitsuba.cli import main
from elo_mitsuba.constants import CHAMBER_INTERIOR_MM, SHEET_BOTTOM_MM, SHEET_Y_MM
from elo_mitsuba.design import store
from elo_mitsuba.design.geometry import CONSTRAINTS
from elo_mitsuba.design.optimize import optimize
from elo_mitsuba.scene_files import scenes_dir

SMALL = """\
count = 4
objectives = ["sigma_worst", "masked_share"]
[parameters]
dh = [100.0, 400.0]
dw = [80.0, 300.0]
radius = 25.0
[metric]
grid = 2
[optimizer]
sampler = "{sampler}"
trials = {trials}
batch = {batch}
"""


def _spec(tmp_path, name="spec.toml", sampler="random", trials=8, batch=4, extra=""):
    p = tmp_path / name
    p.write_text(SMALL.format(sampler=sampler, trials=trials, batch=batch) + extra)
    return p


def _one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("elo-mitsuba: error: ")
    return err[0]


@pytest.mark.parametrize("parameters, words", [
    ("dh = [560.0, 700.0]", "no design within the bounds meets the constraints"),       # above the ceiling
    ("radius = [200.0, 300.0]", "no design within the bounds meets the constraints"),  # discs overlap
    ("dh = [300.0, 100.0]", "low must not exceed high"),
    ("height = 3.0", "'height' is not a key"),
])
def test_impossible_or_bad_specs_are_refused_in_one_line_before_any_work(tmp_path, capsys, parameters, words):
    text = SMALL.format(sampler="tpe", trials=4, batch=2)
    key = parameters.split(" =")[0]
    text = re.sub(rf"^{key} = .*$", parameters, text, flags=re.M) if re.search(rf"^{key} = ", text, re.M) \
        else text.replace("[parameters]\n", f"[parameters]\n{parameters}\n")
    spec = tmp_path / "bad.toml"
    spec.write_text(text)
    out = tmp_path / "out.zarr"
    assert main(["optimize", str(spec), "-o", str(out), "--workers", "0", "--quiet"]) == 2
    line = _one_error_line(capsys)
    assert words in line and str(spec) in line
    assert not out.exists()  # nothing was started


@pytest.mark.parametrize("extra, words", [
    ("[render]\nresolution = 2\nspp = 16\n", "[render] sets the chamber render of the objective e2_share"),
    ("grid_points = 5\n", 'optimizer.grid_points = 5 sets the grid of sampler = "grid" only'),
], ids=["render_without_e2_share", "grid_points_without_grid"])
def test_settings_that_would_not_be_applied_are_refused(tmp_path, capsys, extra, words):
    spec = _spec(tmp_path, trials=2, batch=2, extra=extra)
    out = tmp_path / "out.zarr"
    assert main(["optimize", str(spec), "-o", str(out), "--workers", "0", "--quiet"]) == 2
    line = _one_error_line(capsys)
    assert words in line and str(spec) in line and "recorded but not applied" in line, line
    assert not out.exists()


def test_render_settings_apply_with_their_uses():
    from elo_mitsuba.design.spec import load_spec

    text = SMALL.format(sampler="random", trials=2, batch=2) + "[render]\nresolution = 2\n"
    assert load_spec(tomllib.loads(text), second_event=True).render["resolution"] == 2  # optimize --second-event
    e2 = text.replace('"masked_share"]', '"e2_share"]')
    assert load_spec(tomllib.loads(e2)).render["resolution"] == 2


def _no_memory_limit(monkeypatch):
    import elo_mitsuba.budget as budget

    monkeypatch.setattr(budget, "memory_limit", lambda: (10**15, "available on this machine"))


def _no_store(monkeypatch):
    """Fail the test if the run gets as far as creating its store."""
    def fail(*a, **k):
        pytest.fail("the store was created")

    monkeypatch.setattr(store, "check_store", fail)


def test_a_run_estimated_above_the_limit_is_refused_with_its_estimate(tmp_path, capsys, monkeypatch):
    _no_memory_limit(monkeypatch)
    _no_store(monkeypatch)
    spec = _spec(tmp_path, trials=100_000, batch=8)
    out = tmp_path / "out.zarr"
    t0 = time.perf_counter()
    assert main(["optimize", str(spec), "-o", str(out), "--workers", "0"]) == 2
    line = _one_error_line(capsys)
    assert str(spec) in line and "100000 designs (random, count 4, 2x2 field points" in line, line
    assert "would take about" in line and "days" in line and "--yes" in line and "optimizer.trials" in line, line
    assert not out.exists() and time.perf_counter() - t0 < 30


def test_memory_beyond_what_is_available_is_refused_even_when_forced(tmp_path, monkeypatch):
    import elo_mitsuba.budget as budget
    from elo_mitsuba import EloInputError

    monkeypatch.setattr(budget, "memory_limit", lambda: (2 * 10**9, "available on this machine"))
    _no_store(monkeypatch)
    with pytest.raises(EloInputError, match=r"100000 designs .* needs about 40.2 GB of memory, 2 GB is available"):
        optimize(_spec(tmp_path, trials=100_000), tmp_path / "out.zarr", workers=0, progress=False, force=True)
    assert not (tmp_path / "out.zarr").exists()


def test_force_runs_a_long_estimate_and_a_long_run_gets_its_estimate(tmp_path, capsys, monkeypatch):
    import elo_mitsuba.design.optimize as opt
    from elo_mitsuba import EloInputError

    _no_memory_limit(monkeypatch)
    monkeypatch.setattr(opt, "EVAL_SECONDS_PER_DETECTOR", 3600.0)  # 4 h per design
    spec = _spec(tmp_path, trials=2, batch=2)
    with pytest.raises(EloInputError, match="would take about"):
        optimize(spec, tmp_path / "a.zarr", workers=0, progress=False)
    assert not (tmp_path / "a.zarr").exists()
    s = optimize(spec, tmp_path / "a.zarr", workers=0, progress=False, force=True)
    assert s.evaluated == 2
    assert "note" not in capsys.readouterr().err  # progress=False: no notes either
    monkeypatch.setattr(opt, "EVAL_SECONDS_PER_DETECTOR", 10.0)  # 80 s: over a minute, under the limit
    optimize(spec, tmp_path / "b.zarr", workers=0, progress=True)
    err = capsys.readouterr().err
    assert "elo-mitsuba: note: " in err and "2 designs (random" in err and re.search(r"take about \d+ s ", err), err


def test_a_store_of_another_spec_is_not_replaced(tmp_path, capsys):
    out = tmp_path / "o.zarr"
    optimize(_spec(tmp_path, trials=2, batch=2), out, workers=0, progress=False)
    other = _spec(tmp_path, "other.toml", trials=3, batch=2)
    assert main(["optimize", str(other), "-o", str(out), "--workers", "0", "--quiet"]) == 2
    assert "another spec" in _one_error_line(capsys)
    (tmp_path / "plain.zarr").mkdir()
    assert main(["optimize", str(other), "-o", str(tmp_path / "plain.zarr"), "--workers", "0"]) == 2
    assert "not an optimiser's store" in _one_error_line(capsys)


def test_every_evaluated_design_is_stored_with_its_front(tmp_path):
    out = tmp_path / "o.zarr"
    s = optimize(_spec(tmp_path, sampler="tpe", trials=10, batch=5), out, workers=0, progress=False)
    assert (s.evaluated, s.trials, s.state) == (10, 10, "created")
    ds = store.read_designs(out)
    assert ds.sizes["design"] == 10 and sorted(ds.design.values) == list(range(10))
    viol = np.stack([ds[f"violation_{c}"].values for c in CONSTRAINTS])
    assert np.array_equal(ds.feasible.values, viol.max(axis=0) <= 0)
    # the front: feasible, and no feasible design better in both objectives
    v = np.stack([ds.sigma_worst.values, ds.masked_share.values], axis=-1)
    for i in np.flatnonzero(ds.pareto.values):
        better = np.all(v <= v[i], axis=1) & np.any(v < v[i], axis=1) & ds.feasible.values
        assert not better.any()
    assert ds.pareto.sum() >= 1
    # the discs are the parameters': Table 1's kind, facing the origin
    c = ds.disc_center.values[0]
    assert np.allclose(c[:, 2], ds.dh.values[0]) and np.allclose(np.hypot(c[:, 0], c[:, 1]), ds.dw.values[0])
    assert np.all(np.isfinite(ds.sigma_worst.values))
    # the same command again: nothing left to evaluate
    again = optimize(_spec(tmp_path, sampler="tpe", trials=10, batch=5), out, workers=0, progress=False)
    assert (again.evaluated, again.state) == (0, "resumed")


def test_a_killed_run_resumes_without_evaluating_a_design_twice(tmp_path):
    spec = _spec(tmp_path, sampler="tpe", trials=24, batch=2)
    out = tmp_path / "o.zarr"
    log = out / ".optimize" / "evaluations.jsonl"
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    proc = subprocess.Popen([sys.executable, "-m", "elo_mitsuba", "optimize", str(spec), "-o", str(out), "--workers", "0",
                             "--quiet"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = time.time()
    while time.time() - t0 < 60 and (not log.is_file() or len(log.read_text().splitlines()) < 6):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    before = [json.loads(x)["trial"] for x in log.read_text().splitlines() if x.strip()]
    assert 6 <= len(before) < 24, len(before)  # killed mid-way
    s = optimize(spec, out, workers=0, progress=False)
    after = [r["trial"] for r in store.read_records(out)]
    assert len(after) == len(set(after)) == 24  # every design once: none evaluated again
    assert s.evaluated == 24 - len(before)  # the logged ones are told, not evaluated
    assert s.state == "resumed" and store.read_designs(out).sizes["design"] == 24


def test_evaluations_run_as_tasks_on_a_dask_cluster(tmp_path):
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        s = optimize(_spec(tmp_path, trials=4, batch=4), tmp_path / "o.zarr", scheduler=cluster.scheduler_address,
                     progress=False)
    assert s.evaluated == 4
    assert np.all(store.read_designs(tmp_path / "o.zarr").seconds.values > 0)


def test_results_plot_scene_and_table1(tmp_path, capsys):
    spec = _spec(tmp_path, trials=6, batch=3, extra="[render]\nresolution = 2\nspp = 16\n")
    out, png, xml = tmp_path / "o.zarr", tmp_path / "front.png", tmp_path / "best.xml"
    assert main(["optimize", str(spec), "-o", str(out), "--workers", "0", "--quiet", "--plot", str(png),
                 "--scene", str(xml), "--second-event"]) == 0
    text = capsys.readouterr().out
    shares = re.search(r"2nd-event share .*: (.*)$", text, re.M).group(1)
    assert "zeta25" in shares and "zeta75" in shares
    for z in ("zeta25", "zeta50", "zeta60", "zeta75"):
        assert z in text
    assert png.read_bytes()[:4] == b"\x89PNG" and "<shape type=\"disk\"" in xml.read_text()
    # an existing plot is not replaced without --overwrite, and nothing runs
    assert main(["optimize", str(spec), "-o", str(out), "--workers", "0", "--plot", str(png), "--second-event"]) == 2
    assert str(png) in _one_error_line(capsys)
    # without --second-event (or the objective e2_share) the spec's [render] would not be used
    assert main(["optimize", str(spec), "-o", str(out), "--workers", "0"]) == 2
    assert "[render] sets the chamber render" in _one_error_line(capsys)


def test_the_chamber_constants_are_the_scene_files():
    text = (scenes_dir() / "parts" / "chamber.xml").read_text()
    origins = dict(re.findall(r'id="(\w+)">\s*<transform name="to_world">\s*<scale [^>]*/>\s*<lookat origin="([^"]+)"', text))
    xyz = {k: [float(v) for v in o.split(",")] for k, o in origins.items()}
    (x0, x1), (y0, y1), (z0, z1) = CHAMBER_INTERIOR_MM
    assert xyz["wall_right"][0] == x1 and xyz["wall_left"][0] == x0
    assert xyz["wall_back"][1] == y1 and xyz["wall_front"][1] == y0 and xyz["ceiling_back"][2] == z1
    assert xyz["sheet_front"][1] == SHEET_Y_MM[0] and xyz["sheet_back"][1] == SHEET_Y_MM[1]
    assert xyz["sheet_front"][2] - 115 == SHEET_BOTTOM_MM


def test_designs_stored_but_not_told_are_told_from_the_log(tmp_path, monkeypatch):
    """The narrowest kill: after a batch reached the log, before the optimiser was told."""
    spec = _spec(tmp_path, sampler="tpe", trials=8, batch=4)
    out = tmp_path / "o.zarr"
    real = store.append_records

    def append_then_die(path, records):
        real(path, records)
        raise KeyboardInterrupt  # as a kill right after the write

    monkeypatch.setattr(store, "append_records", append_then_die)
    with pytest.raises(KeyboardInterrupt):
        optimize(spec, out, workers=0, progress=False)
    monkeypatch.setattr(store, "append_records", real)
    assert len(store.read_records(out)) == 4
    s = optimize(spec, out, workers=0, progress=False)
    assert (s.recovered, s.evaluated) == (4, 4)
    trials = [r["trial"] for r in store.read_records(out)]
    assert sorted(trials) == list(range(8))


def test_asymmetric_designs_of_a_chosen_count(tmp_path):
    spec = _spec(tmp_path, trials=6, batch=3).read_text().replace("count = 4", "count = [3, 5]\nsymmetric = false")
    spec = spec.replace("[parameters]\n", "[parameters]\nazimuth = [-10.0, 10.0]\n")
    path = tmp_path / "asym.toml"
    path.write_text(spec)
    optimize(path, tmp_path / "o.zarr", workers=0, progress=False)
    ds = store.read_designs(tmp_path / "o.zarr")
    assert set(ds["count"].values) <= {3, 5} and ds.sizes["slot"] == 5
    for i in range(ds.sizes["design"]):
        k = int(ds["count"].values[i])
        assert np.isfinite(ds.disc_radius.values[i, :k]).all() and np.isnan(ds.disc_radius.values[i, k:]).all()
        # each detector its own height: per-detector parameters, the ones beyond the count NaN
        h = [ds[f"dh_{j}"].values[i] for j in range(5)]
        assert np.allclose(ds.disc_center.values[i, :k, 2], h[:k]) and np.isnan(h[k:]).all()


def test_the_second_event_objective_renders_the_chamber(tmp_path):
    spec = _spec(tmp_path, trials=2, batch=2, extra="[render]\nresolution = 2\nspp = 16\n")
    spec.write_text(spec.read_text().replace('objectives = ["sigma_worst", "masked_share"]',
                                             'objectives = ["sigma_worst", "e2_share"]'))
    optimize(spec, tmp_path / "o.zarr", workers=0, progress=False)
    ds = store.read_designs(tmp_path / "o.zarr")
    e2 = ds.e2_share.values
    assert ds.feasible.values.any()
    assert np.all((e2 > 0) & (e2 < 0.5) | ~ds.feasible.values) and np.all(e2[~ds.feasible.values] == 1.0)


def test_the_grid_sampler_visits_every_grid_point_once(tmp_path):
    spec = _spec(tmp_path, sampler="grid", trials=100, batch=3, extra="")
    spec.write_text(spec.read_text().replace("batch = 3", "batch = 3\ngrid_points = 2"))
    s = optimize(spec, tmp_path / "o.zarr", workers=0, progress=False)
    ds = store.read_designs(tmp_path / "o.zarr")
    pairs = sorted(zip(ds.dh.values.tolist(), ds.dw.values.tolist()))
    assert s.evaluated == 4 and pairs == [(100.0, 80.0), (100.0, 300.0), (400.0, 80.0), (400.0, 300.0)]
