"""Design sweeps (elo_mitsuba.sweeps, ``elo-mitsuba sweep``/``sweep-plot``) on a real Dask cluster.

A module-scoped fixture starts ``dask scheduler`` and two ``dask worker`` processes (one thread,
no nanny, so a killed worker stays dead) on 127.0.0.1 with ephemeral ports, found through a
scheduler file; every process is killed at the end. The worker-kill test runs last: it leaves one
worker.
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

from conftest import same_isa_as_subprocesses
from elo_mitsuba.cli import main

xr = pytest.importorskip("xarray")
pytest.importorskip("distributed")


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _cli(*args) -> int:
    return main([str(a) for a in args])


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """(scheduler file, {name: Popen}) of a scheduler and two workers on 127.0.0.1."""
    tmp = tmp_path_factory.mktemp("dask")
    sched_file = tmp / "scheduler.json"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs = {}
    try:
        procs["scheduler"] = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
             "--no-dashboard", "--scheduler-file", str(sched_file)],
            stdout=subprocess.DEVNULL, stderr=open(tmp / "scheduler.log", "w"), env=env)
        deadline = time.time() + 60
        while not sched_file.is_file() and time.time() < deadline:
            time.sleep(0.1)
        assert sched_file.is_file(), (tmp / "scheduler.log").read_text()
        for k in (1, 2):
            procs[f"w{k}"] = subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file", str(sched_file),
                 "--nthreads", "1", "--no-nanny", "--host", "127.0.0.1", "--no-dashboard", "--name", f"w{k}"],
                stdout=subprocess.DEVNULL, stderr=open(tmp / f"w{k}.log", "w"), env=env)
        from distributed import Client

        with Client(scheduler_file=str(sched_file), timeout="30s") as c:
            c.wait_for_workers(2, timeout=90)
        yield sched_file, procs
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait(timeout=30)


SPEC_DIRECT = """\
scene = "flat_plate"
seed = 7
[vary]
dh = [200, 272]
right.radius = [20, 30]
[render]
resolution = 32
events = 2
quality = "scene"
spp = 4
[keep]
channels = "all"
"""


def test_cluster_sweep_equals_direct_renders(cluster, tmp_path, capsys, request):
    """Through --scheduler: every point's images equal a direct EloScene.render of the same
    parameters and seed, bit for bit, and the metrics are those of the images."""
    same_isa_as_subprocesses(request)
    import elo_mitsuba as em

    sched_file, _ = cluster
    address = json.loads(sched_file.read_text())["address"]  # tcp://127.0.0.1:<ephemeral port>
    assert address.startswith("tcp://127.0.0.1:")
    spec = _write(tmp_path / "s.toml", SPEC_DIRECT)
    out = tmp_path / "s.zarr"
    assert _cli("sweep", spec, "-o", out, "--scheduler", address, "--no-progress") == 0
    ds = xr.open_zarr(out)
    assert ds["status"].values.tolist() == [[1, 1], [1, 1]]
    assert set(ds["worker"].values.ravel()) <= {"w1", "w2"}
    assert ds["dh"].attrs["units"] == "mm" and ds["right_radius"].attrs["units"] == "mm"
    geometry = json.loads(ds.attrs["scan_geometry"])
    assert geometry["field_mm"] == [80.0, 80.0] and geometry["resolution"] == [32, 32]
    assert "dh" in ds.attrs["spec_toml"]
    for i, dh in enumerate((200, 272)):
        scene = em.load_scene("flat_plate", res=32, dh=dh)
        for j, r in enumerate((20.0, 30.0)):
            scene.set_detector("right", radius=r)
            direct = scene.render(spp=4, seed=7, events=2, quality="scene")
            for ch, img in direct.channels.items():
                np.testing.assert_array_equal(ds[f"image_{ch}"].values[i, j], img, err_msg=f"{ch} dh={dh} r={r}")
            for k, d in enumerate(ds["detector"].values):
                img = direct.channels[d].astype(np.float64)
                assert ds["signal_mean"].values[i, j, k] == pytest.approx(img.mean(), rel=1e-12)
                assert ds["signal_spread"].values[i, j, k] == pytest.approx(img.std() / img.mean(), rel=1e-9)
                share = 1 - direct.channels[f"{d}.e1"].sum(dtype=np.float64) / direct.channels[d].sum(dtype=np.float64)
                assert ds["events2_share"].values[i, j, k] == pytest.approx(share, rel=1e-12)
    # a bigger right detector collects more
    right = list(ds["detector"].values).index("right")
    assert np.all(ds["signal_mean"].values[:, 1, right] > ds["signal_mean"].values[:, 0, right])
    # the plot of a metric over one and two swept parameters
    assert _cli("sweep-plot", out, "signal_mean", "-o", tmp_path / "line.png", "--select", "dh=272") == 0
    assert _cli("sweep-plot", out, "signal_spread", "-o", tmp_path / "map.png", "--detector", "right") == 0
    assert (tmp_path / "line.png").stat().st_size > 5000 and (tmp_path / "map.png").stat().st_size > 5000
    capsys.readouterr()
    assert _cli("sweep-plot", out, "nonsense", "-o", tmp_path / "x.png") == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no metric 'nonsense'" in err and "signal_mean" in err


def test_resume_skips_done_points_and_records_failures(cluster, tmp_path, capsys, monkeypatch, request):
    """A point that fails while rendering is recorded with its one-line error and the others are
    kept; re-running the command renders only what is not done (here on the cluster); another
    spec on the same store is refused. (A value that fails in any position is refused before
    the store exists, tests/test_sweep_faults.py; the failure here is injected.)"""
    same_isa_as_subprocesses(request)
    import elo_mitsuba.sweeps.worker as worker
    from elo_mitsuba import EloInputError

    sched_file, _ = cluster
    spec = _write(tmp_path / "r.toml", """\
