"""Height steps: the model gradient + integration across cliffs, least squares against the robust
(Cauchy) integration, and the smooth surfaces it must not make worse.

The stepped layer (:mod:`elo_mitsuba.objects.stepped_layer`: parts raised and sunk by 0.1-1 mm
beside the powder, a dome on some, 10 µm roughness) is rendered as the inversion study renders the
hills (0.27 mm FWHM beam, layout zeta50, ``--quality default``, 1st event, seed 3), with 1 %
Gaussian noise on object and flat; the model gradient (:func:`~elo_mitsuba.analysis.model_gradient.
model_gradient`) is integrated by :func:`elo_mitsuba.analysis.chain.heights` (the ``reconstruct``
command's computation) with each solver. Truth: the layer at the beam's landing points.

Figures per solver: the height RMSE over the measured pixels (means removed), the RMSE over the
relief more than 1 mm from any cliff (the error least squares spreads), and each step as the height
map shows it (:func:`~elo_mitsuba.objects.stepped_layer.step_height`), against the same measure of
the truth. The hills (zeta50, 256²) and the melt plate (512²) check that the robust solver keeps
least squares' figures on smooth surfaces.

Run: ``python -m validation.study_steps [--res 400] [--json out.json]`` (about a minute on two
cores); :func:`measure_reconstruct` and :func:`measure_smooth` return the numbers for a report row.
"""

from __future__ import annotations

import functools
import tempfile
import time
from pathlib import Path

import numpy as np

TITLE = "Height steps: discontinuity-preserving integration of the model gradient (stepped layer, hills, melt plate)"
NAMES = ("right", "left", "back", "front")
#: The solvers compared: ``reconstruct --method`` values, and ``start``: the inversion's start
#: (:func:`elo_mitsuba.analysis.inversion.start_heights`: masked slopes filled from their
#: neighbours, then DCT).
METHODS = ("start", "dct", "masked", "robust")


def _rmse(h, truth, ok=None):
    ok = np.ones(h.shape, bool) if ok is None else ok
    e = (h - truth)[ok]
    e = e - e.mean()
    return float(np.sqrt(np.mean(e ** 2)))


@functools.lru_cache(maxsize=None)
def _render(scene, res, layout):
    import elo_mitsuba as em

    s = em.load_scene(scene, res=res, fwhm=0.27, layout=layout)
    return s.render(quality="default", events=1, seed=3, progress=False)


@functools.lru_cache(maxsize=None)
def _mesh_scene(kind, res):
    """A scene file of a generated surface (written once per process into a temporary folder)."""
    from elo_mitsuba.scene_files import write_object_scene

    if kind == "stepped":
        from elo_mitsuba.objects.stepped_layer import stepped_mesh as make
    else:
        from elo_mitsuba.objects.hills import hills_mesh as make
    folder = Path(tempfile.mkdtemp(prefix=f"elo-steps-{kind}-"))
    return str(write_object_scene(folder, kind, make(80.0, res), overwrite=True))


def model_gradient_case(scene, truth_fn, res, *, layout="zeta50", noise=0.01, seed=7):
    """Render ``scene`` and the flat plate, add ``noise`` (relative, Gaussian) to both, and fit the
    model gradient. Returns the gradient result, the geometry and the truth (mm) at the landing
    points."""
    from elo_mitsuba.analysis.model_gradient import model_gradient
    from elo_mitsuba.analysis.scan_geometry import ScanGeometry

    obj = _render(scene, res, layout)
    flat = _render("flat_plate", res, layout)
    shape = obj.channels["right"].shape
    geo = ScanGeometry.from_metadata(obj.metadata, shape)
    rng = np.random.default_rng(seed)
    img = {n: obj.channels[n] * (1 + noise * rng.standard_normal(shape)) for n in NAMES}
    fl = {n: flat.channels[n] * (1 + noise * rng.standard_normal(shape)) for n in NAMES}
    return model_gradient(img, fl, geo), geo, geo.landing_heights(truth_fn)


def integrate_case(grad, geo, method):
    """``reconstruct``'s computation (:func:`elo_mitsuba.analysis.chain.heights`) on a gradient
    result with one solver; returns the height, its mask and the seconds it took."""
    from elo_mitsuba.analysis.chain import heights

    t0 = time.perf_counter()
    rec = heights(grad.dzdx, grad.dzdy, geo.field_mm, mask=grad.mask, method=method,
                  projection=geo.projection, work_distance_mm=geo.work_distance_mm)
    return rec["height"], rec["mask"], time.perf_counter() - t0


