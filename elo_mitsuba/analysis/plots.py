"""PNG previews with matplotlib's Agg canvas (no display, no pyplot global state) and CMasher maps.

Scan images are drawn seen from above with +y up (row 0 at the top, ``origin="upper"``), axes in mm.
Masked (untrusted) pixels are painted in one flat grey that no colour map of the package contains,
with a legend entry. Signed images get a colour scale symmetric about 0, per panel, never narrower
than the quantity's noise floor (a flat panel must not stretch its noise over the whole map: its
title says so). Every writer refuses to replace an existing file unless ``overwrite=True``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import EloInputError
from ..files import atomic_write, check_output
from ..grid import field_xy

# The palette of every figure of the package and of validation/: one perceptually uniform CMasher
# map per role (names as registered by ``import cmasher``), diverging maps for signed quantities,
# drawn with a colour scale symmetric about 0 so that 0 sits at the map's centre.
#: Detector images, N_d/N_0 (sequential, dark = few electrons).
CMAP_INTENSITY = "cmr.arctic"
#: Signed quantities: M_x, M_y, gradients (diverging, light centre at 0). ColorBrewer's RdBu
#: (reversed: blue < 0 < red): its two ends differ in hue along the blue-yellow axis that
#: red-green colour-blind readers keep (ColorBrewer rates it colour-blind safe), where CMasher's
#: fusion ends in two dark purples that nobody tells apart.
CMAP_DIVERGING = "RdBu_r"
#: Height maps Z (sequential).
CMAP_HEIGHT = "cmr.rainforest"
#: Histograms and reflectance maps (sequential, black at 0).
CMAP_SEQUENTIAL = "cmr.ember"
#: Signed errors and differences (diverging, dark centre at 0: small errors fade out).
CMAP_ERROR = "cmr.iceburn"
#: Masked (untrusted) pixels, one flat mid grey: at least 0.3 (RGB distance) from every colour of
#: the maps above, so a masked pixel never reads as a value (the green of Fig. 14b is in
#: CMAP_HEIGHT).
MASK_COLOUR = "#808080"
#: Smallest half-range of a gradient panel's colour scale (mm/mm, a slope of 0.6 deg): the noise
#: of a flat plate's gradient (quadrature and shot noise) is below it, so a flat panel stays light.
GRADIENT_MIN_SCALE = 0.01


def new_figure(ncols=1, width=5.2, height=4.4):
    import cmasher  # noqa: F401  (registers the cmr.* colour maps)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * ncols, height), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, ncols, squeeze=False)[0]
    return fig, axes


def save_figure(fig, path, overwrite):
    path = check_output(path, (".png",), overwrite=overwrite, what="figure")
    return atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=120))


def _extent(shape, field_mm):
    fx, fy = field_xy(field_mm, shape)
    return (-fx / 2, fx / 2, -fy / 2, fy / 2)


def colour_limits(image, *, mask=None, symmetric=False, clip_percent=0.5, min_scale=0.0):
    """The colour scale ``(lo, hi, note)`` of an image as :func:`preview_image` draws it.

    ``lo``/``hi`` span the ``clip_percent`` .. ``100 - clip_percent`` percentiles of the finite
    unmasked values (a few hot pixels do not flatten the scale); ``symmetric`` makes them
    ``-m, m`` with ``m`` the larger magnitude, at least ``min_scale``. ``note`` is text for the
    title when ``min_scale`` held the scale (the values are below it: noise level), else "".
    """
    img = np.asarray(image, dtype=float)
    shown = img if mask is None else np.where(mask, np.nan, img)
    vals = shown[np.isfinite(shown)]
    lo, hi = np.percentile(vals, [clip_percent, 100 - clip_percent]) if vals.size else (0.0, 1.0)
    note = ""
    if symmetric:
        m = max(abs(float(lo)), abs(float(hi)))
        if m < min_scale:
            top = float(np.max(np.abs(vals))) if vals.size else 0.0
            note = f"noise level: |value| \u2264 {top:.2g}, scale \u00b1{min_scale:g}"
            m = min_scale
        hi = max(m, 1e-12)
        lo = -hi
    if hi <= lo:
        hi = lo + 1e-12
    return float(lo), float(hi), note


def _draw_image(fig, ax, image, field_mm, *, title, label, cmap, symmetric=False, mask=None, clip_percent=0.5,
                min_scale=0.0):
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    img = np.asarray(image, dtype=float)
    shown = np.where(np.isfinite(img), img, np.nan)
    if mask is not None:
        shown = np.where(mask, np.nan, shown)
    lo, hi, note = colour_limits(shown, symmetric=symmetric, clip_percent=clip_percent, min_scale=min_scale)
    if note:
        title = f"{title}\n({note})"
    ext = _extent(img.shape, field_mm)
    im = ax.imshow(shown, cmap=cmap, vmin=lo, vmax=hi, extent=ext, origin="upper", interpolation="nearest")
    if mask is not None and np.any(mask):
        overlay = np.where(mask, 1.0, np.nan)
        ax.imshow(overlay, cmap=ListedColormap([MASK_COLOUR]), extent=ext, origin="upper",
                  interpolation="nearest", vmin=0, vmax=1)
        ax.legend(handles=[Patch(color=MASK_COLOUR, label=f"masked ({100 * np.mean(mask):.1f} %)")],
                  loc="lower right", fontsize=8, framealpha=0.8)
    ax.set_xlabel("x / mm")
    ax.set_ylabel("y / mm")
    ax.set_title(title, fontsize=10)
    cb = fig.colorbar(im, ax=ax, shrink=0.9)
    cb.set_label(label)
    return im


def preview_image(image, field_mm, path, *, title="", label="", cmap=CMAP_INTENSITY, symmetric=False,
                  mask=None, clip_percent=0.5, overwrite=False) -> Path:
    """One image with colour bar (``label`` gives the unit), axes in mm, masked pixels grey.

    The colour scale spans the ``clip_percent`` .. ``100 - clip_percent`` percentiles."""
    fig, (ax,) = new_figure()
    _draw_image(fig, ax, image, field_mm, title=title, label=label, cmap=cmap, symmetric=symmetric, mask=mask,
                clip_percent=clip_percent)
    return save_figure(fig, path, overwrite)


def preview_gradient(dzdx, dzdy, field_mm, path, *, mask=None, title="Surface gradient (Eq. 26)",
                     overwrite=False) -> Path:
    """dZ/dx and dZ/dy side by side, mm/mm: each panel its own colour scale, symmetric about 0 and
    at least :data:`GRADIENT_MIN_SCALE` (a panel at noise level says so in its title)."""
    fig, axes = new_figure(2)
    for ax, img, name in ((axes[0], dzdx, "dZ/dx"), (axes[1], dzdy, "dZ/dy")):
        _draw_image(fig, ax, img, field_mm, title=f"{title}: {name}", label=f"{name} / (mm/mm)",
                    cmap=CMAP_DIVERGING, symmetric=True, mask=mask, min_scale=GRADIENT_MIN_SCALE)
    return save_figure(fig, path, overwrite)


def preview_height(height, field_mm, path, *, mask=None, title="Height map", overwrite=False, warning=None) -> Path:
    """Height map Z(x, y) in mm (relative: up to a constant); ``title`` names how it was made (the
    method), a second line the quantity, unit and the range over the measured pixels, a third
    ``warning`` when given (what the reconstruction's quality figures warn about)."""
    h = np.asarray(height, dtype=float)
    valid = np.isfinite(h) if mask is None else np.isfinite(h) & ~np.asarray(mask, bool)
    span = float(np.ptp(h[valid])) if valid.any() else 0.0
    title = f"{title}\nZ in mm, relative (zero mean); range {span:.3g} mm"
    if warning:
        title += f"\nwarning: {warning}"
    return preview_image(h, field_mm, path, title=title,
                         label="Z / mm (relative)", cmap=CMAP_HEIGHT, mask=mask, clip_percent=0.0,
                         overwrite=overwrite)


def _pq_extent(p, q):
    return (float(p.min()), float(p.max()), float(q.min()), float(q.max()))


def plot_reflectance_maps(p, q, g_full, g_diffuse, masked, d_pq, path, *, title="", overwrite=False) -> Path:
    """Figs. 12-13: full g_BSE (left) and diffuse part (right) over (p, q); masked region hatched,
    detector direction marked with a white cross. Inputs from :func:`~.design.reflectance_map`."""
    from matplotlib import rc_context

    fig, axes = new_figure(2)
    ext = _pq_extent(p, q)
    vmax = float(max(np.max(g_full), np.max(g_diffuse), 1e-12))
    for ax, g, name in ((axes[0], g_full, "full $g_{BSE}$ (Eq. 13)"), (axes[1], g_diffuse, "diffuse part only")):
        im = ax.imshow(g, cmap=CMAP_SEQUENTIAL, extent=ext, origin="upper", vmin=0, vmax=vmax,
                       interpolation="bilinear")
        ax.contour(p, q, g, levels=8, colors="k", linewidths=0.5, alpha=0.6)
        if np.any(masked):
            # Hatch the exact half-plane p d_x + q d_y + 1 <= 0 (a straight border, not the pixel
            # staircase of ``masked``), in white: there g_BSE = 0, the dark end of the map.
            side = p * d_pq[0] + q * d_pq[1] + 1.0
            with rc_context({"hatch.color": "w", "hatch.linewidth": 0.8}):
                hatch = ax.contourf(p, q, side, levels=[min(float(side.min()), -1.0) - 1.0, 0.0],
                                    colors="none", hatches=["///"])
                hatch.set_edgecolor("w")
                hatch.set_linewidth(0.0)
            ax.contour(p, q, side, levels=[0.0], colors="w", linewidths=1.0)
        ax.plot([d_pq[0]], [d_pq[1]], marker="x", color="w", markersize=10, mew=2.5)
        ax.set_xlabel("$p = n_{Sx} = -\\partial Z/\\partial x$")
        ax.set_ylabel("$q = n_{Sy} = -\\partial Z/\\partial y$")
        ax.set_title(name)
        ax.set_aspect("equal")
        cb = fig.colorbar(im, ax=ax, shrink=0.9)
        cb.set_label("$g_{BSE}$ / sr$^{-1}$")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path, overwrite)


