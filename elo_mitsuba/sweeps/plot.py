"""A sweep metric over one swept parameter (a line per detector) or two (a heat map), as PNG.

Dimensions are named as the store names them (:func:`.spec.dimension_name`, ``right_radius``);
``select`` and ``x`` take that name or the spec's key (``right.radius``). A store written before the
names were identifiers (dotted dimensions) is read with its names mapped the same way.

Values that vary by less than :data:`SMALL_SPAN` of their magnitude are named as such in the
title (and the colour bar's label): the axis and colour scale stretch any range over the plot.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..errors import EloInputError
from .spec import dimension_name


def _open(store):
    import xarray as xr

    path = Path(store)
    if not path.exists():  # "not a sweep's store" sent users looking at a store that is not there
        raise EloInputError(f"{path}: no such store; give the .zarr folder that 'elo-mitsuba sweep' wrote")
    if not (path / ".zgroup").is_file():
        raise EloInputError(f"{path} is not a sweep's Zarr store (a folder that 'elo-mitsuba sweep' wrote)")
    try:
        with warnings.catch_warnings():
            # a store whose consolidated metadata is gone still reads (slower): xarray's
            # three-point advice and zarr's note about the claims folder (.claims, ours) would
            # only precede the figure
            warnings.filterwarnings("ignore", message="Failed to open Zarr store with consolidated metadata")
            warnings.filterwarnings("ignore", message=r"Object at \.claims is not recognized")
            ds = xr.open_zarr(str(path))
    except Exception as exc:  # noqa: BLE001 -- damaged metadata: one line
        text = " ".join(str(exc).split())[:200]
        raise EloInputError(f"{path}: cannot read the sweep store ({type(exc).__name__}: {text})") from None
    if "status" not in ds.data_vars:
        raise EloInputError(f"{path} is a Zarr store but not a sweep's (no status variable)")
    old = {n: dimension_name(n) for n in list(ds.variables) + list(ds.dims) if dimension_name(n) != n}
    if old and not set(old.values()) & (set(ds.variables) | set(ds.dims)):  # a store with dotted names
        ds = ds.rename(old)
    return ds


def _dimension(given, swept, what: str, store) -> str:
    """The store's dimension for ``given`` (its name or the spec key, :func:`dimension_name`);
    ``what`` opens the message (``--select right.radius=25``)."""
    dim = dimension_name(given)
    if dim not in swept:
        raise EloInputError(f"{what}: {dim} is not swept in {store} (swept: {', '.join(swept) or 'none'})")
    return dim


def _label(ds, dim) -> str:
    c = ds[dim]
    name = c.attrs.get("long_name", dim)
    units = c.attrs.get("units", "")
    return f"{name} ({units})" if units and units != "1" else name


#: A plot whose values span less than this share of their mean magnitude says so: matplotlib
#: stretches any range over the whole axis or colour map, so 0.3001 .. 0.3008 would look like a
#: change from black to yellow.
SMALL_SPAN = 0.01


def span_note(values) -> str:
    """``"span only 0.23 %: 0.3001 to 0.3008"`` when the finite ``values`` vary by less than
    :data:`SMALL_SPAN` of their mean magnitude, else ""."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return ""
    lo, hi = float(v.min()), float(v.max())
    scale = float(np.mean(np.abs(v)))
    if scale == 0 or (hi - lo) >= SMALL_SPAN * scale:
        return ""
    digits = max(3, int(np.ceil(-np.log10((hi - lo) / scale))) + 2) if hi > lo else 6
    return f"span only {100 * (hi - lo) / scale:.2g} %: {lo:.{digits}g} to {hi:.{digits}g}"


def _positions(ds, dim):
    """Numeric positions and tick labels of a swept coordinate (strings become categories)."""
    vals = ds[dim].values
    if vals.dtype.kind in "iuf":
        return vals.astype(float), None
    return np.arange(len(vals), dtype=float), [str(v) for v in vals]