def measure_reconstruct(res: int = 400, *, noise: float = 0.01, seed: int = 7, methods=METHODS,
                        far_mm: float = 1.0) -> dict:
    """The stepped layer: height RMSE overall and far from the cliffs, and every step recovered,
    per solver.

    Returns
    -------
    dict
        ``res``, ``masked_fraction`` (of the model gradient), ``truth_steps`` (each step as
        :func:`step_height` measures the truth), ``nominal_steps``, ``connected`` (per patch:
        whether a trusted 4-connected path joins its interior to the powder around it), and per
        solver a dict with ``rmse_mm`` (over the pixels with a height), ``rmse_far_mm`` (those more
        than ``far_mm`` from every cliff), ``rmse_far_regionwise_mm`` and
        ``p95_far_regionwise_mm`` (the same pixels, each patch's interior and the powder with
        their own mean removed: the error spread over the relief, without the steps' offsets;
        RMS and 95th percentile of |error|), ``steps_mm`` (recovered, same order as
        :func:`steps`), ``step_ratio`` (recovered / truth's) and ``seconds`` (integration alone).
    """
    from scipy import ndimage

    from elo_mitsuba.objects.stepped_layer import cliff_distance, step_height, stepped_height, steps

    grad, geo, truth = model_gradient_case(_mesh_scene("stepped", res), stepped_height, res, noise=noise, seed=seed)
    x, y = geo.aim_points()
    patches = steps()
    near = np.min([np.abs(cliff_distance(p, x, y)) for p in patches], axis=0)
    truth_steps = [step_height(truth, geo.field_mm, p) for p in patches]
    out = {"res": res, "noise": noise, "masked_fraction": float(np.mean(grad.mask)),
           "nominal_steps": [p["height_mm"] for p in patches], "names": [p["name"] for p in patches],
           "truth_steps": truth_steps}
    # a patch whose cliff is masked all round has no trusted path to the powder: its height
    # relative to the rest is not in the gradient ('masked' and 'robust' give it its own mean)
    labels, _ = ndimage.label(~grad.mask)
    out["connected"] = []
    for p in patches:
        d = cliff_distance(p, x, y)
        inner, ring = set(np.unique(labels[d < -1.0])), set(np.unique(labels[(d > 1.0) & (d < 3.0)]))
        out["connected"].append(bool((inner & ring) - {0}))
    # the relief's regions: each patch's interior and the powder, away from every cliff
    region = np.zeros(truth.shape, int)
    for k, p in enumerate(patches):
        region[cliff_distance(p, x, y) < 0] = k + 1
    far = near > far_mm
    for method in methods:
        if method == "start":
            from elo_mitsuba.analysis.inversion import start_heights

            t0 = time.perf_counter()
            h, mask = start_heights(grad, geo), np.zeros(truth.shape, bool)
            seconds = time.perf_counter() - t0
        else:
            h, mask, seconds = integrate_case(grad, geo, method)
        ok = ~mask
        rec = [step_height(h, geo.field_mm, p, mask=mask) for p in patches]
        # the error that least squares spreads: per region with its own mean removed (a step
        # recovered short shifts a whole region, which rmse_far_mm counts and this does not)
        sq = []
        for r in np.unique(region[far & ok]):
            e = (h - truth)[far & ok & (region == r)]
            sq.append((e - e.mean()) ** 2)
        sq = np.concatenate(sq)
        out[method] = {"rmse_mm": _rmse(h, truth, ok), "rmse_far_mm": _rmse(h, truth, ok & far),
                       "rmse_far_regionwise_mm": float(np.sqrt(np.mean(sq))),
                       "p95_far_regionwise_mm": float(np.sqrt(np.percentile(sq, 95))),
                       "steps_mm": rec, "step_ratio": [r / t for r, t in zip(rec, truth_steps)],
                       "seconds": seconds, "no_height": float(np.mean(mask))}
    return out


def measure_smooth(*, hills_res: int = 256, melt_res: int = 512, noise: float = 0.01, seed: int = 7,
                   methods=METHODS) -> dict:
    """Height RMSE per solver on the smooth surfaces: the hills (zeta50) and the melt plate."""
    from elo_mitsuba.mesh import mesh_surface_height
    from elo_mitsuba.objects import melt_plate as mp
    from elo_mitsuba.objects.hills import hills_height
    from elo_mitsuba.scene_files import scenes_dir

    from .tools import check_melt_resolution

    check_melt_resolution(80.0, melt_res)
    melt_heights = np.load(scenes_dir() / "meshes" / "melt_plate_height.npy").astype(float)

    def melt_truth(x, y):
        return mesh_surface_height(melt_heights, mp.PIXEL_SIZE_MM, x, y)

    out = {}
    for name, scene, truth_fn, res in (("hills", _mesh_scene("hills", hills_res), hills_height, hills_res),
                                       ("melt_plate", "melt_plate", melt_truth, melt_res)):
        grad, geo, truth = model_gradient_case(scene, truth_fn, res, noise=noise, seed=seed)
        out[name] = {"res": res, "masked_fraction": float(np.mean(grad.mask))}
        for method in methods:
            if method == "start":
                continue
            h, mask, seconds = integrate_case(grad, geo, method)
            out[name][method] = {"rmse_mm": _rmse(h, truth, ~mask), "seconds": seconds}
    return out


