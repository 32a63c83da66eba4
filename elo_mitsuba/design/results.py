"""What a builder takes away from an optimiser's store: the front as a plot with sketches of the
layouts (from above and from the side, in the chamber), a chosen design as a scene XML, and the
comparison with the paper's Table 1 layouts under the same metric.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Mapping

import numpy as np

from ..constants import CHAMBER_INTERIOR_MM, COLUMN_HALF_WIDTH_MM, SHEET_BOTTOM_MM, SHEET_Y_MM, TABLE1_LAYOUTS
from ..files import atomic_write, check_output
from ..analysis.precision import SIGMA_CAP
from .evaluate import evaluate_design
from .geometry import design_discs, slot_names
from .spec import OptimizeSpec

#: Radius of Table 1's discs (ATHENE's 50 mm copper plates).
TABLE1_RADIUS_MM = 25.0


def table1_params(zeta: int) -> dict:
    """Design parameters of Table 1's layout ``zeta`` (deg): 4 discs of 25 mm radius facing the origin.

    Examples
    --------
    >>> table1_params(50)
    {'dh': 192.7, 'dw': 229.6, 'radius': 25.0, 'aim_z': 0.0, 'azimuth': 0.0}
    """
    dh, dw = TABLE1_LAYOUTS[int(zeta)]
    return {"dh": dh, "dw": dw, "radius": TABLE1_RADIUS_MM, "aim_z": 0.0, "azimuth": 0.0}


def table1_records(spec: OptimizeSpec) -> dict:
    """Table 1's layouts evaluated with the spec's metric and constraints: ``{"zeta25": record}``
    (records as the store's log holds them; ``metrics``, ``violations``, ``feasible``)."""
    settings = {**spec.to_dict(), "symmetric": True}
    out = {}
    for z in TABLE1_LAYOUTS:
        p = table1_params(z)
        r = evaluate_design(p, 4, settings)
        out[f"zeta{z}"] = {**r, "params": p, "count": 4, "feasible": max(r["violations"].values()) <= 0}
    return out


def _signed(ds):
    """Objective values (n, m) of the store's designs, all as 'smaller is better'."""
    sign = np.array([1.0 if d == "minimize" else -1.0 for d in ds.attrs["directions"]])
    return np.stack([ds[o].values for o in ds.attrs["objectives"]], axis=-1) * sign


def choose_design(ds) -> int:
    """The front's knee: the Pareto design nearest to the ideal point, each objective scaled to the
    front's range (its trial number).

    Examples
    --------
    >>> import xarray as xr
    >>> ds = xr.Dataset({"a": ("design", [0.0, 1.0, 2.0]), "b": ("design", [2.0, 0.4, 0.0]),
    ...                  "pareto": ("design", [True, True, True])}, coords={"design": [7, 8, 9]},
    ...                 attrs={"objectives": ["a", "b"], "directions": ["minimize", "minimize"]})
    >>> choose_design(ds)
    8
    """
    front = np.asarray(ds.pareto.values, bool)
    if not front.any():
        from ..errors import EloInputError

        raise EloInputError("the store has no feasible design: nothing to choose")
    v = _signed(ds)[front]
    lo, hi = v.min(axis=0), v.max(axis=0)
    scaled = (v - lo) / np.where(hi > lo, hi - lo, 1.0)
    return int(ds.design.values[front][np.argmin(np.linalg.norm(scaled, axis=-1))])


def compare_table1(ds, table1: Mapping) -> list[dict]:
    """Each Table 1 layout against the front: its objectives, the chosen design's (:func:`choose_design`)
    as ratios to them, and whether (and by which design) the front dominates it.

    Returns
    -------
    list of dict
        ``layout``, ``feasible``, ``values`` (objective -> value), ``chosen_ratio`` (objective ->
        chosen / layout), ``dominated_by`` (trial number of the front design best on the first
        objective among those that dominate the layout, or None).

    Examples
    --------
    >>> import xarray as xr
    >>> ds = xr.Dataset({"a": ("design", [1.0, 2.0]), "b": ("design", [0.5, 0.1]),
    ...                  "pareto": ("design", [True, True])}, coords={"design": [0, 1]},
    ...                 attrs={"objectives": ["a", "b"], "directions": ["minimize", "minimize"]})
    >>> row = compare_table1(ds, {"zeta25": {"metrics": {"a": 2.0, "b": 1.0}, "feasible": True}})[0]
    >>> row["dominated_by"], row["chosen_ratio"]
    (0, {'a': 0.5, 'b': 0.5})
    """
    objectives = list(ds.attrs["objectives"])
    sign = np.array([1.0 if d == "minimize" else -1.0 for d in ds.attrs["directions"]])
    chosen = ds.sel(design=choose_design(ds))
    front = np.asarray(ds.pareto.values, bool)
    v = _signed(ds)
    rows = []
    for name, rec in table1.items():
        t = np.array([rec["metrics"][o] for o in objectives]) * sign
        dom = front & np.all(v <= t, axis=-1) & np.any(v < t, axis=-1)
        by = None
        if dom.any():
            idx = np.flatnonzero(dom)
            by = int(ds.design.values[idx[np.argmin(v[idx, 0])]])
        best = ds.sel(design=by) if by is not None else None
        rows.append({"layout": name, "feasible": bool(rec["feasible"]),
                     "dominating_values": None if best is None else {o: float(best[o]) for o in objectives},
                     "values": {o: float(rec["metrics"][o]) for o in objectives},
                     "chosen_ratio": {o: float(chosen[o]) / rec["metrics"][o] if rec["metrics"][o] else float("inf")
                                      for o in objectives},
                     "dominated_by": by})
    return rows


def design_of(ds, trial: int) -> dict:
    """The discs of the store's design ``trial`` (name -> Disc)."""
    from ..analysis.scan_geometry import Disc

    d = ds.sel(design=int(trial))
    names = slot_names(int(d["count"]))
    return {n: Disc(tuple(d.disc_center.values[k]), tuple(d.disc_normal.values[k]), float(d.disc_radius.values[k]))
            for k, n in enumerate(names)}


def sketch_layout(ax_top, ax_side, discs: Mapping, *, field_mm: float = 80.0, work_distance_mm: float = 400.0,
                  color="C0", label=None) -> None:
    """Draw a design in the chamber: from above (x, y) on ``ax_top`` and from the side (x, z) on
    ``ax_side``; discs as their outlines, the chamber's walls, column, sheet and the beam's cone.

    Examples
    --------
    >>> import matplotlib
    >>> matplotlib.use("Agg")
    >>> import matplotlib.pyplot as plt
    >>> fig, (a, b) = plt.subplots(1, 2)
    >>> sketch_layout(a, b, design_discs(table1_params(25), 4))
    >>> len(a.lines) > 4
    True
    """
    (x0, x1), (y0, y1), (z0, z1) = CHAMBER_INTERIOR_MM
    grey = dict(color="0.6", lw=0.8)
    ax_top.plot([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0], **grey)
    ax_top.axhspan(*SHEET_Y_MM, color="0.8")
    c = COLUMN_HALF_WIDTH_MM
    ax_top.plot([-c, c, c, -c, -c], [-c, -c, c, c, -c], color="0.4", lw=0.8, ls=":")
    h = field_mm / 2
    ax_top.plot([-h, h, h, -h, -h], [-h, -h, h, h, -h], color="k", lw=0.8)
    ax_side.plot([x0, x1, x1, x0, x0], [z0, z0, z1, z1, z0], **grey)
    ax_side.plot([-h, 0, h], [0, work_distance_mm, 0], color="k", lw=0.8)
    ax_side.plot([-c, -c], [work_distance_mm, z1], color="0.4", lw=0.8, ls=":")
    ax_side.plot([c, c], [work_distance_mm, z1], color="0.4", lw=0.8, ls=":")
    t = np.linspace(0, 2 * np.pi, 49)
    for k, d in enumerate(discs.values()):
        n = np.asarray(d.normal)
        a = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.99 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        rim = np.asarray(d.center) + d.radius * (np.cos(t)[:, None] * a + np.sin(t)[:, None] * b)
        ax_top.plot(rim[:, 0], rim[:, 1], color=color, lw=1.2, label=label if k == 0 else None)
        ax_side.plot(rim[:, 0], rim[:, 2], color=color, lw=1.2)
    for ax, ylab in ((ax_top, "y (mm)"), (ax_side, "z (mm)")):
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel(ylab)
    ax_top.set_title("from above", fontsize=9)
    ax_side.set_title("from the side (-y)", fontsize=9)


def plot_front(ds, path, *, table1: Mapping | None = None, chosen: int | None = None,
               overwrite: bool = False) -> Path:
    """The front as a PNG: objective 1 vs objective 2 (every evaluated feasible design in grey,
    the front joined, Table 1's layouts marked), and sketches of the chosen design (default: the
    front's knee, :func:`choose_design`) and the front's two ends, from above and from the side.

    Examples
    --------
    See :func:`~elo_mitsuba.design.optimize.optimize`; tests/test_optimize.py draws one.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = check_output(path, (".png",), overwrite=overwrite, what="plot")
    objectives = list(ds.attrs["objectives"])
    ox, oy = objectives[0], objectives[1] if len(objectives) > 1 else objectives[0]
    spec = json.loads(ds.attrs["spec"])
    field, wd = spec["metric"]["field"], spec["metric"]["wd"]
    fig = plt.figure(figsize=(13, 7.5))
    gs = fig.add_gridspec(2, 4, width_ratios=[1.6, 1, 1, 1])
    ax = fig.add_subplot(gs[:, 0])
    # a capped bound (the signals cannot fix the gradient) would stretch the axis by 1e5: left out
    capped = np.zeros(ds.sizes["design"], bool)
    for o in (ox, oy):
        if o.startswith("sigma"):
            capped |= ds[o].values >= SIGMA_CAP
    feas = np.asarray(ds.feasible.values, bool) & ~capped
    front = np.asarray(ds.pareto.values, bool)
    ax.scatter(ds[ox].values[feas], ds[oy].values[feas], s=10, color="0.7", label="feasible designs")
    if (~feas).any():
        bad = ~feas & ~capped
        ax.scatter(ds[ox].values[bad], ds[oy].values[bad], s=8, marker="x", color="0.85", label="infeasible")
    order = np.argsort(ds[ox].values[front])
    ax.plot(ds[ox].values[front][order], ds[oy].values[front][order], "o-", color="C0", ms=4, label="Pareto front")
    chosen = choose_design(ds) if chosen is None else int(chosen)
    ends = [int(ds.design.values[front][order[0]]), int(ds.design.values[front][order[-1]])]
    picks = [(chosen, "C3", "chosen")] + [(t, c, lab) for t, c, lab in zip(ends, ("C1", "C2"), ("end 1", "end 2"))]
    for t, c, lab in picks:
        d = ds.sel(design=t)
        ax.plot(float(d[ox]), float(d[oy]), "*", ms=14, color=c, label=f"{lab} (design {t})")
    for name, rec in (table1 or {}).items():
        if any(o.startswith("sigma") and rec["metrics"][o] >= SIGMA_CAP for o in (ox, oy)):
            name += " (off scale: sigma capped)"
            ax.annotate(name, (0.02, 0.98 - 0.04 * len(ax.texts)), xycoords="axes fraction", fontsize=8, va="top")
            continue
        ax.plot(rec["metrics"][ox], rec["metrics"][oy], "s", mfc="none", color="k", ms=7)
        ax.annotate(name, (rec["metrics"][ox], rec["metrics"][oy]), fontsize=8, xytext=(4, 4),
                    textcoords="offset points")
    if ox.startswith("sigma"):
        ax.set_xscale("log")
    ax.set_xlabel(ox + (" (slope units)" if ox.startswith("sigma") else ""))
    ax.set_ylabel(oy + (" (slope units)" if oy.startswith("sigma") else ""))
    ax.legend(fontsize=8)
    ax.set_title(f"{int(np.asarray(ds.feasible.values).sum())} feasible of {ds.sizes['design']} designs; "
                 f"{int(front.sum())} on the front", fontsize=10)
    for j, (t, c, lab) in enumerate(picks):
        sketch_layout(fig.add_subplot(gs[0, 1 + j]), fig.add_subplot(gs[1, 1 + j]), design_of(ds, t),
                      field_mm=field, work_distance_mm=wd, color=c)
        fig.axes[-2].set_title(f"{lab}: design {t}, from above", fontsize=9)
    fig.tight_layout()
    out = atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=90, format="png"))
    plt.close(fig)
    return out


def export_scene(discs: Mapping, path, *, overwrite: bool = False) -> Path:
    """Write a scene XML: the flat plate in the ATHENE-like chamber (``athene_flat``) with the
    design's discs in place of Table 1's four. Its includes are absolute paths (it works from any
    folder); its parameters are athene_flat's but dh, dw and layout, which the design replaces.

    Examples
    --------
    >>> import tempfile
    >>> import elo_mitsuba as em
    >>> with tempfile.TemporaryDirectory() as d:
    ...     xml = export_scene(design_discs(table1_params(50), 4), Path(d) / "best.xml")
    ...     scene = em.load_scene(xml, res=2, events=1)
    ...     [round(v, 1) for v in scene.detector_geometry()["back"]["center"]]
    [0.0, 229.6, 192.7]
    """
    from xml.sax.saxutils import quoteattr

    from ..scene_files import detector_up, portable_scene_text, scenes_dir

    path = check_output(path, (".xml",), overwrite=overwrite, what="scene")
    src = scenes_dir() / "athene_flat.xml"
    text = portable_scene_text(src)
    text = text[text.index("<scene"):]
    layout_inc = [ln for ln in text.splitlines() if "layouts/" in ln and "<include" in ln]
    det_inc = [ln for ln in text.splitlines() if "parts/detectors.xml" in ln]
    if len(layout_inc) != 1 or len(det_inc) != 1:  # the template changed: fail loudly, not write a wrong scene
        raise RuntimeError("athene_flat.xml no longer includes one layout and parts/detectors.xml")
    plates = (scenes_dir() / "parts" / "plates_$plates.xml").as_posix()
    shapes = ['    <default name="plates" value="absorbing"/>',
              f"    <include filename={quoteattr(plates)}/>"]
    for name, d in discs.items():
        c, n = np.asarray(d.center), np.asarray(d.normal)
        up = detector_up(c, n)  # the frame set_detector gives it: the design renders as evaluated
        target = c + n

        def f(v):
            return ", ".join(f"{x:.6g}" for x in v)
        shapes += [f'    <shape type="disk" id={quoteattr(name)}>', '        <transform name="to_world">',
                   f'            <scale value="{d.radius:.6g}"/>',
                   f'            <lookat origin="{f(c)}" target="{f(target)}" up="{f(up)}"/>',
                   "        </transform>", '        <ref id="detector_plate"/>', '        <emitter type="area"/>',
                   "    </shape>"]
    text = text.replace(layout_inc[0] + "\n", "").replace(det_inc[0], "\n".join(shapes))
    header = ("<!-- Written by 'elo-mitsuba optimize': athene_flat.xml (the flat plate in the ATHENE-like chamber) "
              f"with a designed detector system of {len(discs)} discs (centre, normal, radius in mm below). -->\n")
    return atomic_write(path, lambda tmp: tmp.write_text(header + text))
