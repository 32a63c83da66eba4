"""Sizes of the benchmarks: DEFAULT (the full run, about 40 minutes on 2 cores) and QUICK (minutes).

Resolutions are film widths (= heights) in pixels, ``spp`` beam samples per pixel. ``references``
are the converged images the errors are measured against (:mod:`benchmarks.harness`).
"""

from __future__ import annotations

DEFAULT = {
    "references": {"e1_spp": 256, "e2_res": 64, "e2_spp": 16384},
    "ceiling": {"res": 512, "spp": 16, "rounds": 2, "raw_repeat": 5, "skeleton_repeat": 7},
    "accuracy": {"res": 256, "independent_spp": (1, 4, 16, 64)},
    "events": {"res": 128, "spp": 1024, "cost_res": 512},
    "presets": {"res": 128},
    "targets": {"res": 1500, "rounds": 2, "reference_preset": True, "cli_qualities": ("default", "draft")},
    "path": {"res": 256, "spp_list": (16, 64, 256)},
    "scaling": {"resolutions": (256, 512, 1024, 1500, 2048, 3000), "spp_res": 1500,
                "spp_list": (1, 2, 4, 8, 16, 32), "mesh_grids": (72, 160, 320, 710, 1000), "mesh_res": 512,
                "flat_grid": 1000},
    "analysis": {"res": 1500, "rounds": 2},
    "inversion": {"resolutions": (512, 1500)},
}

QUICK = {
    "references": {"e1_spp": 64, "e2_res": 32, "e2_spp": 2048},
    "ceiling": {"res": 256, "spp": 4, "rounds": 1, "raw_repeat": 3, "skeleton_repeat": 3},
    "accuracy": {"res": 128, "independent_spp": (1, 4, 16)},
    "events": {"res": 64, "spp": 256, "cost_res": 256},
    "presets": {"res": 64},
    "targets": {"res": 512, "rounds": 1, "reference_preset": False, "cli_qualities": ("default",)},
    "path": {"res": 128, "spp_list": (16, 64)},
    "scaling": {"resolutions": (256, 512, 1024), "spp_res": 512, "spp_list": (1, 4, 16), "mesh_grids": (72, 225),
                "mesh_res": 256, "flat_grid": 225},
    "analysis": {"res": 256, "rounds": 1},
    "inversion": {"resolutions": (128,)},
}


def settings(quick: bool) -> dict:
    """The sizes of every section: :data:`QUICK` or :data:`DEFAULT`."""
    return QUICK if quick else DEFAULT