scene = "flat_plate"
[vary]
right.center = [[127, 0, 272], [150, 0, 250], [127, 0, 200]]
[render]
resolution = 16
spp = 1
""")
    out = tmp_path / "r.zarr"
    real = worker.render_point

    def flaky(spec_, point):
        if point.index == 2:
            raise EloInputError("detector 'right' is below what this test allows")
        return real(spec_, point)

    monkeypatch.setattr(worker, "render_point", flaky)
    assert _cli("sweep", spec, "-o", out, "--workers", "0", "--no-progress") == 1  # one failed
    monkeypatch.setattr(worker, "render_point", real)
    ds = xr.open_zarr(out)
    assert ds["status"].values.tolist() == [1, 1, 2]
    assert "EloInputError" in str(ds["error"].values[2]) and "below" in str(ds["error"].values[2])
    assert ds["right_center_xyz"].values[1].tolist() == [150, 0, 250]
    first = ds["render_seconds"].values.copy()
    mean = ds["signal_mean"].values.copy()
    # an interrupted run: point 1 never finished
    import zarr

    g = zarr.open_group(str(out), mode="r+")
    g["status"][1] = 0
    g["signal_mean"][1] = np.nan
    capsys.readouterr()
    assert _cli("sweep", spec, "-o", out, "--scheduler", sched_file, "--no-progress") == 0
    line = capsys.readouterr().out
    assert "1 already stored (resumed)" in line  # point 0 kept; 1 redone; 2 retried, now rendered
    ds = xr.open_zarr(out)
    assert ds["status"].values.tolist() == [1, 1, 1]
    assert str(ds["error"].values[2]) == ""
    assert ds["render_seconds"].values[0] == first[0] and ds["render_seconds"].values[1] != first[1]
    np.testing.assert_array_equal(ds["signal_mean"].values[:2], mean[:2])
    # a different spec on this store
    other = _write(tmp_path / "other.toml", spec.read_text().replace("resolution = 16", "resolution = 32"))
    assert _cli("sweep", other, "-o", out, "--workers", "0") == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("elo-mitsuba: error: output ") and "another spec" in err and "\n" not in err


BAD_SPECS = {
    "unknown_parameter": ("scene = 'flat_plate'\n[vary]\nheight = [1, 2]\n", "unknown parameter 'height'"),
    "empty_list": ("scene = 'flat_plate'\n[vary]\ndh = []\n", "vary.dh is an empty list"),
    "not_a_list": ("scene = 'flat_plate'\n[vary]\ndh = 200\n", "a swept parameter is a list"),
    "wrong_type": ("scene = 'flat_plate'\n[vary]\ndh = [true, false]\n", "numbers or strings"),
    "unknown_detector": ("scene = 'flat_plate'\n[vary]\ntop.radius = [20, 30]\n", "unknown detector 'top'"),
    "bad_radius": ("scene = 'flat_plate'\n[vary]\nright.radius = [20, -1]\n", "give numbers > 0"),
    "unknown_key": ("scene = 'flat_plate'\nrepeat = 3\n[vary]\ndh = [200]\n", "unknown key 'repeat'"),
    "unknown_scene": ("scene = 'flat_plat'\n[vary]\ndh = [200]\n", "neither an XML file nor a shipped scene"),
    "bad_toml": ("scene = 'flat_plate'\n[vary\ndh = [200]\n", "not valid TOML"),
    "zip_lengths": ("scene = 'flat_plate'\n[zip.g]\ndh = [200, 272]\ndw = [100]\n", "lists of different lengths"),
    "metric_needs_events": ("scene = 'flat_plate'\n[vary]\ndh = [200]\n[keep]\nmetrics = ['events2_share']\n",
                            "needs events >= 2"),
    "unknown_metric": ("scene = 'flat_plate'\n[vary]\ndh = [200]\n[keep]\nmetrics = ['sharpness']\n",
                       "unknown metric 'sharpness'"),
    "bad_events": ("scene = 'flat_plate'\n[vary]\ndh = [200]\n[render]\nevents = 1.5\n", "render.events = 1.5"),
}


@pytest.mark.parametrize("case", sorted(BAD_SPECS))
def test_bad_spec_is_one_line_and_exit_2_before_any_render(case, tmp_path, capsys, monkeypatch):
    import elo_mitsuba.sweeps.worker as worker

    text, expected = BAD_SPECS[case]
    spec = _write(tmp_path / f"{case}.toml", text)
    out = tmp_path / "out.zarr"
    monkeypatch.setattr(worker, "run_batch", lambda *a: pytest.fail("a render started"))
    assert _cli("sweep", spec, "-o", out, "--workers", "0") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("elo-mitsuba: error: "), err
    assert expected in err, err
    assert err.count(str(spec)) == 1, err  # named once ('b5.toml: b5.toml: unknown parameter' was twice)
    assert not out.exists()


def test_minimal_spec_on_the_local_cluster(tmp_path):
    """The README's minimal form, on Dask's local cluster (the default), one worker."""
    spec = _write(tmp_path / "m.toml", Path(__file__).parents[1].joinpath("examples", "sweep_minimal.toml")
                  .read_text().replace("resolution = 64", "resolution = 16"))
    out = tmp_path / "m.zarr"
    assert _cli("sweep", spec, "-o", out, "--no-progress") == 0
    ds = xr.open_zarr(out)
    assert dict(ds.sizes) == {"dh": 2, "dw": 2, "detector": 4}
    assert (ds["status"].values == 1).all()
    mean = ds["signal_mean"].sel(detector="right")
    assert float(mean.sel(dh=200, dw=100)) > float(mean.sel(dh=272, dw=127)) > 0  # nearer: more signal
    assert float(ds["masked_fraction"].max()) == 0.0  # a flat plate masks nothing


def test_no_memory_growth_over_a_long_sweep(tmp_path):
    """One scene, 48 detector moves, rendered in this process: the resident memory after the
    warm-up points stays flat (the scene is loaded once, not per point)."""
    import elo_mitsuba.sweeps.worker as worker
    from elo_mitsuba import sweep

    worker._STATE["scenes"].clear()  # a test before this one may have loaded the same scene
    loads = worker._STATE["loads"]
    spec = {"scene": "flat_plate", "vary": {"right": {"radius": [10.0 + k for k in range(48)]}},
            "render": {"resolution": 32, "spp": 2}, "keep": {"channels": ["right"]}}
    s = sweep(spec, tmp_path / "long.zarr", workers=0, progress=False)
    assert s.done == 48
    assert worker._STATE["loads"] - loads == 1
    rss = xr.open_zarr(tmp_path / "long.zarr")["worker_rss_mb"].values
    assert rss[-1] - rss[8] < 15, rss  # MB; a reload per point grows by ~several MB each


def test_set_detector_normal_turns_the_front_face():
    import elo_mitsuba as em

    scene = em.load_scene("flat_plate", res=8)
    scene.set_detector("right", center=(127, 0, 272), normal=(-1, 0, -1))
    n = scene.detector_geometry()["right"]["normal"]
    assert np.allclose(n, np.array([-1, 0, -1]) / np.sqrt(2), atol=1e-6)
    with pytest.raises(em.EloInputError, match="faces away"):
        scene.set_detector("right", normal=(1, 0, 1))


def test_a_killed_worker_loses_nothing(cluster, tmp_path):
    """Kill one of the two workers mid-sweep: the other finishes its points (runs last: the
    cluster keeps one worker)."""
    sched_file, procs = cluster
    spec = _write(tmp_path / "k.toml", """\
