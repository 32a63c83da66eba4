"""One benchmark job in its own process: ``python -m benchmarks.worker '<json job>'``.

Prints one JSON line (prefixed ``RESULT ``) with the timings, peak memory (``peak_mb``: the
peak resident set of one timed render, reset before each; ``maxrss_mb``: of the whole process)
and what the job measured. Job kinds:

* ``render``: load a scene (shipped name or XML path, ``params`` as -D), set ``events``, the
  ``quality`` preset and then ``options`` (integrator options, validated), render once to
  compile/warm up (``first_s``), then time ``seeds`` renders of ``spp`` (``times``, seconds of
  :meth:`EloScene.render`, numpy conversion included); optionally count the rays cast per sample
  and save the channels of the first timed render (``save``, .npz).
* ``path``: Mitsuba's built-in ``path`` integrator on the same scene with ONE detector as area
  emitter (the others black absorbers), max_depth = events + 1: the alternative a user has.
* ``raw``: Mitsuba's raw ray-cast throughput on the scene: beam rays, bounce rays from the
  first hits, shadow rays from first hits and from bounce hits to points on the detectors.
* ``presets``: the quality presets on one scene against its reference
  (:func:`benchmarks.section_presets.measure_scene`).
* ``skeleton``: our integrator, a ray-only skeleton of it and the same rays in one bare kernel,
  interleaved with the raw ray casts in one process (the paired ceiling).
"""

from __future__ import annotations

import json
import resource
import sys
import time

import numpy as np


#: The options a ``render`` job reports (``settings``): what RESULTS.md shows of a configuration.
SETTINGS = ("detector_sampling", "detector_samples", "quadrature_triangles", "bounce_fraction", "bounce_samples",
            "bounce_filter", "bounce_min")


def _maxrss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _reset_peak():
    """Reset the process's peak resident set (Linux: VmHWM), so that the next :func:`_peak_mb`
    is the peak of what runs in between; False where the kernel does not allow it."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_mb():
    """Peak resident set since the last :func:`_reset_peak` (or since the start), MB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return _maxrss_mb()


def _sync(dr, *values):
    dr.eval(*values)
    dr.sync_thread()


def job_render(job):
    import elo_mitsuba as em

    em.ensure_variant()
    t0 = time.perf_counter()
    scene = em.load_scene(job["scene"], **job.get("params", {}))
    integ = scene.integrator
    if "events" in job:
        scene.set_events(job["events"])
    preset_spp = scene.set_quality(job["quality"]) if job.get("quality") else None
    scene.configure(**job.get("options", {}))  # validated: an unknown option or bad value is refused
    load_s = time.perf_counter() - t0
    spp = int(job["spp"] if job.get("spp") else preset_spp)
    out = {"load_s": load_s}
    counts = None
    if job.get("count_rays"):
        options = integ.options
        integ.configure(options.replace(count_rays=True))
        scene.render(spp=spp, seed=10_000)
        counts = dict(integ.ray_counts)
        integ.configure(options)
    t = time.perf_counter()
    if job.get("warm", True):
        scene.render(spp=spp, seed=20_000)
    out["first_s"] = time.perf_counter() - t
    # peak memory of one render as a user's process sees it (import, scene, Dr.Jit's caches
    # included): the peak is reset before each timed render and no earlier result is held
    times, peaks = [], []
    for i, seed in enumerate(job.get("seeds", [0])):
        _reset_peak()
        t = time.perf_counter()
        result = scene.render(spp=spp, seed=seed)
        times.append(time.perf_counter() - t)
        peaks.append(_peak_mb())
        if i == 0 and job.get("save"):
            np.savez(job["save"], **result.channels)
        del result
    options = integ.options.as_dict()
    unblockable = integ.unblockable_detectors()
    out.update(times=times, peak_mb=max(peaks), maxrss_mb=_maxrss_mb(), ray_counts=counts, notes=list(integ.notes),
               free_detectors=[name in unblockable for name, _ in integ.detectors], spp=spp,
               settings={k: options[k] for k in SETTINGS})
    return out


def _detector_transforms(mi, scene):
    params = mi.traverse(scene.scene)
    return {name: params[f"{name}.to_world"] for name, _ in scene.integrator.detectors}


