"""The bench: jobs run in worker processes, cached reference images and the error measure.

Errors are per pixel, |x - ref| / max(ref, FLOOR x the image mean of ref), over all pixels: the
RMS and the 99th percentile, worst of the four detectors. References are cached in
:data:`CACHE` (``~/.cache/elo-mitsuba/bench_cache/`` or ``$ELO_BENCH_CACHE``) and keyed by the job and a fingerprint of the code and scenes.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from .config import settings

ROOT = Path(__file__).resolve().parents[1]
#: References, meshes and images the runs share: outside the checkout (a cache, not an output),
#: in $ELO_BENCH_CACHE or the user's cache folder.
CACHE = Path(os.environ.get("ELO_BENCH_CACHE")
             or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "elo-mitsuba" / "bench_cache")
DETS = ("right", "left", "back", "front")
FLOOR = 0.05


class Bench:
    """Runs benchmark jobs, each in its own process (:mod:`benchmarks.worker`), and keeps what
    the sections share.

    Parameters
    ----------
    quick : bool
        Use the :data:`~benchmarks.config.QUICK` sizes.
    fresh : bool
        Recompute cached references.
    verbose : bool
        Print the progress log on stderr.

    Attributes
    ----------
    settings : dict
        The sizes of every section (:func:`benchmarks.config.settings`).
    facts : dict
        Figures the sections measured, for the summary.
    target_results : dict
        Per configuration of the ``targets`` section: times, peak memory, errors, settings.
    """

    def __init__(self, quick: bool, fresh: bool, verbose: bool = True):
        self.quick, self.fresh, self.verbose = quick, fresh, verbose
        self.settings = settings(quick)
        CACHE.mkdir(parents=True, exist_ok=True)
        self.log_lines = []
        self.facts = {}
        self.target_results = {}

    def log(self, msg):
        line = f"[{time.strftime('%H:%M:%S')} load {os.getloadavg()[0]:.2f}] {msg}"
        self.log_lines.append(line)
        if self.verbose:
            print(line, file=sys.stderr, flush=True)

    def job(self, job, timeout=3600):
        """Run one job (a dict, see :mod:`benchmarks.worker`) in a new process; its result."""
        out = run_module("benchmarks.worker", [json.dumps(job)], timeout=timeout)
        out["load_avg"] = os.getloadavg()[0]
        return out

    def cached(self, name, job):
        """Run a saving job unless its image is cached for the same job AND the same code and
        scenes (:func:`code_fingerprint`); returns the channels (dict)."""
        path = CACHE / f"{name}.npz"
        meta = CACHE / f"{name}.json"
        key = {**job, "code": code_fingerprint()}
        if self.fresh or not path.exists() or not meta.exists() or json.loads(meta.read_text()) != key:
            self.log(f"reference {name} ...")
            t = time.perf_counter()
            self.job({**job, "save": str(path)})
            meta.write_text(json.dumps(key))
            self.log(f"reference {name} done in {time.perf_counter() - t:.0f} s")
        return _load(path)

    def render(self, name, job):
        """Run a job that saves its first timed render; returns (result, channels)."""
        path = CACHE / f"{name}.npz"
        out = self.job({**job, "save": str(path)})
        return out, _load(path)


def run_module(module, args, timeout=None):
    """Run ``python -m module args`` in a new process (its own memory and kernels) and return the
    JSON of its last line that starts with ``RESULT ``; RuntimeError with its stderr when it fails."""
    p = subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, capture_output=True, text=True,
                       timeout=timeout, stdin=subprocess.DEVNULL)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if p.returncode or not lines:
        raise RuntimeError(f"benchmark job failed ({p.returncode}): {module} {' '.join(args)}\n{p.stderr[-4000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def _load(path):
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """Hash of everything a cached reference image depends on: the package, the plugins and the
    shipped scenes (a reference computed by other code or another scene is recomputed)."""
    h = hashlib.sha256()
    for folder in ("elo_mitsuba", "plugins", "scenes_xml"):
        for f in sorted((ROOT / folder).rglob("*")):
            if f.is_file() and f.suffix in (".py", ".xml", ".ply", ".npy", ".obj"):
                h.update(str(f.relative_to(ROOT)).encode())
                h.update(f.read_bytes())
    return h.hexdigest()[:16]


def peak(result):
    """Peak memory of one render (MB) of a worker's result; the process's for job kinds that
    do not measure it per render."""
    return result.get("peak_mb", result["maxrss_mb"])


def preset_job(name):
    """Job fields that render with a quality preset (spp and options chosen for the scene)."""
    return {"quality": name, "spp": None}


# ---- errors ---------------------------------------------------------------------------------------------
def rel_error(img, ref):
    """(rms, p99) of the per-pixel relative error with a floor of FLOOR x mean(ref)."""
    img = np.asarray(img, np.float64)
    ref = np.asarray(ref, np.float64)
    denom = np.maximum(ref, FLOOR * max(float(ref.mean()), 1e-300))
    e = np.abs(img - ref) / denom
    return float(np.sqrt(np.mean(e * e))), float(np.percentile(e, 99))


def estimated_rel(result, name):
    """The render's own RMS relative error estimate of channel ``name`` (its halves; the same
    floor as :func:`rel_error`)."""
    return float(result.error_summary()[name]["rms_rel"])


def mean_difference(f, g, groups=None):
    """The bias of one estimator against another from repeated renders of one channel: ``f``, ``g``
    (renders, H, W). Returns ``bias`` (RMS per pixel of the difference of the two means less the
    noise of both, relative to g's mean), ``worst`` (largest difference, relative), ``beyond4``
    (share of pixels whose difference exceeds 4 standard errors) and ``noise`` (one f render's RMS
    noise, relative). ``groups`` (an object with ``flat``, ``counts``, ``index``: pixels of one
    expected value) pools g's per-pixel variance over each group, so that a pixel's z does not carry
    its own few-sample variance (Student's tails)."""
    diff = f.mean(0) - g.mean(0)
    var_g = g.var(0, ddof=1)
    if groups is not None:
        var_g = (np.bincount(groups.flat, weights=var_g.ravel()) / groups.counts)[groups.index]
    var = f.var(0, ddof=1) / len(f) + var_g / len(g)
    m = g.mean()
    z = diff / np.sqrt(np.maximum(var, 1e-300))
    return {"bias": float(np.sqrt(max(0.0, np.mean(diff**2) - np.mean(var))) / m),
            "worst": float(np.abs(diff).max() / m), "beyond4": float(np.mean(np.abs(z) > 4)),
            "noise": float(np.sqrt(np.mean(f.var(0, ddof=1))) / m)}


def worst_error(channels, ref, key):
    """Worst over detectors of (rms, p99); key(d) names the channel."""
    errs = [rel_error(channels[key(d)], ref[key(d)]) for d in DETS if key(d) in channels and key(d) in ref]
    return max(e[0] for e in errs), max(e[1] for e in errs)


def upsample(low, shape):
    """Bilinear interpolation of a cell-centred low-resolution image onto a finer cell-centred grid
    covering the same field (edge cells extrapolated linearly)."""
    from scipy.interpolate import RegularGridInterpolator

    h, w = low.shape
    ys, xs = (np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w
    f = RegularGridInterpolator((ys, xs), low.astype(np.float64), method="linear", bounds_error=False,
                                fill_value=None)
    yy, xx = np.meshgrid((np.arange(shape[0]) + 0.5) / shape[0], (np.arange(shape[1]) + 0.5) / shape[1],
                         indexing="ij")
    return f(np.stack([yy, xx], -1)).astype(np.float32)


# ---- references -----------------------------------------------------------------------------------------
def e1_reference(b, scene, res, params=None):
    """1st event, converged: stratified 16 points per detector (unbiased, exact occlusion), high spp."""
    return b.cached(f"ref_e1_{scene}_{res}", {
        "kind": "render", "scene": scene, "params": {"res": res, **(params or {})}, "events": 1,
        "spp": b.settings["references"]["e1_spp"],
        "options": {"detector_sampling": "stratified", "detector_samples": 16}, "seeds": [12345], "warm": False})


def e1_reference_quadrature(b, scene, res):
    """1st event for scenes where no detector can be occluded (checked): Appendix-A quadrature with
    96 triangles per detector, deterministic (the ``targets`` section holds it to the disc
    quadrature of :func:`elo_mitsuba.analysis.first_event.disc_integral`)."""
    return b.cached(f"ref_e1q_{scene}_{res}", {
        "kind": "render", "scene": scene, "params": {"res": res}, "events": 1, "spp": 1,
        "options": {"detector_sampling": "quadrature", "quadrature_triangles": 96}, "seeds": [1], "warm": False})


def e2_reference(b, scene, res_lo):
    """Events 2 (and more) on a coarse grid with many samples (they vary over tens of mm)."""
    return b.cached(f"ref_e2_{scene}_{res_lo}", {
        "kind": "render", "scene": scene, "params": {"res": res_lo}, "events": 2,
        "spp": b.settings["references"]["e2_spp"],
        "options": {"detector_sampling": "quadrature", "quadrature_triangles": 8}, "seeds": [777], "warm": False})


def athene_reference(b, res):
    """(e1 reference, e2 reference upsampled, total) at res x res for athene_flat."""
    e1 = e1_reference_quadrature(b, "athene_flat", res)
    lo = e2_reference(b, "athene_flat", b.settings["references"]["e2_res"])
    ref = {}
    for d in DETS:
        ref[f"{d}.e1"] = e1[d]
        ref[f"{d}.e2"] = upsample(lo[f"{d}.e2"], e1[d].shape)
        ref[d] = ref[f"{d}.e1"] + ref[f"{d}.e2"]
    return ref
