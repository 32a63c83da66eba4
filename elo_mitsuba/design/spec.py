"""The optimiser's spec: a TOML file naming the design space, the objectives, the metric's settings,
the constraints and the optimiser; parsed and checked completely before anything runs.

Example (``examples/optimize_athene.toml``)::

    count = 4                       # detectors; a list ([4, 6, 8]) lets the optimiser choose
    symmetric = true                # one dh, dw, radius, aim_z, azimuth for all (else per detector)
    objectives = ["sigma_worst", "masked_share"]
    [parameters]                    # [low, high] or one fixed value; mm, deg
    dh = [60.0, 520.0]              # detector centre height
    dw = [60.0, 330.0]              # distance of the centre from the z-axis
    radius = [10.0, 50.0]
    aim_z = 0.0                     # the normals aim at (0, 0, aim_z)
    azimuth = 0.0                   # rotation of the layout about z (deg)
    [metric]                        # elo_mitsuba.analysis.precision.design_metrics
    field = 80.0
    wd = 400.0
    material = "Ti-6Al-4V"
    grid = 5                        # field points per side
    s_max = 0.5                     # precision judged for slopes up to this
    s_mask = 1.0                    # masking judged for slopes up to this
    beam_current = 3e-3             # A
    dwell = 1e-6                    # s per pixel
    amplifier = 1e-3                # V rms at the amplifier output
    [constraints]
    clearance = 10.0                # mm from walls, sheet, beam cone, column and each other
    [optimizer]
    sampler = "tpe"                 # tpe, nsga2, random, grid
    trials = 100
    batch = 8                       # designs evaluated at once (Dask tasks)
    seed = 0
    grid_points = 10                # per free parameter, for sampler = "grid"
    [render]                        # only for the objective e2_share
    resolution = 8
    spp = 64

Every bad value is refused with one line naming the file, the key, the value and what is allowed.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from ..analysis.model_gradient import MAX_SLOPE
from ..constants import DEFAULT_MATERIAL, ELEMENTARY_CHARGE_C, FIELD_MM, MAX_SEED, WORK_DISTANCE_MM
from ..errors import EloInputError
from ..schema import MAX_LENGTH_MM, MIN_LENGTH_MM
from .geometry import PARAMETERS

#: Objectives and their directions. ``e2_share`` renders (the chamber's 2nd event, four detectors).
OBJECTIVES = {"sigma_worst": "minimize", "sigma_median": "minimize", "sigma_flat": "minimize",
              "masked_share": "minimize", "unsolvable_share": "minimize", "signal_min": "maximize",
              "e2_share": "minimize"}
#: Samplers of Optuna the spec may name.
SAMPLERS = ("tpe", "nsga2", "random", "grid")
#: Defaults of each section.
METRIC_DEFAULTS = {"field": FIELD_MM, "wd": WORK_DISTANCE_MM, "material": DEFAULT_MATERIAL, "grid": 5,
                   "s_max": 0.5, "s_mask": 1.0, "beam_current": 3e-3, "dwell": 1e-6, "amplifier": 1e-3}
OPTIMIZER_DEFAULTS = {"sampler": "tpe", "trials": 100, "batch": 8, "seed": 0, "grid_points": 10}
PARAMETER_DEFAULTS = {"dh": [60.0, 520.0], "dw": [60.0, 330.0], "radius": [10.0, 50.0], "aim_z": 0.0, "azimuth": 0.0}
RENDER_DEFAULTS = {"resolution": 8, "spp": 64}
TOP_KEYS = ("count", "symmetric", "objectives", "parameters", "metric", "constraints", "optimizer", "render")
#: Most detectors a design may have, and most trials a spec may ask for.
MAX_COUNT, MAX_TRIALS = 16, 100_000


@dataclass(frozen=True)
class OptimizeSpec:
    """A checked optimiser spec (see the module's description).

    Examples
    --------
    >>> spec = load_spec({"parameters": {"radius": 25.0}, "optimizer": {"trials": 20}})
    >>> spec.counts, spec.free_parameters(4), spec.trials
    ((4,), ['dh', 'dw'], 20)
    """

    counts: tuple
    symmetric: bool
    objectives: tuple
    bounds: Mapping                 # name -> (low, high); low == high: fixed
    metric: Mapping
    clearance: float
    optimizer: Mapping
    render: Mapping
    source: str = "spec"
    text: str = field(default="", compare=False)

    @property
    def trials(self) -> int:
        return int(self.optimizer["trials"])

    @property
    def directions(self) -> list[str]:
        return [OBJECTIVES[o] for o in self.objectives]

    def parameter_names(self, count: int) -> list[str]:
        """Names of the design parameters of a design of ``count`` detectors (fixed ones included)."""
        if self.symmetric:
            return list(PARAMETERS)
        return [f"{p}_{k}" for k in range(int(count)) for p in PARAMETERS]

    def bound(self, name: str) -> tuple[float, float]:
        """(low, high) of a parameter (``dh_2`` has the bounds of ``dh``)."""
        return tuple(self.bounds[name.rsplit("_", 1)[0] if name not in self.bounds else name])

    def free_parameters(self, count: int) -> list[str]:
        """The parameters the optimiser varies (low < high)."""
        return [n for n in self.parameter_names(count) if self.bound(n)[0] < self.bound(n)[1]]

    def to_dict(self) -> dict:
        return {"count": list(self.counts), "symmetric": self.symmetric, "objectives": list(self.objectives),
                "parameters": {k: list(v) for k, v in self.bounds.items()}, "metric": dict(self.metric),
                "constraints": {"clearance": self.clearance}, "optimizer": dict(self.optimizer),
                "render": dict(self.render)}

    def digest(self) -> str:
        """A hash of everything that decides the results (the optimiser's and the metric's settings)."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:16]


#: Ranges of the design parameters (mm, deg): lengths as a header holds them (1e300 raised an
#: IndexError in the feasibility search), azimuths within a turn.
_PARAMETER_RANGE = {"dh": (None, MAX_LENGTH_MM), "dw": (None, MAX_LENGTH_MM), "radius": (None, MAX_LENGTH_MM),
                    "aim_z": (-MAX_LENGTH_MM, MAX_LENGTH_MM), "azimuth": (-360.0, 360.0)}
#: Primary electrons per pixel (beam current x dwell / e) the metric's noise model accepts: 1e300 A
#: made them infinite. Real scans: 3 mA x 1 us = 1.9e10.
MAX_PRIMARIES = 1e30
#: Amplifier noise (V rms) accepted: its square entered the noise model (1e300 overflowed); a kV of
#: noise is beyond any detector amplifier.
MAX_AMPLIFIER_V = 1e3


def _shown(bound) -> str:
    return str(bound) if isinstance(bound, int) else f"{bound:g}"


def _number(where, key, value, lo=None, hi=None, integer=False, positive=False):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if integer:
        ok = ok and float(value).is_integer()
    allowed = ("a whole number" if integer else "a finite number") + (
        " > 0" if positive else "") + (f" >= {_shown(lo)}" if lo is not None else "") + (
        f" <= {_shown(hi)}" if hi is not None else "")
    if not ok or (positive and value <= 0) or (lo is not None and value < lo) or (hi is not None and value > hi):
        raise EloInputError(f"{where}: {key} = {value!r}; must be {allowed}")
    return int(value) if integer else float(value)


def _table(where, doc, key, defaults):
    t = doc.get(key, {})
    if not isinstance(t, dict):
        raise EloInputError(f"{where}: [{key}] must be a table")
    unknown = [k for k in t if k not in defaults]
    if unknown:
        raise EloInputError(f"{where}: [{key}] {unknown[0]!r} is not a key; allowed: {', '.join(defaults)}")
    return {**defaults, **t}


def load_spec(spec, *, second_event: bool = False) -> OptimizeSpec:
    """Parse and check an optimiser spec.

    Parameters
    ----------
    spec : str, Path, dict or OptimizeSpec
        A TOML file, or the parsed table.
    second_event : bool
        The chamber render of ``[render]`` is also used after the run (``optimize --second-event``);
        without it, or the objective ``e2_share``, a ``[render]`` section would be unused and is refused.

    Returns
    -------
    OptimizeSpec

    Raises
    ------
    EloInputError
        One line naming the file, the key, the value and what is allowed.

    Examples
    --------
    >>> load_spec({"objectives": ["sharpness"]})
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: spec: objectives 'sharpness' is not one of sigma_worst, sigma_median, sigma_flat, masked_share, unsolvable_share, signal_min, e2_share
    """
    if isinstance(spec, OptimizeSpec):
        return spec
    text = ""
    if isinstance(spec, (str, Path)):
        path = Path(spec)
        where = str(path)
        if path.suffix.lower() != ".toml":
            raise EloInputError(f"{where}: an optimiser spec is a .toml file")
        try:
            text = path.read_text()
            doc = tomllib.loads(text)
        except OSError as exc:
            raise EloInputError(f"{where}: cannot read ({exc.strerror or exc})") from None
        except tomllib.TOMLDecodeError as exc:
            raise EloInputError(f"{where}: not valid TOML ({exc})") from None
    elif isinstance(spec, Mapping):
        doc, where = dict(spec), "spec"
    else:
        raise EloInputError(f"spec {spec!r}: give a TOML file or a table")
    unknown = [k for k in doc if k not in TOP_KEYS]
    if unknown:
        raise EloInputError(f"{where}: {unknown[0]!r} is not a key of an optimiser spec; allowed: {', '.join(TOP_KEYS)}")
    count = doc.get("count", 4)
    counts = count if isinstance(count, list) else [count]
    if not counts:
        raise EloInputError(f"{where}: count = []; give a number of detectors or a list of them")
    counts = tuple(sorted({_number(where, "count", c, 3, MAX_COUNT, integer=True) for c in counts}))
    symmetric = doc.get("symmetric", True)
    if not isinstance(symmetric, bool):
        raise EloInputError(f"{where}: symmetric = {symmetric!r}; must be true or false")
    objectives = doc.get("objectives", ["sigma_worst", "masked_share"])
    if isinstance(objectives, str) or not isinstance(objectives, list) or not objectives:
        raise EloInputError(f"{where}: objectives = {objectives!r}; give a list of one or more of {', '.join(OBJECTIVES)}")
    for o in objectives:
        if o not in OBJECTIVES:
            raise EloInputError(f"{where}: objectives {o!r} is not one of {', '.join(OBJECTIVES)}")
    if len(set(objectives)) != len(objectives):
        raise EloInputError(f"{where}: objectives {objectives!r} names one twice")
    if "e2_share" in objectives and counts != (4,):
        raise EloInputError(f"{where}: objective e2_share renders the shipped chamber's four detectors; it needs count = 4")
    params = _table(where, doc, "parameters", PARAMETER_DEFAULTS)
    bounds = {}
    for name, v in params.items():
        key = f"parameters.{name}"
        if isinstance(v, list):
            if len(v) != 2:
                raise EloInputError(f"{where}: {key} = {v!r}; give [low, high] or one value")
            lo, hi = (_number(where, key, x, *_PARAMETER_RANGE.get(name, (None, None))) for x in v)
            if lo > hi:
                raise EloInputError(f"{where}: {key} = {v!r}; low must not exceed high")
        else:
            lo = hi = _number(where, key, v, *_PARAMETER_RANGE.get(name, (None, None)))
        if name in ("dh", "dw", "radius") and lo <= 0:
            raise EloInputError(f"{where}: {key} = {v!r}; {name} must be > 0 mm")
        bounds[name] = (lo, hi)
    metric = _table(where, doc, "metric", METRIC_DEFAULTS)
    for k in ("field", "wd"):
        metric[k] = _number(where, f"metric.{k}", metric[k], MIN_LENGTH_MM, MAX_LENGTH_MM)
    for k in ("beam_current", "dwell"):
        metric[k] = _number(where, f"metric.{k}", metric[k], positive=True)
    primaries = metric["beam_current"] * metric["dwell"] / ELEMENTARY_CHARGE_C
    if not primaries <= MAX_PRIMARIES:
        raise EloInputError(f"{where}: metric.beam_current = {metric['beam_current']!r} A x metric.dwell = "
                            f"{metric['dwell']!r} s is {primaries:.3g} electrons per pixel; "
                            f"must be <= {MAX_PRIMARIES:g}")
    metric["grid"] = _number(where, "metric.grid", metric["grid"], 1, 64, integer=True)
    for k in ("s_max", "s_mask"):
        metric[k] = _number(where, f"metric.{k}", metric[k], 0, MAX_SLOPE)
    metric["amplifier"] = _number(where, "metric.amplifier", metric["amplifier"], 0, MAX_AMPLIFIER_V)
    if not isinstance(metric["material"], str):
        raise EloInputError(f"{where}: metric.material = {metric['material']!r}; give a material name or composition")
    from ..physics import get_material

    get_material(metric["material"])
    constraints = _table(where, doc, "constraints", {"clearance": 10.0})
    clearance = _number(where, "constraints.clearance", constraints["clearance"], 0, MAX_LENGTH_MM)
    opt = _table(where, doc, "optimizer", OPTIMIZER_DEFAULTS)
    if opt["sampler"] not in SAMPLERS:
        raise EloInputError(f"{where}: optimizer.sampler = {opt['sampler']!r}; choose {', '.join(SAMPLERS)}")
    opt["trials"] = _number(where, "optimizer.trials", opt["trials"], 1, MAX_TRIALS, integer=True)
    opt["batch"] = _number(where, "optimizer.batch", opt["batch"], 1, 1024, integer=True)
    opt["seed"] = _number(where, "optimizer.seed", opt["seed"], 0, MAX_SEED, integer=True)
    opt["grid_points"] = _number(where, "optimizer.grid_points", opt["grid_points"], 2, 1000, integer=True)
    if "grid_points" in doc.get("optimizer", {}) and opt["sampler"] != "grid":
        raise EloInputError(f"{where}: optimizer.grid_points = {opt['grid_points']} sets the grid of sampler = \"grid\" "
                            f"only; with sampler = {opt['sampler']!r} it would be recorded but not applied: drop it, "
                            "or set sampler = \"grid\"")
    if opt["sampler"] == "grid" and not symmetric:
        raise EloInputError(f"{where}: optimizer.sampler = 'grid' needs symmetric = true (a grid per detector "
                            "would hold grid_points^(5 x count) designs)")
    render = _table(where, doc, "render", RENDER_DEFAULTS)
    if "render" in doc and "e2_share" not in objectives and not second_event:
        raise EloInputError(f"{where}: [render] sets the chamber render of the objective e2_share (and of "
                            "optimize --second-event), which this run does not use: it would be recorded but not "
                            "applied; add e2_share to objectives, or drop [render]")
    render["resolution"] = _number(where, "render.resolution", render["resolution"], 1, 256, integer=True)
    render["spp"] = _number(where, "render.spp", render["spp"], 1, 4096, integer=True)
    out = OptimizeSpec(counts=counts, symmetric=symmetric, objectives=tuple(objectives), bounds=bounds,
                       metric=metric, clearance=clearance, optimizer=opt, render=render, source=where, text=text)
    if not any(out.free_parameters(c) for c in counts) and len(counts) == 1:
        raise EloInputError(f"{where}: every parameter is fixed and count is one number: nothing to optimise")
    return out
