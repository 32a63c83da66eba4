"""One evaluation of the optimiser: a design's constraints and objectives (a Dask task).

The figures of merit come from the first-event model (:func:`~elo_mitsuba.analysis.precision.design_metrics`,
~0.1 s); only the objective ``e2_share`` renders: the flat plate in the ATHENE-like chamber
(``athene_flat``, events = 2) at a coarse resolution with the design's four detectors moved into
place, its share of 2nd-event electrons per detector (the bias the chamber adds to each signal; the
largest over the four). The scene is loaded once per worker process and kept.
"""

from __future__ import annotations

import time
from typing import Mapping

import numpy as np

from ..analysis.precision import SignalNoise, design_metrics
from .geometry import design_discs, slot_names, violations

#: The loaded chamber scene of this process, by its load-time values (resolution, wd, field, material).
_SCENES: dict = {}


def second_event_share(discs: Mapping, *, resolution: int = 8, spp: int = 64, work_distance_mm: float = 400.0,
                       field_mm: float = 80.0, material: str = "Ti-6Al-4V", seed: int = 0) -> float:
    """The largest share of 2nd-event electrons e2 / (e1 + e2) of the four detectors' flat-plate
    signals in the ATHENE-like chamber (a render of ``athene_flat`` with the discs moved there).

    Parameters
    ----------
    discs : mapping of str to Disc
        ``right``, ``back``, ``left``, ``front``.
    resolution, spp : int
        The coarse render's pixels per side and samples per pixel.
    work_distance_mm, field_mm : float
        Beam pivot height and scan field.
    material : str
        The plate's material.
    seed : int
        Sampler seed.

    Returns
    -------
    float

    Examples
    --------
    >>> from elo_mitsuba.design.geometry import design_discs
    >>> d = design_discs({"dh": 272, "dw": 127, "radius": 25, "aim_z": 0, "azimuth": 0}, 4)
    >>> share = second_event_share(d, resolution=2, spp=16)
    >>> 0.0 < share < 0.5
    True
    """
    key = (int(resolution), float(work_distance_mm), float(field_mm), str(material))
    scene = _SCENES.get(key)
    if scene is None:
        from ..render import load_scene

        scene = _SCENES[key] = load_scene("athene_flat", res=key[0], wd=key[1], field=key[2], material=key[3],
                                          events=2)
    for name, d in discs.items():
        scene.set_detector(name, center=d.center, radius=d.radius, normal=d.normal)
    result = scene.render(spp=int(spp), seed=int(seed), events=2, progress=False)
    shares = []
    for name in discs:
        e1 = float(np.sum(result.channels[f"{name}.e1"]))
        e2 = float(np.sum(result.channels[f"{name}.e2"]))
        shares.append(e2 / (e1 + e2) if e1 + e2 > 0 else 1.0)
    return float(max(shares))


def evaluate_design(params: Mapping, count: int, settings: Mapping) -> dict:
    """Constraints and figures of merit of one design.

    Parameters
    ----------
    params : mapping
        The design parameters (:func:`~.geometry.design_discs`).
    count : int
        Number of detectors.
    settings : mapping
        :meth:`~.spec.OptimizeSpec.to_dict` of the spec.

    Returns
    -------
    dict
        ``metrics`` (name -> float), ``violations`` (constraint -> mm), ``seconds``.

    Examples
    --------
    >>> from elo_mitsuba.design.spec import load_spec
    >>> s = load_spec({"metric": {"grid": 2}}).to_dict()
    >>> out = evaluate_design({"dh": 272, "dw": 127, "radius": 25, "aim_z": 0, "azimuth": 0}, 4, s)
    >>> max(out["violations"].values()), round(out["metrics"]["masked_share"], 3)
    (0.0, 0.0)
    """
    t0 = time.perf_counter()
    m = settings["metric"]
    discs = design_discs(params, count, settings["symmetric"])
    viol = violations(discs, field_mm=m["field"], work_distance_mm=m["wd"],
                      clearance=settings["constraints"]["clearance"])
    noise = SignalNoise.from_chain(m["beam_current"], m["dwell"], m["amplifier"])
    metrics = design_metrics(discs, field_mm=m["field"], work_distance_mm=m["wd"], material=m["material"],
                             grid=m["grid"], s_max=m["s_max"], s_mask=m["s_mask"], noise=noise)
    if "e2_share" in settings["objectives"]:
        if max(viol.values()) > 0 or tuple(discs) != slot_names(4):
            # a design that does not fit the chamber is not rendered (a disc through a wall would
            # count the wall's electrons): the worst share, and the constraints say why
            metrics["e2_share"] = 1.0
        else:
            r = settings["render"]
            metrics["e2_share"] = second_event_share(discs, resolution=r["resolution"], spp=r["spp"],
                                                     work_distance_mm=m["wd"], field_mm=m["field"],
                                                     material=m["material"])
    return {"metrics": metrics, "violations": viol, "seconds": time.perf_counter() - t0}
