"""The inversion at 512² and 1500²: time to converge and peak memory, against the model gradient
(its start) on the same images, with the height errors; melt plate and steep hills."""

from __future__ import annotations

import json
import subprocess
import sys

from .harness import ROOT
from .report import fmt, table

TITLE = "Inversion: time to converge at 512² and 1500² (melt plate, steep hills)"

_JOB = r"""
import json, resource, sys, time, tempfile
import numpy as np
import elo_mitsuba as em
from elo_mitsuba.analysis.scan_geometry import ScanGeometry
from elo_mitsuba.analysis.model_gradient import model_gradient_refined
from elo_mitsuba.analysis.inversion import invert_heights, start_heights
em.ensure_variant()
surface, res = sys.argv[1], int(sys.argv[2])
names = ("right", "left", "back", "front")
if surface == "hills":
    from elo_mitsuba.objects.hills import hills_height as truth_fn, hills_mesh
    from elo_mitsuba.scene_files import write_object_scene
    d = tempfile.mkdtemp()
    scene, layout = write_object_scene(d, "h", hills_mesh(80.0, res, oversample=1 if res > 1024 else 3)), "zeta50"
else:
    from elo_mitsuba.mesh import mesh_surface_height
    from elo_mitsuba.objects import melt_plate as mp
    from elo_mitsuba.scene_files import scenes_dir
    H = np.load(scenes_dir() / "meshes" / "melt_plate_height.npy").astype(float)
    truth_fn = lambda x, y: mesh_surface_height(H, mp.PIXEL_SIZE_MM, x, y)
    scene, layout = "melt_plate", "zeta25"
obj = em.load_scene(scene, res=res, fwhm=0.27, layout=layout).render(quality="default", events=1, progress=False)
flat = em.load_scene("flat_plate", res=res, fwhm=0.27, layout=layout).render(quality="default", events=1, progress=False)
geo = ScanGeometry.from_metadata(obj.metadata, (res, res))
rng = np.random.default_rng(7)
img = {n: obj.channels[n] * (1 + 0.01 * rng.standard_normal((res, res))) for n in names}
fl = {n: flat.channels[n] * (1 + 0.01 * rng.standard_normal((res, res))) for n in names}
del obj, flat
truth = geo.landing_heights(truth_fn)
rmse = lambda h: float(np.sqrt(np.mean(((h - h.mean()) - (truth - truth.mean())) ** 2)))
t = time.perf_counter()
mg = model_gradient_refined(img, fl, geo)  # the start `invert` takes
t_mg = time.perf_counter() - t
inv = invert_heights(img, fl, geo, start=mg, fwhm_mm=0.27)
t_all = time.perf_counter() - t
print(json.dumps({"model_s": t_mg, "total_s": t_all, "steps": len(inv.history) - 1, "stopped": inv.stopped,
                  "model_um": 1000 * rmse(start_heights(mg, geo)), "inv_um": 1000 * rmse(inv.height),
                  "floor_um": 1000 * inv.height_error_rms,
                  "maxrss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2}))
"""


def _job(surface, res):
    out = subprocess.run([sys.executable, "-c", _JOB, surface, str(res)], check=True, cwd=ROOT, capture_output=True,
                         text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def run(b):
    cfg = b.settings.get("inversion", {"resolutions": (512, 1500)})
    rows = []
    for res in cfg["resolutions"]:
        for surface, label in (("melt", "melt plate (zeta25)"), ("hills", "steep hills (zeta50)")):
            r = _job(surface, res)
            rows.append([f"{res}²", label, fmt(r["model_s"]), fmt(r["total_s"] - r["model_s"]), fmt(r["total_s"]),
                         f"{r['steps']} ({r['stopped']})", fmt(r["maxrss_gb"]),
                         f"{r['model_um']:.1f} → {r['inv_um']:.1f}", f"{r['floor_um']:.1f}"])
            b.facts[f"inversion_{surface}_{res}_s"] = r["total_s"]
    from elo_mitsuba.analysis.height_solver import UNCERTAINTY_PROBES

    return ("Each in a fresh process (renders not timed): the model gradient (the start), then the inversion "
            f"(`invert_heights`, defaults: its time includes the local refinement, the step search and the "
            f"height_error, {UNCERTAINTY_PROBES} noise draws propagated through the solution), on images with the ATHENE beam blur (0.27 mm FWHM) and 1 % noise per "
            "pixel. Height RMSE against the truth at the landing points (mean removed):\n\n"
            + table(["size", "surface", "model gradient (s)", "inversion (s)", "total (s)", "steps",
                     "peak memory (GB)", "height RMSE (µm): start → inverted", "height_error RMS (µm)"], rows))