def job_path(job):
    """Mitsuba's ``path`` integrator, one detector (both faces: two back-to-back emitter discs) as
    the only emitter."""
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
        to_world = mi.ScalarTransform4f(np.array(xf.matrix).reshape(4, 4))
        det = {"type": "disk", "to_world": to_world, "bsdf": {"type": "diffuse", "reflectance": 0.0}}
        if name == target:
            det["emitter"] = {"type": "area"}
            # our detectors collect on both faces, Mitsuba's emitters on one: a second disc just
            # behind, turned over, collects what arrives at the back
            normal = np.array(to_world @ mi.ScalarNormal3f(0, 0, 1), float)
            normal /= np.linalg.norm(normal)
            d[f"det_{name}_back"] = {
                "type": "disk", "emitter": {"type": "area"}, "bsdf": {"type": "diffuse", "reflectance": 0.0},
                "to_world": mi.ScalarTransform4f().translate((-1e-3 * normal).tolist()) @ to_world
                @ mi.ScalarTransform4f().rotate([1, 0, 0], 180.0)}
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


def _raw_casts(mi, dr, scene, spp):
    """The kinds of rays the integrator casts, prepared in memory and cast raw (no physics):
    {name: (function casting them once, number of rays)} and the bounce-hit fraction."""
    sc, sensor = scene.scene, scene.sensor
    res = sensor.resolution
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

    casts = {
        "beam rays (ray_intersect)": (lambda: full(ray, True), n),
        "bounce rays (ray_intersect)": (lambda: full(bounce, valid1), n1),
        "beam rays (preliminary)": (lambda: prelim(ray, True), n),
        "bounce rays (preliminary)": (lambda: prelim(bounce, valid1), n1),
        "shadow rays from 1st hits": (lambda: _sync(dr, *[sc.ray_test(r, valid1) for r in s1]), len(dets) * n1),
        "shadow rays from bounce hits": (lambda: _sync(dr, *[sc.ray_test(r, valid2) for r in s2]), len(dets) * n2),
    }
    for fn, _ in casts.values():
        fn()  # compile
    return casts, n2 / max(n1, 1)


def _time_raw(casts):
    """Cast each kind of ray once; rays per second of each."""
    rates = {}
    for key, (fn, count) in casts.items():
        t = time.perf_counter()
        fn()
        rates[key] = count / (time.perf_counter() - t)
    return rates


def job_raw(job):
    """Raw ray casting: the same kinds of rays as the integrator, without any physics."""
    import elo_mitsuba as em

    mi = em.ensure_variant()
    import drjit as dr

    scene = em.load_scene(job["scene"], **job.get("params", {}))
    casts, bounce_hits = _raw_casts(mi, dr, scene, int(job.get("spp", 1)))
    per_rep = [_time_raw(casts) for _ in range(int(job.get("repeat", 5)))]  # interleaved
    rates = {k: float(np.median([r[k] for r in per_rep])) for k in casts}
    return {"rates": rates, "counts": {k: v[1] for k, v in casts.items()}, "maxrss_mb": _maxrss_mb(),
            "bounce_hit_fraction": bounce_hits}