def plot_normal_histogram(hist, p_edges, q_edges, path, *, lines: Mapping | None = None,
                          title="Surface normals n_S = [p, q, 1]", overwrite=False) -> Path:
    """Fig. 14a: log-scaled 2-D histogram of normals with the masking lines of detector layouts.

    ``lines`` is :func:`~.design.masking_lines` output ``{label: {detector: (d_x, d_y)}}``.
    """
    from matplotlib.colors import LogNorm

    fig, (ax,) = new_figure(1, width=6.0, height=5.2)
    h = np.asarray(hist, dtype=float)
    shown = np.where(h > 0, h, np.nan)
    vmax = max(np.nanmax(shown) if np.isfinite(shown).any() else 1.0, 1.0)
    im = ax.imshow(shown, cmap=CMAP_SEQUENTIAL, norm=LogNorm(vmin=1, vmax=vmax), origin="upper",
                   extent=(p_edges[0], p_edges[-1], q_edges[0], q_edges[-1]), interpolation="nearest")
    styles = ["-", "--", ":", "-."]
    t = np.linspace(min(p_edges[0], q_edges[0]), max(p_edges[-1], q_edges[-1]), 2)
    for k, (label, dets) in enumerate((lines or {}).items()):
        for j, (det, (dx, dy)) in enumerate(dets.items()):
            # p d_x + q d_y + 1 = 0; the four detectors of Eq. 17 have d_x = 0 or d_y = 0.
            kw = dict(color=f"C{k}", ls=styles[k % 4], lw=1.2, label=(f"zeta = {label} deg" if isinstance(label, (int, float)) else str(label)) if j == 0 else None)
            if abs(dx) >= abs(dy):
                ax.plot(-(1 + dy * t) / dx, t, **kw)
            else:
                ax.plot(t, -(1 + dx * t) / dy, **kw)
    ax.set_xlim(p_edges[0], p_edges[-1])
    ax.set_ylim(q_edges[0], q_edges[-1])
    ax.set_xlabel("$p = n_{Sx}$")
    ax.set_ylabel("$q = n_{Sy}$")
    ax.set_title(title)
    if lines:
        ax.legend(loc="upper right", fontsize=8)
    cb = fig.colorbar(im, ax=ax, shrink=0.9)
    cb.set_label("pixels per bin")
    return save_figure(fig, path, overwrite)


