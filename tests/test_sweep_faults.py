"""Design sweeps under bad input and faults (issue 23): every point's values checked before the
store exists, unbounded work refused with its estimate, cluster faults bounded in time, stores
created exclusively and resumed without rendering a point twice, damaged stores and bad arguments
answered in one line, and the determinism the README states.

Clusters are started here on 127.0.0.1 (a scheduler and one ``dask worker`` without nanny, so a
killed worker stays dead) and killed at the end of each test that needs one; resolutions are
16-64 px so that the whole file stays well under two minutes on two cores.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from elo_mitsuba.cli import main
from elo_mitsuba.scene_files import portable_scene_text, scenes_dir

xr = pytest.importorskip("xarray")
pytest.importorskip("distributed")

FLAT = 'scene = "flat_plate"\n'
SMALL = "[render]\nresolution = 16\n"


def _cli(*args) -> int:
    return main([str(a) for a in args])


def _spec(tmp_path, text, name="s.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("elo-mitsuba: error: "), err
    assert "Traceback" not in err
    return err


@pytest.fixture
def no_render(monkeypatch):
    """Fail the test if any point starts rendering (in process) or a local cluster starts."""
    import elo_mitsuba.sweeps.run as run
    import elo_mitsuba.sweeps.worker as worker

    def fail(*a, **k):
        pytest.fail("a render started")

    real_connect = run.connect

    def connect(address, workers):
        if address is None:
            pytest.fail("a local cluster started")
        return real_connect(address, workers)

    monkeypatch.setattr(run, "connect", connect)
    monkeypatch.setattr(worker, "run_batch", fail)
    monkeypatch.setattr(run, "run_batch", fail)
    monkeypatch.setattr(worker, "render_point", fail)


# ---- 3: every point validated, before the store exists ------------------------------------------
BAD_POINTS = {
    "dh_second": (FLAT + "[vary]\ndh = [200, -50]\n" + SMALL, "dh = -50", "below the build plane"),
    "layout_second": ('scene = "corrugated_sheet"\n[vary]\nlayout = ["zeta25", "zeta99"]\n' + SMALL,
                      "layout = 'zeta99'", "allowed: zeta25"),
    "material_second": (FLAT + '[vary]\nmaterial = ["316L", "unobtainium"]\n' + SMALL,
                        "material = 'unobtainium'", "unknown material"),
    "fwhm_second": (FLAT + "[vary]\nfwhm = [0.1, -1]\n" + SMALL, "fwhm = -1", "must be 0 (a single ray) or 1e-06 to 1e+06 mm"),
    "zipped_second": (FLAT + "[zip.g]\ndh = [272, 20]\ndw = [127, 300]\n" + SMALL, "dh = 20", "detector"),
    "center_second": (FLAT + "[vary]\nright.center = [[127, 0, 272], [127, 0, -10]]\n" + SMALL,
                      "right.center = [127.0, 0.0, -10.0]", "at or below the build plane"),
    "normal_second": (FLAT + "[vary]\nright.normal = [[-1, 0, -1], [1, 0, 1]]\n" + SMALL,
                      "right.normal = [1.0, 0.0, 1.0]", "faces away"),
    "centre_onto_another": (FLAT + "[vary]\nright.center = [[127, 0, 272], [0, 127, 272]]\n" + SMALL,
                            "right.center = [0.0, 127.0, 272.0]", "detectors 'right' and 'back' intersect"),
    "radius_through_plate": (FLAT + "[vary]\nright.center = [[127, 0, 272], [300, 0, 30]]\nright.radius = [20, 60]\n"
                             + SMALL, "right.radius = 60", "through the build plane"),
    "events_nan": (FLAT + "[vary]\ndh = [200]\n[render]\nevents = nan\n", "render.events = nan", "whole number"),
    "events_inf": (FLAT + "[vary]\ndh = [200]\n[render]\nevents = inf\n", "render.events = inf", "whole number"),
    "seed_nan": (FLAT + "seed = nan\n[vary]\ndh = [200]\n", "seed = nan", "whole number"),
    "vary_events_second": (FLAT + "[vary]\nevents = [1, 11]\n" + SMALL, "vary.events = 11", "[1, 10]"),
    "dh_nan": (FLAT + "[vary]\ndh = [200, nan]\n" + SMALL, "vary.dh: value nan", "finite"),
    "surface_contradicts_scene": (FLAT + "[vary]\ndh = [200]\n" + SMALL + '[surface]\nobject = "corrugated_sheet"\n',
                                  "surface.object = 'corrugated_sheet' contradicts the scene flat_plate.xml",
                                  "no relief"),
    "surface_flat_not_flat": ('scene = "corrugated_sheet"\n[vary]\ndh = [272]\n' + SMALL
                              + '[surface]\nobject = "corrugated_sheet"\nflat = "melt_plate"\n',
                              "surface.flat = 'melt_plate' is not flat", "relief melt_plate"),
    "surface_flat_unknown": ('scene = "corrugated_sheet"\n[vary]\ndh = [272]\n' + SMALL
                             + '[surface]\nobject = "corrugated_sheet"\nflat = "flat_plat"\n',
                             "surface.flat = 'flat_plat'", "neither an XML file nor a shipped scene"),
    "height_map_corrupt": ('scene = "corrugated_sheet"\n[vary]\ndh = [272]\n' + SMALL
                           + '[surface]\nheight_map = "h.npy"\npixel_mm = 0.1\n', "surface.height_map", "could not be read"),
    "height_map_pixel_inf": ('scene = "corrugated_sheet"\n[vary]\ndh = [272]\n' + SMALL
                             + '[surface]\nheight_map = "good.npy"\npixel_mm = inf\n', "surface.pixel_mm = inf", "> 0"),
    "beam_current_without_volts": (FLAT + "[vary]\ndh = [200]\n" + SMALL + "[integrator]\nbeam_current = 1e-3\n",
                                   "beam_current", "add units='voltage'"),
    "detector_samples_with_preset": (FLAT + "[vary]\ndh = [200]\n" + SMALL + "[integrator]\ndetector_samples = 4\n",
                                     "integrator.detector_samples=4 would change nothing", "quadrature"),
    # options a quality preset sets: the preset is applied over them at every point
    "detector_sampling_with_preset": (FLAT + "[vary]\ndh = [200]\n" + SMALL + 'quality = "draft"\n[integrator]\n'
                                      'detector_sampling = "stratified"\n',
                                      "integrator.detector_sampling='stratified' would change nothing",
                                      "render.quality 'draft' sets detector_sampling itself"),
    "quadrature_triangles_with_default_preset": (FLAT + "[vary]\ndh = [200]\n" + SMALL
                                                 + "[integrator]\nquadrature_triangles = 64\n",
                                                 "integrator.quadrature_triangles=64 would change nothing",
                                                 "render.quality 'default' (the default) sets quadrature_triangles"),
    "bounce_filter_with_swept_preset": (FLAT + '[vary]\nquality = ["scene", "reference"]\n' + SMALL
                                        + "[integrator]\nbounce_filter = 0.5\n",
                                        "integrator.bounce_filter=0.5 would change nothing",
                                        "the swept quality 'reference' sets bounce_filter"),
    "events_in_integrator": (FLAT + "[vary]\ndh = [200]\n" + SMALL + 'quality = "scene"\n[integrator]\nevents = 2\n',
                             "integrator.events=2 would change nothing", "set [render] events = 2"),
}


@pytest.mark.parametrize("case", sorted(BAD_POINTS))
def test_every_point_is_checked_before_the_store_exists(case, tmp_path, capsys, no_render):
    text, where, what = BAD_POINTS[case]
    (tmp_path / "h.npy").write_bytes(b"not a numpy file")
    np.save(tmp_path / "good.npy", np.zeros((8, 8)))
    spec = _spec(tmp_path, text)
    out = tmp_path / "out.zarr"
    t0 = time.perf_counter()
    assert _cli("sweep", spec, "-o", out, "--workers", "0") == 2
    err = _one_line_error(capsys)
    assert str(spec) in err and where in err and what in err, err
    assert not out.exists() and not list(tmp_path.glob(".out.zarr*"))
    assert time.perf_counter() - t0 < 30


def test_integrator_options_apply_with_the_scene_quality():
    """Under render.quality = "scene" no preset is applied over [integrator]: its sampling
    options are accepted (and each point renders with them)."""
    from elo_mitsuba.sweeps import load_spec

    spec = load_spec(FLAT + "[vary]\ndh = [200]\n" + SMALL + 'quality = "scene"\n[integrator]\n'
                     'detector_sampling = "stratified"\nquadrature_triangles = 64\n')
    assert spec.integrator == {"detector_sampling": "stratified", "quadrature_triangles": 64}


def test_valid_values_in_every_position_pass(tmp_path):
    """The checks load each load-time value and apply each move without rendering; a valid
    spec with several of each is accepted (and then renders)."""
    import elo_mitsuba.sweeps.validate as validate
    from elo_mitsuba.sweeps import load_spec

    spec = load_spec(FLAT + "[vary]\ndh = [200, 250, 272]\nright.center = [[127, 0, 272], [150, 0, 250]]\n"
                     "right.radius = [15, 25]\n" + SMALL)
    probe = validate.check_first_point(spec)
    validate.check_points(spec)
    assert probe.detector_geometry()["right"]["center"][2] == pytest.approx(200.0)  # dh of point 0, not moved


# ---- 1: unbounded work refused with its estimate ----------------------------------------------------
def test_unbounded_sweeps_are_refused_with_their_estimate(tmp_path, capsys, no_render):
    spec = _spec(tmp_path, FLAT + "[vary]\ndh = [200, 272]\n[render]\nresolution = 64\nspp = 1e9\n")
    out = tmp_path / "big.zarr"
    assert _cli("sweep", spec, "-o", out, "--workers", "0") == 2
    err = _one_line_error(capsys)
    assert "days on this machine" in err and "of memory" in err and "a store of" in err and "--yes" in err, err
    assert not out.exists()
    # 10^6 points: refused in seconds, before the store (minutes and GB to create) exists
    radii = ", ".join(f"{10 + k * 0.01:.2f}" for k in range(1000))
    heights = ", ".join(f"{200 + k * 0.05:.2f}" for k in range(1000))
    spec = _spec(tmp_path, FLAT + f"[vary]\nright.radius = [{radii}]\ndh = [{heights}]\n" + SMALL, "million.toml")
    t0 = time.perf_counter()
    assert _cli("sweep", spec, "-o", out, "--workers", "0") == 2
    err = _one_line_error(capsys)
    assert "1000000 points" in err and "files" in err and "--yes" in err, err
    assert time.perf_counter() - t0 < 20 and not out.exists()


def test_force_passes_the_estimate(tmp_path, monkeypatch):
    """force=True (--yes) runs what the estimate refuses; memory and disk stay refused."""
    import elo_mitsuba.sweeps.cost as cost
    import elo_mitsuba.sweeps.run as run
    from elo_mitsuba import EloInputError, sweep

    monkeypatch.setattr(run, "run_batch", lambda store, job, batch: [])
    spec = FLAT + "[vary]\ndh = [200, 272]\n[render]\nresolution = 16\nspp = 1e9\n"
    with pytest.raises(EloInputError, match="refused as likely a mistake"):
        sweep(spec, tmp_path / "a.zarr", workers=0, progress=False)
    s = sweep(spec, tmp_path / "a.zarr", workers=0, progress=False, force=True)
    assert s.state == "created" and s.done == 0
    monkeypatch.setattr(cost, "CREATE_BYTES_PER_POINT", 1e30)
    with pytest.raises(EloInputError, match="of memory is"):
        sweep(spec, tmp_path / "b.zarr", workers=0, progress=False, force=True)
    assert not (tmp_path / "b.zarr").exists()


# ---- 4 and 9: arguments and the scheduler, before the store exists --------------------------------
BAD_ARGUMENTS = {
    "workers_text": ({"workers": "2"}, "workers='2'"),
    "workers_many": ({"workers": 64}, "workers=64; this machine has"),
    "workers_negative": ({"workers": -1}, "workers=-1"),
    "threads_many": ({"workers": 1, "threads_per_worker": 1_000_000}, "threads per worker 1000000"),
    "output_none": ({"output": None}, "output None"),
    "output_number": ({"output": 3}, "output 3"),
    "scheduler_missing_file": ({"scheduler": "{tmp}/nope.json"}, "cannot read it"),
    "scheduler_garbage_file": ({"scheduler": "{tmp}/garbage.json"}, "not JSON"),
    "scheduler_no_address": ({"scheduler": "{tmp}/empty.json"}, 'no "address"'),
    "scheduler_malformed": ({"scheduler": "tcp://127.0.0.1"}, "not an address of the form"),
    "scheduler_bad_port": ({"scheduler": "tcp://127.0.0.1:99999"}, "not an address of the form"),
    # nothing listens on port 9: refused at once (Dask's client retried for its 10 s timeout)
    "scheduler_unreachable": ({"scheduler": "tcp://127.0.0.1:9"},
                              "cannot reach the Dask scheduler tcp://127.0.0.1:9: nothing listens there"),
    "worker_wait": ({"worker_wait_s": -1}, "worker_wait_s=-1"),
    # an infinite wait reached Dask, which gave up at once, after the store was made
    "worker_wait_inf": ({"worker_wait_s": float("inf")}, "worker_wait_s=inf (--worker-wait); must be a number"),
    "worker_wait_nan": ({"worker_wait_s": float("nan")}, "worker_wait_s=nan"),
    "worker_wait_year": ({"worker_wait_s": 3.2e7}, "at most 604800 (a week)"),
}


@pytest.mark.parametrize("case", sorted(BAD_ARGUMENTS))
def test_bad_arguments_are_one_line_within_seconds(case, tmp_path, no_render):
    from elo_mitsuba import EloInputError, sweep

    (tmp_path / "garbage.json").write_bytes(b"\x00\xffgarbage{")
    (tmp_path / "empty.json").write_text("{}")
    kwargs, expected = BAD_ARGUMENTS[case]
    kwargs = {k: v.format(tmp=tmp_path) if isinstance(v, str) else v for k, v in kwargs.items()}
    output = kwargs.pop("output", tmp_path / "out.zarr")
    t0 = time.perf_counter()
    with pytest.raises(EloInputError) as info:
        sweep(FLAT + "[vary]\ndh = [200, 272]\n" + SMALL, output, progress=False, **kwargs)
    message = str(info.value)
    assert "\n" not in message and expected in message, message
    assert time.perf_counter() - t0 < (5 if case == "scheduler_unreachable" else 20)
    assert not list(tmp_path.glob("*.zarr")) and not list(tmp_path.glob(".*.zarr*"))


def test_cli_caps_workers_and_threads(tmp_path, capsys, no_render):
    spec = _spec(tmp_path, FLAT + "[vary]\ndh = [200]\n" + SMALL)
    for flags, expected in ((["--workers", "64"], "workers=64"), (["--threads", "1000000"], "threads per worker")):
        assert _cli("sweep", spec, "-o", tmp_path / "o.zarr", *flags) == 2
        assert expected in _one_line_error(capsys)
    assert not (tmp_path / "o.zarr").exists()


# ---- 9: a damaged store on resume -------------------------------------------------------------------
def _small_store(tmp_path, name="r.zarr", extra=""):
    from elo_mitsuba import sweep

    spec = FLAT + "[vary]\ndh = [200, 272]\n[render]\nresolution = 16\nspp = 1\n" + extra
    out = tmp_path / name
    s = sweep(spec, out, workers=0, progress=False)
    assert s.done == 2
    return spec, out


def test_a_corrupt_status_chunk_is_one_line(tmp_path, capsys):
    spec, out = _small_store(tmp_path)
    path = _spec(tmp_path, spec)
    (out / "status" / "1").write_bytes(b"\x00garbage\xff" * 3)
    assert _cli("sweep", path, "-o", out, "--workers", "0", "--no-progress") == 2
    err = _one_line_error(capsys)
    assert "status" in err and "point [1]" in err and "damaged" in err and "--overwrite" in err, err
    # a status value outside 0/1/2
    import zarr

    (out / "status" / "1").unlink()
    zarr.open_group(str(out), mode="r+")["status"][0] = 7
    assert _cli("sweep", path, "-o", out, "--workers", "0", "--no-progress") == 2
    assert "point [0] has status 7" in _one_line_error(capsys)


def test_sweep_plot_select_is_checked(tmp_path, capsys):
    _, out = _small_store(tmp_path)
    png = tmp_path / "p.png"
    for select, expected in (("wd=123", "wd is not swept"), ("dh=201", "not a value of the sweep; dh takes 200, 272"),
                             ("dh=abc", "not a value of the sweep")):
        assert _cli("sweep-plot", out, "signal_mean", "-o", png, "--select", select) == 2
        assert expected in _one_line_error(capsys)
    assert not png.exists()
    assert _cli("sweep-plot", out, "signal_spread", "-o", png, "--detector", "right") == 0


# ---- 7: the signal's units from the render metadata ------------------------------------------------
def test_a_voltage_sweep_labels_the_signal_in_volts(tmp_path):
    _, out = _small_store(tmp_path, "v.zarr", '[integrator]\nunits = "voltage"\n')
    ds = xr.open_zarr(out)
    assert ds["signal_mean"].attrs["units"] == "V"
    assert json.loads(ds.attrs["scan_geometry"])["units"] == "V"
    assert ds["signal_spread"].attrs["units"] == "1"
    _, out = _small_store(tmp_path, "f.zarr")
    assert xr.open_zarr(out)["signal_mean"].attrs["units"] == "N_d/N_0"


# ---- 4: exclusive creation and claims ---------------------------------------------------------------
def test_two_clients_creating_one_store(tmp_path, monkeypatch):
    """Exactly one creates it: the other finds it created meanwhile and joins (same spec) or is
    told (another spec); nothing half-made is left."""
    import elo_mitsuba.sweeps.store as store
    from elo_mitsuba import EloInputError
    from elo_mitsuba.sweeps import load_spec

    out = tmp_path / "race.zarr"
    spec_a = load_spec(FLAT + "[vary]\ndh = [200, 272]\n" + SMALL)
    spec_b = load_spec(FLAT + "[vary]\ndh = [200, 250]\n" + SMALL)
    layout = {"metrics": {}, "detectors": ["right"], "channels": [], "image_shape": (16, 16),
              "pixel_axes": None, "units": "N_d/N_0", "geometry": {}}
    real = store._create

    def racing(path, spec, lay):  # another client creates the store while this one builds its own
        real(path, spec, lay)
        monkeypatch.setattr(store, "_create", real)
        assert store.open_or_create(out, spec_a, layout) == "created"

    monkeypatch.setattr(store, "_create", racing)
    assert store.open_or_create(out, spec_a, layout) == "joined"
    monkeypatch.setattr(store, "_create", racing)
    out = tmp_path / "race2.zarr"  # now the other client creates this one, for spec_a
    with pytest.raises(EloInputError, match="created meanwhile by another client for another spec"):
        store.open_or_create(out, spec_b, layout)
    assert not [p for p in tmp_path.iterdir() if ".creating-" in p.name]


def test_claims_keep_two_clients_apart(tmp_path):
    from elo_mitsuba.sweeps.claims import Claims

    (tmp_path / "s.zarr").mkdir()
    a, b = Claims(tmp_path / "s.zarr"), Claims(tmp_path / "s.zarr")
    mine_a, others = a.claim(range(4))
    assert mine_a == [0, 1, 2, 3] and not others
    mine_b, others = b.claim(range(6))
    assert mine_b == [4, 5] and others == {a.id: 4}
    a.release()
    assert b.claim(range(4))[0] == [0, 1, 2, 3]
    b.release()
    # a claim of a client that died is taken over
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    c = Claims(tmp_path / "s.zarr")
    c.owner_file.write_text(json.dumps({"host": c.host, "pid": pid, "started": 0}))
    assert c.claim([7])[0] == [7]
    d = Claims(tmp_path / "s.zarr")
    assert d.claim([7, 8])[0] == [7, 8]
    assert sorted(p.name for p in (tmp_path / "s.zarr" / ".claims").iterdir() if not p.name.startswith("client-")) \
        == ["7", "8"]


def test_two_clients_resuming_render_each_point_once(tmp_path):
    """Two processes start the same sweep on one new store at once: one creates it, every point
    is rendered once (the rendered counts add up to the points)."""
    spec = _spec(tmp_path, FLAT + "[vary]\nright.radius = [16, 18, 20, 22, 24, 26]\n[render]\nresolution = 64\n"
                 "quality = \"scene\"\nspp = 16\n")
    out = tmp_path / "two.zarr"
    cmd = [sys.executable, "-m", "elo_mitsuba", "sweep", str(spec), "-o", str(out), "--workers", "0", "--no-progress"]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    lines = [o[0] for o in outs]
    assert sum("(created)" in line for line in lines) == 1, lines
    rendered = [int(line.split("; ")[1].split(" rendered")[0]) for line in lines]
    assert sum(rendered) == 6, lines
    ds = xr.open_zarr(out)
    assert (ds["status"].values == 1).all()
    assert not [p for p in (out / ".claims").iterdir()]  # every claim released


# ---- 5: determinism -------------------------------------------------------------------------------
def test_a_point_does_not_depend_on_what_the_worker_rendered_before():
    """A worker's cached scene whose detector an earlier sweep moved (and this point does not)
    is loaded afresh: the point equals a direct render bit for bit (put back from its float32
    copy it differs by ~2e-7)."""
    import elo_mitsuba as em
    from elo_mitsuba.sweeps import worker

    fresh = em.load_scene("flat_plate", res=32).render(spp=3, seed=1, quality="scene", events=2).channels["right"]
    ls = worker._scene("flat_plate", {"res": 32}, {}, {"right": {"radius": 30.0}})
    ls.prepare({"right": {"radius": 30.0}})
    ls.scene.render(spp=8, seed=5, quality="default")
    ls = worker._scene("flat_plate", {"res": 32}, {}, {})
    ls.prepare({})
    again = ls.scene.render(spp=3, seed=1, quality="scene", events=2).channels["right"]
    np.testing.assert_array_equal(again, fresh)
    # the scene file's sampler count survives a render with another spp (render.py keeps it)
    ls.scene.render(spp=5, seed=1, quality="scene")
    np.testing.assert_array_equal(ls.scene.render(seed=2, quality="scene", events=2).channels["right"],
                                  em.load_scene("flat_plate", res=32).render(seed=2, quality="scene",
                                                                             events=2).channels["right"])


def test_a_render_does_not_depend_on_the_thread_count():
    """The same render with 1 and 2 Dr.Jit threads (and 3, more than the cores), spp not a power
    of two so that a pixel's samples straddle the threads' blocks: bit for bit equal."""
    import drjit as dr

    import elo_mitsuba as em

    scene = em.load_scene("flat_plate", res=64)
    before = dr.thread_count()
    images = []
    try:
        for threads in (1, 2, 3):
            dr.set_thread_count(threads)
            images.append(scene.render(spp=3, seed=4, events=2, quality="scene").channels["right"])
    finally:
        dr.set_thread_count(before)
    np.testing.assert_array_equal(images[0], images[1])
    np.testing.assert_array_equal(images[0], images[2])


# ---- 4: a real cluster losing its workers or its scheduler ----------------------------------------
def _start_cluster(tmp: Path, n_workers: int):
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    sched_file = tmp / "scheduler.json"
    procs = {"scheduler": subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
         "--no-dashboard", "--scheduler-file", str(sched_file)],
        stdout=subprocess.DEVNULL, stderr=open(tmp / "scheduler.log", "w"), env=env)}
    deadline = time.time() + 60
    while not sched_file.is_file() and time.time() < deadline:
        time.sleep(0.1)
    assert sched_file.is_file(), (tmp / "scheduler.log").read_text()
    for k in range(n_workers):
        procs[f"w{k}"] = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file", str(sched_file),
             "--nthreads", "1", "--no-nanny", "--host", "127.0.0.1", "--no-dashboard", "--name", f"w{k}"],
            stdout=subprocess.DEVNULL, stderr=open(tmp / f"w{k}.log", "w"), env=env)
    if n_workers:
        from distributed import Client

        with Client(scheduler_file=str(sched_file), timeout="30s") as c:
            c.wait_for_workers(n_workers, timeout=90)
    return sched_file, procs


def _stop(procs):
    for p in procs.values():
        if p.poll() is None:
            p.kill()
            p.wait(timeout=30)


SLOW = FLAT + "[vary]\nright.radius = [16, 18, 20, 22, 24, 26, 28, 30, 32, 34, 36, 38]\n[render]\nresolution = 96\n" \
    "quality = \"scene\"\nspp = 48\n"


def _kill_after_points(tmp_path, sched_file, victim, extra=()):
    """Run the SLOW sweep through the scheduler in a subprocess; kill ``victim`` once 2 points
    are stored; returns (returncode, stdout, stderr, seconds after the kill, status array)."""
    import zarr

    spec = _spec(tmp_path, SLOW, "slow.toml")
    out = tmp_path / "slow.zarr"
    cmd = [sys.executable, "-m", "elo_mitsuba", "sweep", str(spec), "-o", str(out), "--scheduler", str(sched_file),
           "--no-progress", *extra]
    run = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 120
        while time.time() < deadline:
            if (out / "status" / ".zarray").is_file():
                if (np.asarray(zarr.open_group(str(out), mode="r")["status"][...]) == 1).sum() >= 2:
                    break
            time.sleep(0.05)
        victim.send_signal(signal.SIGKILL)
        victim.wait(timeout=30)
        t_kill = time.perf_counter()
        stdout, stderr = run.communicate(timeout=120)
        after = time.perf_counter() - t_kill
    finally:
        if run.poll() is None:
            run.kill()
    return run.returncode, stdout, stderr, after, np.asarray(zarr.open_group(str(out), mode="r")["status"][...])


def test_all_workers_lost_stops_within_the_wait(tmp_path):
    sched_file, procs = _start_cluster(tmp_path, 1)
    try:
        rc, stdout, stderr, after, status = _kill_after_points(tmp_path, sched_file, procs["w0"],
                                                               ("--worker-wait", "3"))
    finally:
        _stop(procs)
    assert rc == 2, stderr
    assert stderr.count("\n") == 1 and "every worker of the Dask scheduler" in stderr and "within 3 s" in stderr, stderr
    assert "re-run the same command to resume" in stderr
    assert after < 20, after
    assert (status == 1).sum() >= 2 and not (status == 2).any(), status  # nothing recorded as failed


def test_scheduler_lost_keeps_what_finished(tmp_path):
    sched_file, procs = _start_cluster(tmp_path, 1)
    try:
        rc, stdout, stderr, after, status = _kill_after_points(tmp_path, sched_file, procs["scheduler"])
    finally:
        _stop(procs)
    assert rc == 2, stderr
    assert stderr.count("\n") == 1 and "was lost" in stderr and "points are stored" in stderr, stderr
    assert after < 30, after
    assert (status == 1).sum() >= 2 and not (status == 2).any(), status  # done stay done, none failed


def test_a_scheduler_without_workers_is_one_line(tmp_path, capsys):
    sched_file, procs = _start_cluster(tmp_path, 0)
    try:
        spec = _spec(tmp_path, FLAT + "[vary]\ndh = [200]\n" + SMALL)
        t0 = time.perf_counter()
        assert _cli("sweep", spec, "-o", tmp_path / "n.zarr", "--scheduler", sched_file, "--worker-wait", "2",
                    "--no-progress") == 2
        err = _one_line_error(capsys)
        assert "no worker joined the Dask scheduler" in err and "within 2 s" in err, err
        assert time.perf_counter() - t0 < 30
    finally:
        _stop(procs)


def test_a_scenes_own_sampling_under_a_preset_is_refused_with_the_spec(tmp_path, capsys, no_render):
    """The scene file sets detector_sampling and detector_samples, the sweep renders at a preset:
    every point would have rendered the preset's quadrature instead (render refuses it; so does
    the spec's check, before the store exists)."""
    text = portable_scene_text(scenes_dir() / "flat_plate.xml").replace(
        '<integer name="events" value="$events"/>', '<integer name="events" value="$events"/><string '
        'name="detector_sampling" value="stratified"/><integer name="detector_samples" value="16"/>', 1)
    assert 'name="detector_samples"' in text
    (tmp_path / "own.xml").write_text(text)
    spec = _spec(tmp_path, 'scene = "own.xml"\n[vary]\ndh = [200]\n[render]\nresolution = 4\nquality = "draft"\n')
    out = tmp_path / "out.zarr"
    assert _cli("sweep", spec, "-o", out, "--workers", "0") == 2
    assert ("sets detector_sampling='stratified', detector_samples=16, which quality 'draft' would override"
            in _one_line_error(capsys))
    assert not out.exists()


