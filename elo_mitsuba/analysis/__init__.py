"""Analysis of detector images: STSA correction, gradients, height maps, design tools (numpy).

Pipeline (Renner et al. 2023): four detector images R, L, B, F and flat-plate images ->
:func:`stsa_correct` (Sec. 2.1.4) -> :func:`normalised_differences` M_x, M_y (Eq. 15) ->
:func:`gradient_from_differences` dZ/dx, dZ/dy (Eq. 26) -> :func:`integrate_gradient` Z(x, y).
:func:`surface_gradient` runs the first three steps and returns a :class:`GradientResult`.

Conventions: lengths in mm; the image orientation of :mod:`elo_mitsuba.grid`; pixel centres by
:func:`pixel_coordinates`; n_S = [-dZ/dx, -dZ/dy, 1] (Eq. 16); masks are True (1) = untrusted, and
untrusted pixels hold 0, never NaN/Inf.

Importing this package imports none of its modules: each name is imported on first use (PEP 562
``__getattr__``), so that a command that needs one function (or only its help text) does not pay
for the others' imports (scipy, matplotlib).
"""

from __future__ import annotations

import importlib

#: Public name -> (module of this package, name there).
_EXPORTS = {
    **{n: ("reflectance", n) for n in (
        "detector_pq", "image_statistics", "layout_geometry", "masked_normal_fraction", "masking_lines",
        "normal_histogram", "pq_grid", "reflectance_map")},
    **{n: ("layout", n) for n in (
        "check_detector_geometry", "detector_vectors", "field_xy", "masking_condition", "pixel_axes",
        "pixel_coordinates", "pixel_size", "symmetric_layout", "zeta_deg")},
    **{n: ("gradient", n) for n in (
        "MASK_BITS", "GradientResult", "detector_masking", "eq26_denominator", "gradient_from_differences",
        "raw_gradient", "surface_gradient")},
    "INTEGRATION_METHODS": ("integrate", "METHODS"),
    **{n: ("integrate", n) for n in (
        "height_gradient", "integrate_dct", "integrate_fft", "integrate_gradient", "integrate_masked",
        "integrate_robust")},
    **{n: ("point_detector", n) for n in (
        "beam_directions", "eq24_differences", "flat_plate_images", "point_detector_images", "point_solid_angle")},
    **{n: ("precision", n) for n in ("SignalNoise", "design_metrics", "gradient_bound")},
    **{n: ("stsa", n) for n in ("mean_flat", "normalised_differences", "normalized_differences", "stsa_correct", "sum_images")},
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    try:
        module, attr = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(f".{module}", __name__), attr)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
