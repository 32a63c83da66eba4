"""One benchmark job in its own process: ``python -m benchmarks.worker '<json job>'``.

Prints one JSON line (prefixed ``RESULT ``) with the timings, the process's peak memory
(``ru_maxrss``) and what the job measured. Job kinds:

* ``render``: load a scene (shipped name or XML path, ``params`` as -D), set integrator options,
  render once to compile/warm up (``first_s``), then time ``seeds`` renders of ``spp``
  (``times``, seconds of :meth:`EloScene.render`, numpy conversion included); optionally count
  the rays cast per sample and save the channels of the first timed render (``save``, .npz).
* ``path``: Mitsuba's built-in ``path`` integrator on the same scene with ONE detector as area
  emitter (the others black absorbers), max_depth = events + 1: the alternative a user has.
* ``raw``: Mitsuba's raw ray-cast throughput on the scene: beam rays, bounce rays from the
  first hits, shadow rays from first hits and from bounce hits to points on the detectors.
"""

from __future__ import annotations

import json
import resource
import sys
import time

import numpy as np


def _maxrss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _sync(dr, *values):
    dr.eval(*values)
    dr.sync_thread()


def job_render(job):
    import elo_mitsuba as em

    mi = em.ensure_variant()
    t0 = time.perf_counter()
    scene = em.load_scene(job["scene"], **job.get("params", {}))
    integ = scene.integrator
    if "events" in job:
        scene.set_events(job["events"])
    preset_spp = scene.set_quality(job["quality"]) if job.get("quality") else None
    for key, value in job.get("options", {}).items():
        if not hasattr(integ, key):
            raise SystemExit(f"integrator has no option {key!r}")
        setattr(integ, key, type(getattr(integ, key))(value) if getattr(integ, key) is not None else value)
    load_s = time.perf_counter() - t0
    spp = int(job["spp"] if job.get("spp") else preset_spp)
    out = {"load_s": load_s}
    counts = None
    if job.get("count_rays"):
        integ.count_rays = True
        scene.render(spp=spp, seed=10_000)
        counts = dict(integ.ray_counts)
        integ.count_rays = False
    t = time.perf_counter()
    if job.get("warm", True):
        scene.render(spp=spp, seed=20_000)
    out["first_s"] = time.perf_counter() - t
    times, first = [], None
    for seed in job.get("seeds", [0]):
        t = time.perf_counter()
        result = scene.render(spp=spp, seed=seed)
        times.append(time.perf_counter() - t)
        if first is None:
            first = result
    out.update(times=times, maxrss_mb=_maxrss_mb(), ray_counts=counts, notes=list(integ.notes),
               free_detectors=[bool(f) for f in integ._free], spp=spp,
               settings={k: getattr(integ, k) for k in (
                   "detector_sampling", "detector_samples", "quadrature_triangles", "bounce_fraction",
                   "bounce_samples", "bounce_filter", "bounce_min")})
    if job.get("save"):
        np.savez(job["save"], **first.channels)
    return out


def _detector_transforms(mi, scene):
    params = mi.traverse(scene.scene)
    return {name: params[f"{name}.to_world"] for name, _ in scene.integrator.detectors}


def job_path(job):
    """Mitsuba's ``path`` integrator, one detector as the only emitter."""
    import elo_mitsuba as em

    mi = em.ensure_variant()
    import drjit as dr

    scene = em.load_scene(job["scene"], **job.get("params", {}))
    target = job["detector"]
    xforms = _detector_transforms(mi, scene)
    d = {"type": "scene", "sensor": scene.sensor,
         "integrator": {"type": "path", "max_depth": int(job["events"]) + 1, "rr_depth": 1000,
                        "hide_emitters": False}}
    for shape in scene.scene.shapes():
        if shape.is_emitter():
            continue
        key = shape.id() or f"shape_{len(d)}"
        d[key] = shape
    for name, xf in xforms.items():
        det = {"type": "disk", "to_world": mi.ScalarTransform4f(np.array(xf.matrix).reshape(4, 4)),
               "bsdf": {"type": "diffuse", "reflectance": 0.0}}
        if name == target:
            det["emitter"] = {"type": "area"}
        d[f"det_{name}"] = det
    path_scene = mi.load_dict(d)
    spp = int(job["spp"])
    t = time.perf_counter()
    img = mi.render(path_scene, spp=spp, seed=20_000)
    _sync(dr, img)
    out = {"first_s": time.perf_counter() - t}
    times, first = [], None
    for seed in job.get("seeds", [0]):
        t = time.perf_counter()
        img = mi.render(path_scene, spp=spp, seed=seed)
        arr = np.array(img)[..., 0].astype(np.float32)
        times.append(time.perf_counter() - t)
        if first is None:
            first = arr
    out.update(times=times, maxrss_mb=_maxrss_mb())
    if job.get("save"):
        np.savez(job["save"], **{target: first})
    return out


