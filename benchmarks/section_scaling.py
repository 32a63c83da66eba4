"""Scaling: render time and peak memory against resolution, spp and mesh size; a flat plate as a
rectangle against the same plate as a heavy mesh."""

from __future__ import annotations

import numpy as np

from .harness import CACHE, DETS, code_fingerprint, peak, preset_job, rel_error
from .report import fmt, median, pct, table

TITLE = "Scaling"


def mesh_scene(n_grid, flat=False):
    """A melt-plate scene (or a flat plate) whose mesh is the height map sampled on n_grid x n_grid
    points, cached in the bench cache (harness.CACHE); (scene path, triangles)."""
    from elo_mitsuba.mesh import heightmap_to_mesh, write_mesh
    from elo_mitsuba.objects.melt_plate import melt_plate_height
    from elo_mitsuba.scene_files import write_scene

    tag = f"{'flat' if flat else 'melt'}_{n_grid}"
    scene_path = CACHE / f"mesh_{tag}.xml"
    mesh_path = CACHE / f"mesh_{tag}.ply"
    stamp = CACHE / f"mesh_{tag}.code"  # regenerate when the mesh/melt-plate code changed
    if (not scene_path.exists() or not mesh_path.exists() or not stamp.exists()
            or stamp.read_text() != code_fingerprint()):
        p = 99.8 / n_grid
        c = -49.9 + (np.arange(n_grid) + 0.5) * p
        xx, yy = np.meshgrid(c, -c)
        z = np.zeros_like(xx) if flat else melt_plate_height(xx, yy)
        write_mesh(heightmap_to_mesh(z, p), mesh_path, overwrite=True)
        write_scene(scene_path, mesh_path, overwrite=True)
        stamp.write_text(code_fingerprint())
    return str(scene_path), 2 * (n_grid - 1) ** 2


def _block(caption, header, rows):
    """A caption over its table."""
    return f"{caption}\n\n{table(header, rows)}"


def _resolution(b, cfg):
    rows = []
    for res in cfg["resolutions"]:
        o = b.job({"kind": "render", "scene": "athene_flat", "params": {"res": res}, "events": 2,
                   **preset_job("default"), "options": {}, "seeds": [0, 1]})
        t = median(o["times"])
        rows.append([f"{res}²", fmt(t, 3), fmt(t / (res * res) * 1e9), fmt(peak(o))])
        b.facts.setdefault("res", []).append((res, t, peak(o)))
    return _block("Resolution (athene_flat, events 2, default preset, 1 spp): time should grow linearly in pixels.",
                  ["resolution", "time (s)", "ns per pixel", "peak RSS (MB)"], rows)


def _spp(b, cfg):
    rows = []
    res = cfg["spp_res"]
    for spp in cfg["spp_list"]:
        o = b.job({"kind": "render", "scene": "athene_flat", "params": {"res": res}, "events": 2, "spp": spp,
                   "options": {}, "seeds": [0]})
        t = median(o["times"])
        rows.append([spp, fmt(t, 3), fmt(t / (res * res * spp) * 1e9), fmt(peak(o))])
        b.facts.setdefault("spp", []).append((spp, t, peak(o)))
    return _block(f"Samples per pixel (athene_flat {res}², independent, events 2): time linear in spp, memory flat "
                  "(passes of at most 2^24 samples).", ["spp", "time (s)", "ns per sample", "peak RSS (MB)"], rows)


def _mesh_size(b, cfg):
    rows = []
    res = cfg["mesh_res"]
    for n in cfg["mesh_grids"]:
        path, tris = mesh_scene(n)
        o = b.job({"kind": "render", "scene": path, "params": {"res": res}, "events": 1,
                   **preset_job("default"), "options": {}, "seeds": [0, 1, 2]})
        rows.append([f"{tris:,}", fmt(o["load_s"], 3), fmt(median(o["times"]), 3), fmt(peak(o))])
        b.facts.setdefault("mesh", []).append((tris, median(o["times"]), peak(o)))
    return _block(f"Height-map mesh size (melt plate sampled on n x n points, {res}², events 1, default preset): "
                  "render time should grow sub-linearly in triangles (BVH).",
                  ["triangles", "scene load (s)", "render time (s)", "peak RSS (MB)"], rows)


def _flat_mesh(b, cfg):
    rows = []
    res = cfg["mesh_res"]
    path, tris = mesh_scene(cfg["flat_grid"], flat=True)
    ref = None
    for label, scene in (("rectangle (flat_plate.xml)", "flat_plate"), (f"height-map mesh, {tris:,} triangles", path)):
        o, ch = b.render("flatmesh", {"kind": "render", "scene": scene, "params": {"res": res}, "events": 2,
                                      **preset_job("default"), "options": {}, "seeds": [0, 1, 2]})
        if ref is None:
            ref = ch
        diff = max(rel_error(ch[d], ref[d])[0] for d in DETS)
        rows.append([label, fmt(o["load_s"], 3), fmt(median(o["times"]), 3), fmt(peak(o)), pct(diff),
                     "; ".join(o["notes"]) or "-"])
    return _block(f"A flat plate needs no heavy mesh ({res}², events 2, default preset):",
                  ["plate geometry", "scene load (s)", "render time (s)", "peak RSS (MB)",
                   "RMS difference to the rectangle", "integrator notes"], rows)


def run(b):
    """Measure the four scalings; the section's Markdown."""
    cfg = b.settings["scaling"]
    return "\n\n".join([_resolution(b, cfg), _spp(b, cfg), _mesh_size(b, cfg), _flat_mesh(b, cfg)])