scene = "flat_plate"
[vary]
right.radius = [18, 20, 22, 24, 26, 28, 30, 32, 34, 36, 38, 40]
[render]
resolution = 128
quality = "scene"
spp = 64
""")
    out = tmp_path / "k.zarr"
    cmd = [sys.executable, "-m", "elo_mitsuba", "sweep", str(spec), "-o", str(out), "--scheduler",
           str(sched_file), "--no-progress"]
    run = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        import zarr

        deadline = time.time() + 120
        while time.time() < deadline:
            if out.exists() and (out / "status" / ".zarray").is_file():
                done = np.asarray(zarr.open_group(str(out), mode="r")["status"][...])
                if (done == 1).sum() >= 2:
                    break
            time.sleep(0.05)
        done_at_kill = int((np.asarray(zarr.open_group(str(out), mode="r")["status"][...]) == 1).sum())
        assert 2 <= done_at_kill < 12, "the sweep ended before a worker could be killed"
        procs["w1"].send_signal(signal.SIGKILL)
        procs["w1"].wait(timeout=30)
        stdout, stderr = run.communicate(timeout=180)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, stderr
    ds = xr.open_zarr(out)
    assert (ds["status"].values == 1).all(), ds["error"].values
    assert "w2" in set(ds["worker"].values)
    assert "12/12 points done" in stdout


def test_zipped_groups_moves_and_the_gradient_metric(tmp_path):
    """A zipped group is one dimension with a coordinate per member; detectors.radius and
    right.normal move detectors; with a test surface the Eq. 26 error is that of
    analysis.surface_gradient on the object and flat renders against the true gradient."""
    import elo_mitsuba as em
    from elo_mitsuba.analysis import surface_gradient
    from elo_mitsuba.sweeps.metrics import gradient_rms, true_gradient

    spec = _write(tmp_path / "z.toml", """\