def plot_metric(store, metric: str, path, *, detector: str | None = None, select: dict | None = None,
                x: str | None = None, overwrite: bool = False) -> Path:
    """Plot ``metric`` of a sweep store against its swept parameters.

    Parameters
    ----------
    store : str or Path
        The sweep's ``.zarr`` store.
    metric : str
        A data variable without image dimensions (``signal_mean``, ``gradient_rms_eq26``, ...).
    path : str or Path
        The ``.png`` to write.
    detector : str, optional
        For per-detector metrics: one detector (default: a line per detector; a heat map shows
        the mean over detectors).
    select : dict, optional
        ``{dim: value}`` for swept dimensions beyond the one or two plotted (a value of the
        sweep: numbers equal to 1e-9 relative, strings exactly); ``dim`` is the store's name
        (``right_radius``) or the spec's key (``right.radius``).
    x : str, optional
        The dimension along the horizontal axis (default: the first one left); either spelling.
    overwrite : bool
        Replace an existing PNG.

    Returns
    -------
    Path
    """
    from ..analysis.plots import CMAP_SEQUENTIAL, new_figure, save_figure

    ds = _open(store)
    if metric not in ds.data_vars or {"y", "x"} & set(ds[metric].dims) or metric in ("error", "worker"):
        allowed = [v for v in ds.data_vars if not {"y", "x"} & set(ds[v].dims) and v not in ("error", "worker")]
        raise EloInputError(f"{store}: no metric {metric!r}; metrics in this store: {', '.join(allowed)}")
    da = ds[metric].where(ds["status"] == 1)
    swept = [d for d in da.dims if d != "detector"]
    chosen = {}
    for given, value in (select or {}).items():
        dim = _dimension(given, swept, f"--select {given}={value}", store)
        if dim in chosen:
            raise EloInputError(f"--select names {dim} twice ({chosen[dim][0]}, {given})")
        chosen[dim] = (given, value)
    for dim, (_, value) in chosen.items():
        vals = ds[dim].values
        numeric = vals.dtype.kind in "iuf"
        try:
            wanted = float(value) if numeric else str(value)
        except (TypeError, ValueError, OverflowError):
            wanted = None
        hits = [i for i, v in enumerate(vals)
                if wanted is not None and (np.isclose(float(v), wanted, rtol=1e-9, atol=0) if numeric else str(v) == wanted)]
        if not hits:
            raise EloInputError(f"--select {dim}={value}: not a value of the sweep; {dim} takes "
                                f"{', '.join(f'{v:g}' if numeric else str(v) for v in vals)}")
        da = da.isel({dim: hits[0]})
    title = metric + "".join(f", {k}={v}" for k, (_, v) in chosen.items())
    if detector is not None and "detector" not in da.dims:
        raise EloInputError(f"--detector {detector}: {metric} is one value per sweep point, not one per detector; "
                            "drop --detector")
    if "detector" in da.dims and detector is not None:
        if detector not in list(ds["detector"].values):
            raise EloInputError(f"detector {detector!r}: not in {', '.join(map(str, ds['detector'].values))}")
        da = da.sel(detector=detector)
        title += f" ({detector})"
    dims = [d for d in da.dims if d != "detector" and da.sizes[d] > 1]
    da = da.squeeze([d for d in da.dims if d != "detector" and da.sizes[d] == 1])
    if len(dims) == 0 or len(dims) > 2:
        raise EloInputError(f"{metric} varies over {len(dims)} swept dimensions ({', '.join(dims) or 'none'}); "
                            "plot one or two: fix the others with --select DIM=VALUE")
    if x is not None:
        if dimension_name(x) not in dims:
            raise EloInputError(f"--x {x}: {dimension_name(x)} is not among the plotted dimensions ({', '.join(dims)})")
        dims.insert(0, dims.pop(dims.index(dimension_name(x))))
    units = ds[metric].attrs.get("units", "")
    vlabel = f"{metric} ({units})" if units and units != "1" else metric
    fig, axes = new_figure()
    ax = axes[0]
    if len(dims) == 1:
        xs, ticks = _positions(ds, dims[0])
        if "detector" in da.dims:
            for d in ds["detector"].values:
                ax.plot(xs, da.sel(detector=d).transpose(dims[0]).values, "o-", label=str(d))
            ax.legend(title="detector")
        else:
            ax.plot(xs, da.transpose(dims[0]).values, "o-")
        if ticks:
            ax.set_xticks(xs, ticks)
        note = span_note(da.values)
        if note:
            title += f"\n({note})"
        ax.set_xlabel(_label(ds, dims[0]))
        ax.set_ylabel(vlabel)
        ax.grid(alpha=0.3)
    else:
        if "detector" in da.dims:
            da = da.mean("detector")
            title += " (mean over detectors)"
        xs, xt = _positions(ds, dims[0])
        ys, yt = _positions(ds, dims[1])
        z = da.transpose(dims[1], dims[0]).values
        if not np.all(np.isfinite(z)):
            title += " (blank: undefined)"
        mesh = ax.pcolormesh(np.arange(len(xs)), np.arange(len(ys)), z, cmap=CMAP_SEQUENTIAL, shading="nearest")
        ax.set_xticks(np.arange(len(xs)), xt or [f"{v:g}" for v in xs])
        ax.set_yticks(np.arange(len(ys)), yt or [f"{v:g}" for v in ys])
        if z.size <= 64:  # small grids: the numbers in the cells, with the digits that differ
            finite = z[np.isfinite(z)]
            spread = float(np.ptp(finite)) / max(float(np.mean(np.abs(finite))), 1e-300) if finite.size else 1.0
            digits = max(3, int(np.ceil(-np.log10(spread))) + 2) if spread > 0 else 3
            for j in range(z.shape[0]):
                for i in range(z.shape[1]):
                    if np.isfinite(z[j, i]):
                        ax.text(i, j, f"{z[j, i]:.{digits}g}", ha="center", va="center", fontsize=8, color="0.5")
        ax.set_xlabel(_label(ds, dims[0]))
        ax.set_ylabel(_label(ds, dims[1]))
        note = span_note(z)
        if note:
            title += f"\n({note})"
        fig.colorbar(mesh, ax=ax, label=vlabel + (f"\n(colours stretch a {note.split(': ')[0][5:]} range)" if note else ""))
    ax.set_title(title, fontsize=10)
    return save_figure(fig, path, overwrite)
