"""Analysis of detector images: STSA correction, gradients, height maps, design tools (numpy).

Pipeline (Renner et al. 2023): four detector images R, L, B, F and flat-plate images ->
:func:`stsa_correct` (Sec. 2.1.4) -> :func:`normalised_differences` M_x, M_y (Eq. 15) ->
:func:`gradient_from_differences` dZ/dx, dZ/dy (Eq. 26) -> :func:`integrate_gradient` Z(x, y).
:func:`surface_gradient` runs the first three steps and returns a :class:`GradientResult`.

Conventions: lengths in mm; the image orientation of :mod:`elo_mitsuba.grid`; pixel centres by
:func:`pixel_coordinates`; n_S = [-dZ/dx, -dZ/dy, 1] (Eq. 16); masks are True (1) = untrusted, and
untrusted pixels hold 0, never NaN/Inf.
"""

from .design import (
    detector_pq,
    image_statistics,
    layout_geometry,
    masked_normal_fraction,
    masking_lines,
    normal_histogram,
    pq_grid,
    reflectance_map,
)
from .geometry import (
    check_detector_geometry,
    detector_vectors,
    field_xy,
    geometry_from_metadata,
    masking_condition,
    pixel_axes,
    pixel_coordinates,
    pixel_size,
    zeta_deg,
)
from .gradient import (
    MASK_BITS,
    GradientResult,
    detector_masking,
    eq26_denominator,
    gradient_from_differences,
    raw_gradient,
    surface_gradient,
)
from .integrate import (
    METHODS as INTEGRATION_METHODS,
    height_gradient,
    integrate_dct,
    integrate_fft,
    integrate_gradient,
    integrate_masked,
)
from .point_detector import (
    beam_directions,
    eq24_differences,
    flat_plate_images,
    point_detector_images,
    point_solid_angle,
)
from .stsa import normalised_differences, normalized_differences, stsa_correct, sum_images

__all__ = [
    "INTEGRATION_METHODS", "MASK_BITS", "GradientResult", "beam_directions", "check_detector_geometry",
    "detector_masking", "detector_pq", "detector_vectors", "eq24_differences", "eq26_denominator",
    "field_xy", "flat_plate_images", "geometry_from_metadata", "gradient_from_differences",
    "height_gradient", "image_statistics", "integrate_dct", "integrate_fft", "integrate_gradient",
    "integrate_masked", "layout_geometry", "masked_normal_fraction", "masking_condition", "masking_lines",
    "normal_histogram", "normalised_differences", "normalized_differences", "pixel_axes", "pixel_coordinates",
    "pixel_size", "point_detector_images", "point_solid_angle", "pq_grid", "raw_gradient",
    "reflectance_map", "stsa_correct", "sum_images", "surface_gradient", "zeta_deg",
]