scene = "corrugated_sheet"
[fixed]
field = 20
[zip.position]
dh = [272, 250]
dw = [127, 150]
[vary]
detectors.radius = [20, 30]
right.normal = [[-127, 0, -272]]
[render]
resolution = 32
spp = 2
[surface]
object = "corrugated_sheet"
""")
    out = tmp_path / "z.zarr"
    assert _cli("sweep", spec, "-o", out, "--workers", "0", "--no-progress") == 0
    ds = xr.open_zarr(out)
    assert dict(ds.sizes) == {"position": 2, "detectors_radius": 2, "right_normal": 1, "detector": 4, "xyz": 3}
    assert ds["dw"].dims == ("position",) and ds["dw"].values.tolist() == [127, 150]
    assert ds["right_normal_xyz"].values.tolist() == [[-127, 0, -272]]
    assert set(ds.data_vars) >= {"gradient_rms_eq26", "masked_fraction", "signal_mean", "signal_spread"}
    # point (position 1, radius 30): recompute the metric from direct renders
    kw = {"field": 20, "res": 32, "dh": 250, "dw": 150}
    renders = {}
    for name in ("corrugated_sheet", "flat_plate"):
        scene = em.load_scene(name, **kw)
        for d in scene.detector_names:
            scene.set_detector(d, radius=30.0)
        scene.set_detector("right", normal=(-127, 0, -272))
        renders[name] = scene.render(spp=2, seed=0, quality="default")
    geo = renders["corrugated_sheet"].metadata["detectors"]
    d_h = float(np.mean([geo[d]["center"][2] for d in geo]))
    d_w = float(np.mean([np.hypot(*geo[d]["center"][:2]) for d in geo]))
    g = surface_gradient(renders["corrugated_sheet"].channels, renders["flat_plate"].channels, (20.0, 20.0), d_h, d_w)
    truth = true_gradient({"object": "corrugated_sheet"}, (32, 32), (20.0, 20.0))
    assert abs(truth[0]).max() == pytest.approx(1.0)  # the flanks' slope, where a pixel lies on one
    expected = gradient_rms(g.dzdx, g.dzdy, g.mask, truth)
    at = {"position": 1, "detectors_radius": 1, "right_normal": 0}
    assert float(ds["gradient_rms_eq26"].isel(at)) == pytest.approx(expected, rel=1e-12)
    assert float(ds["masked_fraction"].isel(at)) == pytest.approx(float(g.mask.mean()))
    # the model method's metric: the same computation on the point's renders and its own discs
    from elo_mitsuba.analysis.model_gradient import model_gradient
    from elo_mitsuba.analysis.scan_geometry import ScanGeometry

    r = renders["corrugated_sheet"]
    m = model_gradient(r.channels, renders["flat_plate"].channels, ScanGeometry.from_metadata(r.metadata, (32, 32)))
    assert float(ds["gradient_rms_model"].isel(at)) == pytest.approx(gradient_rms(m.dzdx, m.dzdy, m.mask, truth),
                                                                      rel=1e-6)


_FAULTS = """
import resource, sys
import numpy as np
from elo_mitsuba.runtime import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else False
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
a = np.ones(1 << 24)  # 128 MB: glibc would map and unmap it
del a
f0 = faults()
for _ in range(3):
    b = np.ones(1 << 24)
    del b
