"""Matplotlib (Agg) helpers: image panels in mm with colour bars, saving.

The colour maps are the package's palette (:mod:`elo_mitsuba.analysis.plots`), so that the
validation figures and the CLI previews draw each quantity alike.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import cmasher  # noqa: E402,F401  (registers the cmr.* colour maps the palette names)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import to_rgba  # noqa: E402

from elo_mitsuba.analysis.plots import (  # noqa: E402,F401  (re-exported for the studies)
    CMAP_DIVERGING,
    CMAP_ERROR,
    CMAP_HEIGHT,
    CMAP_INTENSITY,
    CMAP_SEQUENTIAL,
    MASK_COLOUR,
)

DPI = 100

plt.rcParams.update({
    "font.size": 8.5, "axes.titlesize": 9, "axes.labelsize": 8.5, "legend.fontsize": 7.5,
    "xtick.labelsize": 7.5, "ytick.labelsize": 7.5, "figure.dpi": DPI, "savefig.dpi": DPI,
    "axes.grid": False, "image.interpolation": "nearest",
})


def extent(shape, field_mm):
    fx, fy = (field_mm, field_mm) if np.isscalar(field_mm) else field_mm
    return (-fx / 2, fx / 2, -fy / 2, fy / 2)


def image(fig, ax, img, field_mm, *, title="", label="", cmap=CMAP_INTENSITY, vmin=None, vmax=None,
          symmetric=False, scale=1.0, mask=None, colorbar=True):
    """Show ``img`` (row 0 = +y edge) with axes in mm and a labelled colour bar."""
    data = np.asarray(img, dtype=float) * scale
    if symmetric and vmax is None:
        vmax = float(np.nanpercentile(np.abs(data), 99.5)) or 1.0
        vmin = -vmax
    im = ax.imshow(data, extent=extent(data.shape, field_mm), origin="upper", cmap=cmap,
                   vmin=vmin, vmax=vmax)
    if mask is not None and np.any(mask):
        overlay = np.zeros(data.shape + (4,))
        overlay[np.asarray(mask, bool)] = to_rgba(MASK_COLOUR)
        ax.imshow(overlay, extent=extent(data.shape, field_mm), origin="upper")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    if title:
        ax.set_title(title)
    if colorbar:
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
        cb.set_label(label)
    return im


def save(fig, ctx, name: str, caption: str, study) -> Path:
    """Save ``fig`` as ``<figures>/<name>.png`` and register it with its caption in ``study``."""
    from .report import Figure

    path = Path(ctx.fig_dir) / f"{name}.png"
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    _shrink(path)
    study.figures.append(Figure(path, caption))
    return path


def _shrink(path: Path, limit: int = 250_000) -> None:
    """Keep committed figures modest: a PNG above ``limit`` bytes (noisy Monte Carlo images compress
    badly) is re-encoded with a 256-colour palette when that saves at least 30 %."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        return
    size = path.stat().st_size
    if size <= limit:
        return
    with Image.open(path) as im:
        q = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    tmp = path.with_suffix(".tmp.png")
    q.save(tmp, optimize=True)
    if tmp.stat().st_size < 0.7 * size:
        tmp.replace(path)
    else:
        tmp.unlink()