def plot_image_histograms(stats: Mapping[str, dict], path, *, unit="N_d/N_0", title="Image histograms",
                          overwrite=False) -> Path:
    """Fig. 15: histograms of several images (``{label: image_statistics(...)}``), mean dashed."""
    fig, (ax,) = new_figure(1, width=6.5, height=4.2)
    for k, (label, s) in enumerate(stats.items()):
        edges = np.asarray(s["bin_edges"])
        ax.stairs(s["hist"], edges, color=f"C{k}",
                  label=f"{label}: mean {s['mean']:.3g}, std {s['std']:.2g}, masked {100 * s['masked_fraction']:.1f} %")
        ax.axvline(s["mean"], color=f"C{k}", ls="--", lw=1)
    ax.set_xlabel(f"intensity / {unit}")
    ax.set_ylabel("pixels")
    ax.set_title(title)
    ax.legend(fontsize=8)
    return save_figure(fig, path, overwrite)


def preview_detectors(channels: Mapping[str, np.ndarray], field_mm, path, *, unit="N_d/N_0", title="",
                      overwrite=False) -> Path:
    """The total image of every detector side by side (one colour bar each, axes in mm).

    ``channels`` maps detector ids to images; per-event channels (``<id>.e<k>``) are skipped.
    """
    names = [n for n in channels if "." not in n]
    if not names:
        raise EloInputError(f"{path}: no detector channels to preview")
    fig, axes = new_figure(len(names), width=4.4, height=3.9)
    for ax, name in zip(axes, names):
        _draw_image(fig, ax, channels[name], field_mm, title=f"{title}{name}", label=unit,
                    cmap=CMAP_INTENSITY, clip_percent=0.0)
    return save_figure(fig, path, overwrite)