def job_raw(job):
    """Raw ray casting: the same kinds of rays as the integrator, without any physics."""
    import elo_mitsuba as em

    mi = em.ensure_variant()
    import drjit as dr

    scene = em.load_scene(job["scene"], **job.get("params", {}))
    sc, sensor = scene.scene, scene.sensor
    res = sensor.resolution
    spp = int(job.get("spp", 1))
    n = res[0] * res[1] * spp
    idx = dr.arange(mi.UInt32, n)
    pix = idx // spp
    film = mi.Point2f((mi.Float(pix % res[0]) + 0.5) / res[0], (mi.Float(pix // res[0]) + 0.5) / res[1])
    ray, _ = sensor.sample_ray(0.0, 0.0, film, mi.Point2f(0.5))
    _sync(dr, ray)
    si = sc.ray_intersect(ray)
    _sync(dr, si)
    rng = mi.PCG32(n, idx)
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    _sync(dr, u)
    valid1 = si.is_valid() & ~si.shape.is_emitter()
    bounce = si.spawn_ray(si.to_world(mi.warp.square_to_cosine_hemisphere(u)))
    _sync(dr, bounce, valid1)
    si2 = sc.ray_intersect(bounce, valid1)
    _sync(dr, si2)
    valid2 = valid1 & si2.is_valid() & ~si2.shape.is_emitter()
    _sync(dr, valid2)
    dets = [shape for _, shape in scene.integrator.detectors]

    def shadow(si_, valid):
        rays = [si_.spawn_ray_to(shape.sample_position(0.0, u).p) for shape in dets]
        _sync(dr, *rays)
        return rays

    s1, s2 = shadow(si, valid1), shadow(si2, valid2)
    n1 = int(dr.count(valid1)[0] if hasattr(dr.count(valid1), "__len__") else dr.count(valid1))
    n2 = int(dr.count(valid2)[0] if hasattr(dr.count(valid2), "__len__") else dr.count(valid2))

    def full(r, active):  # Mitsuba's ray_intersect: the surface interaction the integrator uses
        s = sc.ray_intersect(r, active)
        _sync(dr, s.p, s.sh_frame.n, s.wi, dr.reinterpret_array(mi.UInt32, s.shape))

    def prelim(r, active):  # the bare hit (distance and primitive), no surface interaction
        _sync(dr, sc.ray_intersect_preliminary(r, active=active).t)

    tests = {
        "beam rays (ray_intersect)": (lambda: full(ray, True), n),
        "bounce rays (ray_intersect)": (lambda: full(bounce, valid1), n1),
        "beam rays (preliminary)": (lambda: prelim(ray, True), n),
        "bounce rays (preliminary)": (lambda: prelim(bounce, valid1), n1),
        "shadow rays from 1st hits": (lambda: _sync(dr, *[sc.ray_test(r, valid1) for r in s1]), len(dets) * n1),
        "shadow rays from bounce hits": (lambda: _sync(dr, *[sc.ray_test(r, valid2) for r in s2]), len(dets) * n2),
    }
    for fn, _ in tests.values():
        fn()  # compile
    reps = int(job.get("repeat", 5))
    times = {k: [] for k in tests}
    for _ in range(reps):  # interleaved
        for key, (fn, _) in tests.items():
            t = time.perf_counter()
            fn()
            times[key].append(time.perf_counter() - t)
    rates = {k: tests[k][1] / float(np.median(v)) for k, v in times.items()}
    return {"rates": rates, "counts": {k: v[1] for k, v in tests.items()}, "maxrss_mb": _maxrss_mb(),
            "bounce_hit_fraction": n2 / max(n1, 1)}


JOBS = {"render": job_render, "path": job_path, "raw": job_raw}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    job = json.loads(argv[0])
    out = JOBS[job["kind"]](job)
    print("RESULT " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