def job_skeleton(job):
    """Our integrator against a ray-only skeleton of itself in Mitsuba's render loop: the same
    rays (beam, one shadow ray per detector and event to a point drawn on it, cosine-distributed
    bounce), the same film channels, but no g_BSE, no BSDF sampling, no quadrature. Both timed
    through ``mi.render`` (kernel, film), interleaved with the same rays in one bare kernel and
    with the raw ray casts (the ceiling); every shadow ray cast."""
    import elo_mitsuba as em

    mi = em.ensure_variant()
    import drjit as dr

    from elo_mitsuba.plugins.integrator_elo import EloIntegrator

    class Skeleton(EloIntegrator):
        def sample(self, scene, sampler, ray, medium=None, active=True):
            si = scene.ray_intersect(ray, active)
            alive = si.is_valid() & ~si.shape.is_emitter()
            per_event = []
            for event in range(self.events):
                row = []
                for _, shape in self.detectors:
                    ds, w = shape.emitter().sample_direction(si, sampler.next_2d(alive), alive)
                    seen = alive & ~scene.ray_test(si.spawn_ray_to(ds.p), alive)
                    row.append(dr.select(seen, w[0], 0.0))
                per_event.append(row)
                if event + 1 < self.events:
                    d = si.to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d(alive)))
                    si = scene.ray_intersect(si.spawn_ray(d), alive)
                    alive &= si.is_valid() & ~si.shape.is_emitter()
            aovs = []
            for k in range(len(self.detectors)):
                events = [per_event[e][k] for e in range(self.events)]
                total = events[0]
                for e in events[1:]:
                    total = total + e
                aovs += [total] + (events if self.events > 1 else [])
            return mi.Spectrum(0.0), mi.Bool(True), aovs

    mi.register_integrator("elo_benchmark_skeleton", Skeleton)
    scene = em.load_scene(job["scene"], **job.get("params", {}))
    events = int(job.get("events", scene.integrator.events))
    ours = mi.load_dict({"type": "elo", "events": events})
    skel = mi.load_dict({"type": "elo_benchmark_skeleton", "events": events})
    for integ in (ours, skel):
        integ.configure(integ.options.replace(occlusion_analysis=False))
    spp = int(job["spp"])
    sc, sensor = scene.scene, scene.sensor
    ours.prepare_scene(sc, sensor)
    dets = [shape for _, shape in ours.detectors]
    w, h = sensor.resolution
    n = w * h * spp

    def rays_only(seed):
        """The same rays in one kernel outside Mitsuba's render loop: no sampler object, no
        emitter pdf, one output channel; the fastest a one-kernel (megakernel) design can be."""
        lane = dr.arange(mi.UInt32, n)
        pixel = lane // spp
        film = mi.Point2f((mi.Float(pixel % w) + 0.5) / w, (mi.Float(pixel // w) + 0.5) / h)
        ray, _ = sensor.sample_ray(0.0, 0.0, film, mi.Point2f(0.5))
        rng = mi.PCG32(n, lane + dr.opaque(mi.UInt32, seed * n))
        si = sc.ray_intersect(ray)
        alive = si.is_valid() & ~si.shape.is_emitter()
        acc = mi.Float(0.0)
        for event in range(events):
            u = mi.Point2f(rng.next_float32(), rng.next_float32())
            for shape in dets:
                blocked = sc.ray_test(si.spawn_ray_to(shape.sample_position(0.0, u).p), alive)
                acc += dr.select(alive & ~blocked, 1.0, 0.0)
            if event + 1 < events:
                u = mi.Point2f(rng.next_float32(), rng.next_float32())
                si = sc.ray_intersect(si.spawn_ray(si.to_world(mi.warp.square_to_cosine_hemisphere(u))), alive)
                alive &= si.is_valid() & ~si.shape.is_emitter()
        out = dr.zeros(mi.Float, w * h)
        dr.scatter_reduce(dr.ReduceOp.Add, out, acc, pixel)
        return out

    runs = {"ours": lambda seed: mi.render(sc, integrator=ours, spp=spp, seed=seed),
            "skeleton": lambda seed: mi.render(sc, integrator=skel, spp=spp, seed=seed),
            "rays only": rays_only}
    # the raw ceiling in the same process, interleaved with the renders: each repetition gives
    # one (raw rates, our time) pair measured under the same machine load
    raw_casts, _ = _raw_casts(mi, dr, scene, 4)
    times = {key: [] for key in runs}
    raw_rates = []
    for fn in runs.values():
        _sync(dr, fn(0))
    for rep in range(int(job.get("repeat", 5))):
        raw_rates.append(_time_raw(raw_casts))
        for key, fn in runs.items():
            t = time.perf_counter()
            _sync(dr, fn(rep + 1))
            times[key].append(time.perf_counter() - t)
    return {"times": times, "raw_rates": raw_rates, "maxrss_mb": _maxrss_mb()}


def job_presets(job):
    from .section_presets import measure_scene

    return measure_scene(job)


JOBS = {"render": job_render, "path": job_path, "raw": job_raw, "skeleton": job_skeleton, "presets": job_presets}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    job = json.loads(argv[0])
    out = JOBS[job["kind"]](job)
    print("RESULT " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