def synthetic_gradient(n: int, *, clip: float = 0.5, noise: float = 0.01, shadow_mm: float = 1.0, seed: int = 1):
    """A model-gradient-like field of the stepped layer at n x n without rendering: the exact
    gradient of the layer (walls one pixel wide), slopes clipped at ``clip`` (the model's fit
    saturates on a wall: the cliff is truncated), ``noise`` added, and a shadow of ``shadow_mm``
    masked at the foot of every wall facing -x. Returns dzdx, dzdy, mask and the truth (mm)."""
    from elo_mitsuba.analysis.integrate import height_gradient
    from elo_mitsuba.grid import pixel_coordinates
    from elo_mitsuba.objects.stepped_layer import cliff_distance, stepped_height, steps

    x, y = pixel_coordinates((n, n), 80.0)
    truth = stepped_height(x, y)
    gx, gy = height_gradient(truth, 80.0)
    rng = np.random.default_rng(seed)
    gx = np.clip(gx, -clip, clip) + noise * rng.standard_normal(gx.shape)
    gy = np.clip(gy, -clip, clip) + noise * rng.standard_normal(gy.shape)
    mask = np.zeros((n, n), bool)
    for p in steps():
        d = cliff_distance(p, x, y)
        mask |= (d > 0) & (d < shadow_mm) & (x < p["centre"][0])
    return gx, gy, mask, truth


def timing(sizes=(400, 1500), *, methods=("masked", "robust")) -> dict:
    """Seconds of the solvers on :func:`synthetic_gradient` of each size (what they cost, not what
    they recover; run with OPENBLAS_NUM_THREADS=1 on a shared machine, as the CLI does)."""
    from elo_mitsuba.analysis.integrate import integrate_gradient

    out = {}
    for n in sizes:
        gx, gy, mask, _ = synthetic_gradient(n)
        out[n] = {}
        for method in methods:
            t0 = time.perf_counter()
            integrate_gradient(gx, gy, 80.0, method=method, mask=mask)
            out[n][method] = time.perf_counter() - t0
    return out


def main(argv=None):
    import argparse
    import json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--res", type=int, default=400, help="stepped layer's resolution (default 400)")
    p.add_argument("--noise", type=float, default=0.01, help="relative Gaussian noise on object and flat (default 0.01)")
    p.add_argument("--hills-res", type=int, default=256)
    p.add_argument("--melt-res", type=int, default=512)
    p.add_argument("--no-smooth", action="store_true", help="skip the hills and the melt plate")
    p.add_argument("--timing", action="store_true", help="also time the solvers at 400² and 1500²")
    p.add_argument("--json", help="write the numbers here")
    args = p.parse_args(argv)
    import elo_mitsuba

    elo_mitsuba.ensure_variant()
    result = {"steps": measure_reconstruct(args.res, noise=args.noise)}
    s = result["steps"]
    print(f"stepped layer {s['res']}², noise {100 * s['noise']:g} %: model gradient masked "
          f"{100 * s['masked_fraction']:.1f} %")
    for m in METHODS:
        r = s[m]
        print(f"  {m:7s} RMSE {1000 * r['rmse_mm']:.1f} µm, >1 mm from cliffs {1000 * r['rmse_far_mm']:.1f} µm "
              f"(per region {1000 * r['rmse_far_regionwise_mm']:.2f} µm, 95 % within "
              f"{1000 * r['p95_far_regionwise_mm']:.1f} µm), {r['seconds']:.2f} s; steps "
              + ", ".join(f"{v:+.3f}" for v in r["steps_mm"]))
    print("  truth   steps " + ", ".join(f"{v:+.3f}" + ("" if c else "*") for v, c in zip(s["truth_steps"], s["connected"]))
          + "   (* masked all round: no trusted path to the powder)")
    if not args.no_smooth:
        result["smooth"] = measure_smooth(hills_res=args.hills_res, melt_res=args.melt_res, noise=args.noise)
        for name, r in result["smooth"].items():
            print(f"{name} {r['res']}²: " + ", ".join(f"{m} {1000 * r[m]['rmse_mm']:.2f} µm ({r[m]['seconds']:.2f} s)"
                                                   for m in METHODS if m in r))
    if args.timing:
        result["timing"] = timing()
        for n, r in result["timing"].items():
            print(f"timing {n}²: " + ", ".join(f"{m} {t:.1f} s" for m, t in r.items()))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