print(applied, faults() - f0)
"""


@pytest.mark.parametrize("mode", ["keep", "default"])
def test_workers_reuse_freed_memory(mode):
    """A sweep worker keeps freed memory for reuse (elo_mitsuba.runtime.keep_freed_memory): an
    image-sized array allocated again after a free costs no page faults, where glibc's default
    maps fresh pages every time (the 31 % CPU overhead per point of a Dask worker at 1024^2)."""
    out = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, check=True,
                         timeout=120).stdout.split()
    applied, faults = out[0] == "True", int(out[1])
    if mode == "keep":
        assert applied
        assert faults < 100, faults  # the pages stay mapped
    else:
        assert faults > 3 * 60, faults  # 3 x 128 MB fresh: >= 64 faults each even with 2 MB pages


def test_a_detector_in_the_beams_path_fails_its_point(tmp_path):
    """A point whose detector stands between the gun and the field was stored as done with zero
    signal and NaN spread; it fails with the render's note, and the other points go on."""
    spec = _write(tmp_path / "b.toml", """
scene = "flat_plate"
[vary]
right.center = [[127, 0, 272], [0, 0, 200]]
right.normal = [[-127, 0, -272], [0, 0, -1]]
[render]
resolution = 8
quality = "draft"
""")
    out = tmp_path / "b.zarr"
    assert _cli("sweep", spec, "-o", out, "--workers", "0", "--no-progress") == 1  # one failed
    ds = xr.open_zarr(out)
    status = ds["status"].values
    assert (status == 1).sum() >= 1 and (status == 2).sum() >= 1, status
    errors = [str(e) for e in np.ravel(ds["error"].values) if "beam's path" in str(e)]
    assert errors and all("detector 'right' lies in the beam's path over about" in e for e in errors)
