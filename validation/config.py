"""Settings of the studies: DEFAULT (~10 min on 2 cores) and QUICK (~1 min, CI).

Resolutions are film widths (= heights) in pixels; ``spp`` beam samples per pixel; fields in mm.
Per-pixel relative noise of a 1st-event image is about 2.4 %/sqrt(spp) (independent sampler, one
detector sample); the convergence study measures it for every event order.
"""

from __future__ import annotations

DEFAULT = {
    "checks": {
        "sym_res": 128, "sym_spp": 1024,          # four-detector rotation symmetry (flat plate)
        "energy_thetas": (0, 10, 20, 30, 40, 50, 60, 70, 80, 85, 89),
        "energy_nodes": (512, 1024),               # (cos theta_o, azimuth) quadrature nodes
    },
    "stsa": {"res": 200, "spp": 2048},             # athene_flat, events = 2 (two halves of spp/2)
    "corrugated": {"field": 80.0, "res": 1536, "spp": 8, "band_mm": 3.0},
    "reflectance": {"n": 401},
    # melt-plate resolutions keep pixel centres off the mesh's 0.2 mm vertex grid, where beam rays
    # could slip through a mesh that is not watertight (row E7; validation.tools.check_melt_resolution)
    "masking": {"field": 16.0, "res": 384, "spp": 64, "relief_scale": 6.0, "hist_bins": 161},
    "melt_plate": {
        "full_res": 500, "full_spp": 64,           # Fig. 6 and the height reconstruction, 80 mm
        "zoom_field": 20.0, "zoom_res": 480, "beam_spp": 256,  # Figs. 7, 11
        "material_res": 250, "material_spp": 16,   # M_x with another material
    },
    "convergence": {
        "res": 32, "events": 3, "ref_spp": 65536,
        "spp_list": (1, 4, 16, 64, 256, 1024, 4096), "ds_list": (1, 2, 4, 8), "ds_spp": 1024,
        "quad_res": 32,
        # detector-sampling strategies (when the integrator offers them)
        "strategy_spp": 64, "strategy_samples": 4, "quadrature_triangles": (4, 8, 16, 64, 256),
    },
    "topography": {"res": 512, "cal_res": 1024},   # sawtooth plate; the calibration's flat
    "inversion": {"melt_res": 512, "hills_res": 256},
    "design": {"res": 128, "spp": 16},             # flat plate twice: the bound vs the model fit
    # issue 25: rough layer with pores and bumps, stepped layer, hills, melt plate
    "defects": {"surfaces": ("rough", "steps", "hills", "melt"),
                "res": {"rough": 400, "steps": 400, "hills": 256, "melt": 512}},
}

QUICK = {
    "checks": {"sym_res": 16, "sym_spp": 64, "energy_thetas": (0, 30, 60, 85), "energy_nodes": (256, 512)},
    "stsa": {"res": 32, "spp": 64},
    "corrugated": {"field": 20.0, "res": 256, "spp": 2, "band_mm": 2.0},
    "reflectance": {"n": 121},
    "masking": {"field": 16.0, "res": 50, "spp": 4, "relief_scale": 6.0, "hist_bins": 81},
    "melt_plate": {
        "full_res": 96, "full_spp": 4,
        "zoom_field": 20.0, "zoom_res": 96, "beam_spp": 8,
        "material_res": 48, "material_spp": 4,
    },
    "convergence": {
        "res": 8, "events": 3, "ref_spp": 1024,
        "spp_list": (1, 4, 16, 64), "ds_list": (1, 2, 4), "ds_spp": 16,
        "quad_res": 8,
        "strategy_spp": 8, "strategy_samples": 4, "quadrature_triangles": (4, 8, 16),
    },
    "topography": {"res": 160, "cal_res": 256},
    "inversion": {"melt_res": 64, "hills_res": 64},
    "design": {"res": 48, "spp": 16},
    "defects": {"surfaces": ("steps",), "res": {"steps": 64}},
}


def settings(quick: bool) -> dict:
    return QUICK if quick else DEFAULT