def test_detectors_the_presets_cannot_integrate_are_refused_with_the_spec(tmp_path, capsys, no_render):
    """A sphere detector under a quality preset (whose triangle quadrature takes discs, rectangles
    and meshes): the spec passed, the store was created and every point failed (exit 1)."""
    disc = ('<shape type="{t}" id="{n}"><transform name="to_world"><scale value="25"/><rotate x="1" angle="180"/><translate x="{x}" y="{y}" '
            'z="$dh"/></transform><emitter type="area"/></shape>')
    shapes = "".join(disc.format(t="sphere" if n == "right" else "disk", n=n, x=x, y=y)
                     for n, x, y in (("right", 127, 0), ("left", -127, 0), ("back", 0, 127), ("front", 0, -127)))
    (tmp_path / "sphere.xml").write_text(
        '<scene version="3.0.0"><default name="dh" value="272"/><default name="res" value="4"/><integrator type="elo"/>'
        '<sensor type="elo_beam"><float name="field" value="80"/><film type="hdrfilm"><integer name="width" '
        'value="$res"/><integer name="height" value="$res"/><rfilter type="box"/></film></sensor>'
        '<shape type="rectangle" id="plate">'
        '<transform name="to_world"><scale x="100" y="100"/></transform><bsdf type="elo_bse"/></shape>'
        + shapes + "</scene>")
    spec = _spec(tmp_path, 'scene = "sphere.xml"\n[vary]\ndh = [200]\n[render]\nresolution = 4\nquality = "draft"\n')
    out = tmp_path / "out.zarr"
    assert _cli("sweep", spec, "-o", out, "--workers", "0") == 2
    assert "detector 'right': detector_sampling=quadrature (what every quality preset uses)" in _one_line_error(capsys)
    assert not out.exists()
