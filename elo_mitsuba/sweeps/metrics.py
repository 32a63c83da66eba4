"""Design metrics computed on a worker from one render: a registry, so that new metrics (and new
gradient methods, e.g. a model-based one) are one entry each.

A metric is a function ``f(ctx) -> value`` where ``ctx`` (:class:`PointContext`) holds the
render's channels and metadata and, when the spec names a test surface, the flat reference render
and the true gradient. Per-detector metrics return ``{detector: float}`` and become one data
variable with a ``detector`` dimension; scalar metrics return a float.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

#: Masked-pixel criterion without a test surface: a detector whose signal at a pixel is below this
#: fraction of its mean over the field receives (almost) no direct electrons there. The same
#: threshold as the gradient mask's ``detector_dark`` (analysis.gradient.MIN_CORRECTED), which
#: applies it to STSA-corrected images (flat plate = 1); the field mean stands in for the flat
#: (a median would be more robust but costs 10 ms per detector at 512^2, 10 % of a render).
DARK_FRACTION = 0.02
#: The units of a metric in the render's own units (the render metadata's ``units``, labelled by
#: :func:`elo_mitsuba.schema.signal_units`: N_d/N_0, or V with ``units = "voltage"``); the store
#: labels it with them (one source for the label).
SIGNAL_UNITS = "signal"


@dataclass
class PointContext:
    """What the metrics of one point may use."""

    channels: dict                      # the render's channels (float32 images)
    metadata: dict                      # RenderResult.metadata
    detectors: list[str]
    flat: dict | None = None            # flat reference channels (surface metrics)
    true_gradient: tuple | None = None  # (dzdx, dzdy) box-averaged over each pixel
    cache: dict = field(default_factory=dict)

    @property
    def field_mm(self):
        return tuple(self.metadata["field_mm"])

    def geometry(self):
        """(d_h, d_w) of Eq. 26 from the rendered detectors: mean height and mean horizontal
        distance from the z-axis of the four detectors (equal for a symmetric layout)."""
        geo = self.metadata["detectors"]
        c = np.array([geo[d]["center"] for d in ("right", "left", "back", "front")], dtype=float)
        return float(c[:, 2].mean()), float(np.hypot(c[:, 0], c[:, 1]).mean())


@dataclass(frozen=True)
class Metric:
    """One registered metric."""

    function: Callable[[PointContext], object]
    per_detector: bool
    units: str
    description: str
    needs_events: int = 1
    needs_surface: bool = False

    def unavailable(self, ctx: dict) -> str | None:
        """Why this metric cannot be computed for a sweep (``ctx``: ``events`` = the smallest
        events of any point, ``surface`` = whether a test surface is given, ``detectors``), or
        None."""
        if ctx["events"] < self.needs_events:
            return f"needs events >= {self.needs_events} (render.events, or every value of vary.events)"
        if self.needs_surface and not ctx["surface"]:
            return "needs a test surface ([surface] object = \"corrugated_sheet\" or height_map = ...)"
        if self.needs_surface and not {"right", "left", "back", "front"} <= set(ctx["detectors"]):
            return "needs the four detectors right, left, back, front (Eq. 26)"
        return None


def _moments(ctx, d):
    """Mean and mean square of detector ``d``'s image accumulated in float64, once per point
    (two reductions without a float64 copy: a tenth of numpy's std's CPU time at 1024^2; no BLAS
    dot, whose spinning threads would take the cores from the next render)."""
    key = ("moments", d)
    if key not in ctx.cache:
        v = ctx.channels[d].ravel()
        ctx.cache[key] = (float(np.add.reduce(v, dtype=np.float64)) / v.size,
                          float(np.add.reduce(np.square(v, dtype=np.float64))) / v.size)
    return ctx.cache[key]


def _signal_mean(ctx):
    return {d: _moments(ctx, d)[0] for d in ctx.detectors}


def _signal_spread(ctx):
    out = {}
    for d in ctx.detectors:
        mean, square = _moments(ctx, d)
        out[d] = float(np.sqrt(max(square - mean * mean, 0.0)) / mean) if mean > 0 else float("nan")
    return out


def _events2_share(ctx):
    out = {}
    for d in ctx.detectors:
        total = float(ctx.channels[d].sum(dtype=np.float64))
        first = float(ctx.channels[f"{d}.e1"].sum(dtype=np.float64))
        out[d] = (total - first) / total if total > 0 else float("nan")
    return out


def _masked_fraction(ctx):
    if ctx.flat is not None:
        return float(np.mean(_eq26(ctx).mask))
    dark = np.zeros(ctx.channels[ctx.detectors[0]].shape, dtype=bool)
    for d in ctx.detectors:
        img = ctx.channels[d]
        dark |= img <= DARK_FRACTION * _moments(ctx, d)[0]
    return float(dark.mean())


def _eq26(ctx):
    """The gradient of Eq. 26 (with STSA correction by the flat reference), computed once per point."""
    if "eq26" not in ctx.cache:
        from ..analysis import surface_gradient

        d_h, d_w = ctx.geometry()
        ctx.cache["eq26"] = surface_gradient(ctx.channels, ctx.flat, ctx.field_mm, d_h, d_w)
    return ctx.cache["eq26"]


def gradient_rms(dzdx, dzdy, mask, true_gradient) -> float:
    """RMS over the trusted pixels of |grad Z - grad Z_true| (mm/mm); NaN if none is trusted."""
    tx, ty = true_gradient
    keep = ~np.asarray(mask, dtype=bool)
    if not keep.any():
        return float("nan")
    err2 = (np.asarray(dzdx) - tx) ** 2 + (np.asarray(dzdy) - ty) ** 2
    return float(np.sqrt(err2[keep].mean()))


#: Gradient methods: name -> function(ctx) -> (dzdx, dzdy, mask). Each gives a metric
#: ``gradient_rms_<name>``. A model-based method registers here with :func:`register_gradient_method`.
GRADIENT_METHODS: dict[str, Callable] = {
    "eq26": lambda ctx: (_eq26(ctx).dzdx, _eq26(ctx).dzdy, _eq26(ctx).mask),
}

#: The registry: name -> :class:`Metric`, in the order they are stored.
METRICS: dict[str, Metric] = {
    "signal_mean": Metric(_signal_mean, True, SIGNAL_UNITS, "mean of the detector image over the scan field"),
    "signal_spread": Metric(_signal_spread, True, "1", "std / mean of the detector image over the field"),
    "events2_share": Metric(_events2_share, True, "1", "share of the signal from scattering events >= 2",
                            needs_events=2),
    "masked_fraction": Metric(_masked_fraction, False, "1",
                              "share of untrusted pixels: with a test surface the gradient mask of Eq. 26 "
                              "(analysis.surface_gradient); without one, pixels where some detector gets < "
                              f"{DARK_FRACTION:g} of its field mean"),
}


def register_gradient_method(name: str, function: Callable) -> None:
    """Add a gradient method ``function(ctx) -> (dzdx, dzdy, mask)`` and its metric
    ``gradient_rms_<name>`` (RMS error against the test surface's true gradient)."""
    GRADIENT_METHODS[name] = function
    METRICS[f"gradient_rms_{name}"] = Metric(
        lambda ctx, f=function: gradient_rms(*f(ctx), ctx.true_gradient), False, "mm/mm",
        f"RMS error of the {name} gradient against the true gradient, over trusted pixels",
        needs_surface=True)


register_gradient_method("eq26", GRADIENT_METHODS["eq26"])


def _model(ctx):
    """The model-based gradient (:mod:`elo_mitsuba.analysis.model_gradient`) with the point's
    rendered detectors as its geometry, computed once per point."""
    if "model" not in ctx.cache:
        from ..analysis.model_gradient import model_gradient
        from ..analysis.scan_geometry import ScanGeometry

        shape = next(iter(ctx.channels.values())).shape
        geo = ScanGeometry.from_metadata(ctx.metadata, shape, "sweep point")
        ctx.cache["model"] = model_gradient(ctx.channels, ctx.flat, geo)
    res = ctx.cache["model"]
    return res.dzdx, res.dzdy, res.mask


register_gradient_method("model", _model)


def applicable(ctx: dict) -> list[str]:
    """The metrics that apply to a sweep (default of ``keep.metrics``)."""
    return [name for name, m in METRICS.items() if m.unavailable(ctx) is None]


# ---- true gradients of test surfaces -------------------------------------------------------------
def true_gradient(surface: dict, shape, field_mm) -> tuple[np.ndarray, np.ndarray]:
    """The true gradient of a test surface averaged over each pixel of an image of ``shape``:
    (Z(x + w/2) - Z(x - w/2)) / w along x at the pixel's centre row (and likewise in y), which is
    what a pixel that straddles several flanks of the corrugated sheet sees on average."""
    from ..grid import pixel_coordinates, pixel_size

    x, y = pixel_coordinates(shape, field_mm)
    px, py = pixel_size(shape, field_mm)
    height = _height_function(surface)
    dzdx = (height(x + px / 2, y) - height(x - px / 2, y)) / px
    dzdy = (height(x, y + py / 2) - height(x, y - py / 2)) / py
    return dzdx, dzdy


def _height_function(surface: dict):
    if surface.get("object") == "corrugated_sheet":
        from ..objects.corrugated_sheet import corrugated_profile

        px, pz = corrugated_profile()
        return lambda x, y: np.interp(x, px, pz)
    if surface.get("object") == "melt_plate":
        from ..objects.melt_plate import melt_plate_height

        return melt_plate_height
    from scipy.interpolate import RegularGridInterpolator

    from ..heightmap import load_heightmap, pixel_centres

    h = load_heightmap(surface["height_map"])
    xs, ys = pixel_centres(h.shape, surface["pixel_mm"])
    # rows run towards -y (package orientation): the interpolator wants increasing axes
    ys = np.asarray(ys)
    order = np.argsort(ys)
    f = RegularGridInterpolator((ys[order], np.asarray(xs)), h[order], bounds_error=False, fill_value=None)
    return lambda x, y: f(np.stack([np.asarray(y), np.asarray(x)], -1))
