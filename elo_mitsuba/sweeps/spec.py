"""The sweep spec: a TOML file naming a scene, the parameters to vary, the render settings and what
to keep per point; parsed and validated completely before anything renders.

Example (``examples/sweep_layouts.toml``)::

    scene = "corrugated_sheet"            # shipped name or XML path (relative to the spec file)
    seed = 0                              # one seed for every point (common random numbers)
    [fixed]                               # scene parameters (XML <default>s) held fixed
    wd = 400
    [vary]                                # swept: the Cartesian product of these lists
    layout = ["zeta25", "zeta50", "zeta60", "zeta75"]
    detectors.radius = [20, 25, 30]       # all four detectors; or right.radius, right.center ...
    [zip.geometry]                        # zipped group: one dimension "geometry", lists of equal length
    # dh = [200, 272]
    # dw = [100, 127]
    [render]
    resolution = 64                       # the scene parameter res
    events = 1
    quality = "default"                   # draft / default / reference / unbiased / scene; spp overrides
    [keep]
    channels = ["right", "left"]          # or "all"; images cost res^2 x 4 bytes each per point
    downsample = 2                        # box-average images by this factor before storing
    metrics = ["signal_mean", "signal_spread", "masked_fraction", "gradient_rms_eq26"]
    [surface]                             # a test surface: enables the gradient metrics
    object = "corrugated_sheet"           # or melt_plate, or height_map = "h.npy" + pixel_mm
    flat = "flat_plate"                   # the flat reference scene of the STSA correction

What a swept name means, and what it costs on a worker:

* an XML ``<default>`` of the scene (``dh``, ``dw``, ``layout``, ``res``, ``wd``, ``field``,
  ``material``, ...) is a *load-time* parameter: Mitsuba builds the geometry from it, so each
  distinct combination is one scene load per worker (points are grouped by it);
* ``spp``, ``events``, ``quality`` and detector moves (``<detector>.center``, ``.normal``,
  ``.radius``, ``detectors.radius``) change a loaded scene in place (``mi.traverse``): no reload,
  no recompilation.

The store names each swept key (and each zipped group) by :func:`dimension_name`: a Python
identifier, the spec key with ``.`` (and any other character an identifier cannot hold) as
``_``: ``right.radius`` is the dimension ``right_radius``, so ``ds.sel(right_radius=25)``; a
``[zip.NAME]`` group is the dimension ``NAME`` with one coordinate per member (``dh``,
``right_center``). A spec whose names would not make such keywords (a group ``[zip."2nd"]``, a
name the store or ``Dataset.sel`` uses itself, two keys with one name) is refused when parsed.
"""

from __future__ import annotations

import hashlib
import json
import keyword
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ..constants import MAX_SEED, MAX_SPP
from ..errors import EloInputError
from ..schema import event_channels
from ..options import MAX_EVENTS

#: Top-level keys of a spec.
SECTIONS = ("scene", "seed", "fixed", "vary", "zip", "render", "integrator", "keep", "surface")
#: Keys of [render].
RENDER_KEYS = ("resolution", "events", "quality", "spp")
#: Render settings that may also be swept (they change a loaded scene, never reload it).
RENDER_TIME = ("spp", "events", "quality")
#: Detector attributes a spec can move, and their value shapes.
DETECTOR_ATTRIBUTES = ("center", "normal", "radius")
#: The pseudo-detector whose attributes apply to every detector of the scene.
ALL_DETECTORS = "detectors"
#: Test surfaces whose true gradient the package knows.
SURFACE_OBJECTS = ("corrugated_sheet", "melt_plate")
#: Units of the coordinates (millimetres unless dimensionless).
UNITS = {"dh": "mm", "dw": "mm", "wd": "mm", "field": "mm", "fwhm": "mm", "res": "px",
         "center": "mm", "radius": "mm", "normal": "1", "spp": "1", "events": "1"}
#: Most points one spec may hold: far beyond a sensible sweep, but it stops a typo (a list of
#: 10^6 values) before the store is allocated.
MAX_POINTS = 1_000_000
#: Keywords of ``xarray.Dataset.sel`` itself: a dimension of that name could not be selected as
#: ``ds.sel(name=value)``.
SEL_KEYWORDS = ("indexers", "method", "tolerance", "drop")


def dimension_name(key: str) -> str:
    """The store's name for a swept spec key or zipped group: ``right.radius`` -> ``right_radius``,
    ``detectors.radius`` -> ``detectors_radius``, ``dh`` -> ``dh`` (every character a Python
    identifier cannot hold becomes ``_``), so that ``ds.sel(right_radius=25)`` selects it. The one
    mapping used by the store, sweep-plot and the spec's checks; the spec itself keeps its TOML
    keys (``right.radius = [...]``)."""
    return re.sub(r"\W", "_", str(key))


@dataclass(frozen=True)
class Member:
    """One swept name: ``key`` as the spec writes it, its values, and what it changes."""

    key: str
    values: tuple
    target: str                 # "scene" (load-time), "render" or "detector"
    detector: str | None = None  # for target "detector": the detector id or ALL_DETECTORS
    attribute: str | None = None  # center / normal / radius

    @property
    def units(self) -> str:
        return UNITS.get(self.attribute or self.key, "")

    @property
    def dim(self) -> str:
        """Its name in the store (:func:`dimension_name`): the dimension, or in a zipped group
        the coordinate along the group's dimension."""
        return dimension_name(self.key)


@dataclass(frozen=True)
class Axis:
    """One dimension of the sweep: a single product member, or a zipped group of several."""

    name: str
    members: tuple[Member, ...]

    def __len__(self):
        return len(self.members[0].values)

    @property
    def zipped(self) -> bool:
        return len(self.members) > 1 or self.members[0].key != self.name

    @property
    def dim(self) -> str:
        """The dimension's name in the store (:func:`dimension_name` of the key or group name;
        ``name`` stays the spec's, which the digest is made of)."""
        return dimension_name(self.name)


@dataclass
class SweepSpec:
    """A parsed and validated sweep spec (see the module docstring for the file format)."""

    scene: str
    source: str                       # where it came from, for messages
    text: str                         # the TOML text (stored in the output's attrs)
    seed: int = 0
    fixed: dict = field(default_factory=dict)
    axes: list[Axis] = field(default_factory=list)
    resolution: int | None = None
    events: int = 1
    quality: str = "default"
    spp: int | None = None
    integrator: dict = field(default_factory=dict)
    channels: list[str] | str = field(default_factory=list)
    downsample: int = 1
    metrics: list[str] | None = None   # None: every metric that applies
    surface: dict | None = None

    # -- the points --
    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(len(a) for a in self.axes)

    @property
    def n_points(self) -> int:
        return math.prod(self.shape)

    def point(self, index: int) -> "Point":
        """Point number ``index`` (C order over :attr:`shape`)."""
        idx = _unravel(index, self.shape)
        load = dict(self.fixed)
        if self.resolution is not None:
            load["res"] = self.resolution
        render = {"spp": self.spp, "events": self.events, "quality": self.quality, "seed": self.seed}
        moves: dict[str, dict] = {}
        values = {}
        for axis, i in zip(self.axes, idx):
            for m in axis.members:
                v = m.values[i]
                values[m.key] = v
                if m.target == "scene":
                    load[m.key] = v
                elif m.target == "render":
                    render[m.key] = v
                else:
                    moves.setdefault(m.detector, {})[m.attribute] = v
        return Point(index, idx, values, load, render, moves)

    def points(self):
        return (self.point(i) for i in range(self.n_points))

    def to_dict(self) -> dict:
        """Everything a worker needs, as plain data (what is shipped to a worker)."""
        return {"scene": self.scene, "source": self.source, "text": self.text, "seed": self.seed,
                "fixed": self.fixed, "resolution": self.resolution, "events": self.events,
                "quality": self.quality, "spp": self.spp, "integrator": self.integrator,
                "channels": self.channels, "downsample": self.downsample, "metrics": self.metrics,
                "surface": self.surface,
                "axes": [[a.name, [[m.key, list(m.values), m.target, m.detector, m.attribute]
                                   for m in a.members]] for a in self.axes]}

    @classmethod
    def from_dict(cls, d: dict) -> "SweepSpec":
        axes = [Axis(name, tuple(Member(k, tuple(_freeze(v) for v in vals), t, det, attr)
                                 for k, vals, t, det, attr in members))
                for name, members in d["axes"]]
        keys = ("scene", "source", "text", "seed", "fixed", "resolution", "events", "quality", "spp",
                "integrator", "channels", "downsample", "metrics", "surface")
        return cls(axes=axes, **{k: d[k] for k in keys})

    def digest(self) -> str:
        """Identity of the sweep (what decides whether an existing store may be resumed): the
        parsed content, not the file's formatting or comments."""
        d = self.to_dict()
        d.pop("text")
        d.pop("source")
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Point:
    """One sweep point: its flat index, its index per axis, the swept values, and what they do."""

    index: int
    idx: tuple[int, ...]
    values: dict
    load: dict      # scene parameters for load_scene (load-time key)
    render: dict    # spp, events, quality, seed
    moves: dict     # {detector or "detectors": {center/normal/radius: value}}

    @property
    def load_key(self) -> str:
        return json.dumps(self.load, sort_keys=True, default=str)


def _unravel(index, shape):
    out = []
    for n in reversed(shape):
        out.append(index % n)
        index //= n
    return tuple(reversed(out))


def _freeze(v):
    return tuple(v) if isinstance(v, list) else v


# ---- parsing -----------------------------------------------------------------------------------
def load_spec(spec, *, base_dir=None) -> SweepSpec:
    """Parse a sweep spec: a TOML file path, TOML text, a dict, or a :class:`SweepSpec`.

    Parameters
    ----------
    spec : str, Path, dict or SweepSpec
        A path to a ``.toml`` file, TOML text (a string containing a newline or ``=``), or the
        parsed table.
    base_dir : Path, optional
        Folder that relative scene and height-map paths are resolved against (default: the spec
        file's folder, or the current one).

    Returns
    -------
    SweepSpec
        Checked for everything that can be checked without loading the scene; the scene-dependent
        checks (parameter names, detectors, channels) are in :func:`check_against_scene`.

    Raises
    ------
    EloInputError
        One line ``<source>: <what is wrong, what is allowed>``.
    """
    if isinstance(spec, SweepSpec):
        return spec
    if isinstance(spec, dict):
        table, text, source = spec, _dump_toml(spec), "spec"
    else:
        s = str(spec)
        if "\n" in s or ("=" in s and not s.endswith(".toml")):
            text, source = s, "spec"
        else:
            path = Path(s)
            if path.suffix.lower() != ".toml":
                raise EloInputError(f"{path}: a sweep spec is a .toml file")
            try:
                text = path.read_text()
            except OSError as exc:
                raise EloInputError(f"{path}: cannot read the sweep spec ({exc.strerror or exc})") from None
            source = str(path)
            base_dir = path.parent if base_dir is None else base_dir
        try:
            table = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise EloInputError(f"{source}: not valid TOML ({exc})") from None
    return _parse(table, text, source, Path(base_dir) if base_dir is not None else Path("."))


def _fail(source, message):
    raise EloInputError(f"{source}: {message}")


def _parse(t: dict, text: str, source: str, base: Path) -> SweepSpec:
    unknown = [k for k in t if k not in SECTIONS]
    if unknown:
        _fail(source, f"unknown key {unknown[0]!r}; a sweep spec has: {', '.join(SECTIONS)}")
    if "scene" not in t:
        _fail(source, "no 'scene' (a shipped scene name such as \"flat_plate\", or an XML path)")
    scene = t["scene"]
    if not isinstance(scene, str) or not scene:
        _fail(source, f"scene = {scene!r}; give a shipped scene name or an XML path as a string")
    if scene.lower().endswith(".xml"):  # absolute: the digest (resume) must not depend on the cwd
        scene = str((base / scene).resolve())
    seed = _integer(source, "seed", t.get("seed", 0), 0, MAX_SEED)
    for sec in ("fixed", "vary", "zip", "render", "integrator", "keep", "surface"):
        if sec in t and not isinstance(t[sec], dict):
            _fail(source, f"{sec} must be a table ([{sec}]), not {type(t[sec]).__name__}")
    fixed = {}
    for k, v in t.get("fixed", {}).items():
        if not _scalar(v) or (_number(v) and not _finite(v)):
            _fail(source, f"fixed.{k} = {v!r}; a fixed scene parameter is one finite number or a string")
        if k in RENDER_KEYS or k == "res":
            _fail(source, f"fixed.{k}: set it in [render] ({', '.join(RENDER_KEYS)})")
        fixed[k] = v
    render = t.get("render", {})
    bad = [k for k in render if k not in RENDER_KEYS]
    if bad:
        _fail(source, f"unknown key render.{bad[0]}; [render] has: {', '.join(RENDER_KEYS)}")
    resolution = _integer(source, "render.resolution", render["resolution"], 1, 16384) \
        if "resolution" in render else None
    events = _integer(source, "render.events", render.get("events", 1), 1, MAX_EVENTS)
    spp = _integer(source, "render.spp", render["spp"], 1, MAX_SPP) if "spp" in render else None
    quality = _quality(source, "render.quality", render.get("quality", "default"))

    axes: list[Axis] = []
    seen: set[str] = set(fixed)
    for key, value in t.get("vary", {}).items():
        for member in _members(source, f"vary.{key}", key, value):
            if member.key in seen:
                _fail(source, f"{member.key} is given twice (in [fixed], [vary] or [zip])")
            seen.add(member.key)
            axes.append(Axis(member.key, (member,)))
    for name, group in t.get("zip", {}).items():
        if not isinstance(group, dict) or not group:
            _fail(source, f"zip.{name} must be a table of lists of equal length ([zip.{name}] dh = [...] dw = [...])")
        members = []
        for key, value in group.items():
            for member in _members(source, f"zip.{name}.{key}", key, value):
                if member.key in seen:
                    _fail(source, f"{member.key} is given twice (in [fixed], [vary] or [zip])")
                seen.add(member.key)
                members.append(member)
        lengths = {m.key: len(m.values) for m in members}
        if len(set(lengths.values())) > 1:
            _fail(source, f"zip.{name}: lists of different lengths ({', '.join(f'{k}: {n}' for k, n in lengths.items())}); "
                  "zipped lists pair up element by element")
        if name in seen:
            _fail(source, f"zip.{name}: the group's name is also a swept parameter; name it differently")
        axes.append(Axis(name, tuple(members)))
    _check_store_names(source, axes)
    _check_scene_values(source, fixed, axes)
    _check_detector_moves(source, axes)
    if "res" in seen and resolution is not None:
        _fail(source, "res is swept and render.resolution is set; give one of them")
    n = math.prod(len(a) for a in axes)
    if n > MAX_POINTS:
        _fail(source, f"{n} points; at most {MAX_POINTS} in one sweep (split it)")

    integrator = t.get("integrator", {})
    if integrator:
        from ..options import EloOptions

        try:
            EloOptions().replace(**integrator)
        except (EloInputError, TypeError, ValueError) as exc:
            _fail(source, f"[integrator]: {exc}")
        _check_integrator_applies(source, integrator, render, axes)

    keep = t.get("keep", {})
    bad = [k for k in keep if k not in ("channels", "downsample", "metrics")]
    if bad:
        _fail(source, f"unknown key keep.{bad[0]}; [keep] has: channels, downsample, metrics")
    channels = keep.get("channels", [])
    if channels != "all" and not (isinstance(channels, list) and all(isinstance(c, str) for c in channels)):
        _fail(source, f"keep.channels = {channels!r}; give \"all\" or a list of channel names (\"right\", \"right.e2\")")
    downsample = _integer(source, "keep.downsample", keep.get("downsample", 1), 1, 4096)
    if downsample > 1 and not channels:  # it applies to kept images only: accepted, it would change nothing
        _fail(source, f"keep.downsample = {downsample} shrinks kept images, and keep.channels keeps none; give "
              "keep.channels (\"all\" or a list) too, or drop keep.downsample")
    metrics = keep.get("metrics")
    if metrics is not None:
        from .metrics import METRICS

        if not isinstance(metrics, list) or not all(isinstance(m, str) for m in metrics):
            _fail(source, f"keep.metrics = {metrics!r}; give a list of metric names ({', '.join(METRICS)})")
        bad = [m for m in metrics if m not in METRICS]
        if bad:
            _fail(source, f"unknown metric {bad[0]!r}; metrics: {', '.join(METRICS)}")
    swept = {m.key for a in axes for m in a.members}
    if (channels == "all" or channels) and ({"res", "field"} & swept):
        _fail(source, "keep.channels with res or field swept: the images would not share one pixel grid; "
              "keep metrics only, or fix res and field")
    surface = _surface(source, t.get("surface"), base)
    spec = SweepSpec(scene=scene, source=source, text=text, seed=seed, fixed=fixed, axes=axes,
                     resolution=resolution, events=events, quality=quality, spp=spp, integrator=dict(integrator),
                     channels=channels, downsample=downsample, metrics=metrics, surface=surface)
    if resolution is not None and resolution % downsample:
        _fail(source, f"keep.downsample = {downsample} does not divide render.resolution = {resolution}")
    return spec


def _where(axes) -> dict:
    """Where the spec gives each swept key (``vary.dh``, ``zip.position.dh``), for messages."""
    return {m.key: (f"zip.{a.name}.{m.key}" if a.zipped else f"vary.{m.key}") for a in axes for m in a.members}


def _check_scene_values(source, fixed: dict, axes) -> None:
    """A ``layout`` and the ``dh``/``dw`` it sets, both fixed or swept, refused as the render command
    refuses ``-D layout=... -D dh=...`` (:func:`~elo_mitsuba.scene_files.scene_values`, the one rule):
    the store would name a layout whose geometry its points do not have."""
    from ..scene_files import scene_values

    where = {**{k: f"fixed.{k}" for k in fixed}, **_where(axes)}
    first = {**fixed, **{m.key: m.values[0] for a in axes for m in a.members if m.target == "scene"}}
    try:
        scene_values(None, first, names=where)
    except EloInputError as exc:
        _fail(source, str(exc))


def _check_detector_moves(source, axes) -> None:
    """One attribute swept for all detectors (``detectors.radius``) and for one of them
    (``right.radius``): the one detector's value wins at every point (the worker applies
    ``detectors`` first), so its images would not vary along the other dimension, which the store
    says they do."""
    where = _where(axes)
    moves = [m for a in axes for m in a.members if m.target == "detector"]
    for every in (m for m in moves if m.detector == ALL_DETECTORS):
        one = next((m for m in moves if m.detector != ALL_DETECTORS and m.attribute == every.attribute), None)
        if one is not None:
            _fail(source, f"{where[one.key]} and {where[every.key]} both set the {one.attribute} of {one.detector!r} "
                  f"({one.key} wins, so {one.detector!r} would not vary with {every.key}); sweep each detector's "
                  f"{one.attribute} by its name, or only {every.key}")


def _check_integrator_applies(source, integrator: dict, render: dict, axes) -> None:
    """Refuse ``[integrator]`` options a point would record but not apply: ``events`` (every
    point renders with [render]'s or the swept events) and, under a quality preset, the options
    it sets (:data:`~elo_mitsuba.options.PRESET_FIELDS`: each render applies its preset over
    them). Worded as :func:`~elo_mitsuba.options.check_combination`, the render command's rule,
    whose sample counts need the scene and are checked in :mod:`.validate`."""
    from ..options import PRESET_FIELDS, QUALITY_PRESETS

    if "events" in integrator:
        events = integrator["events"]
        _fail(source, f"integrator.events={events!r} would change nothing: every point renders with render.events "
              f"(default 1) or the swept events; set [render] events = {events!r} instead")
    overridden = [k for k in PRESET_FIELDS if k in integrator]
    if not overridden:
        return
    swept = [v for a in axes for m in a.members if m.key == "quality" for v in m.values]
    if swept:  # then render.quality is not used
        presets = [q for q in swept if q in QUALITY_PRESETS]
        where = f"the swept quality {presets[0]!r}" if presets else None
    else:
        quality = render.get("quality", "default")
        presets = [quality] if quality in QUALITY_PRESETS else []
        where = f"render.quality {quality!r}" + ("" if "quality" in render else " (the default)")
    if presets:
        name = overridden[0]
        _fail(source, f"integrator.{name}={integrator[name]!r} would change nothing: {where} sets {name} itself "
              f"(a preset sets {', '.join(PRESET_FIELDS)}); use render.quality = \"scene\" for [integrator]'s "
              "settings, or drop it")


def _store_names(axes) -> list[tuple[str, str]]:
    """(name in the store, where the spec gives it) of every swept dimension and coordinate."""
    out = []
    for a in axes:
        group = f"zip.{a.name}" if a.zipped else None
        out.append((a.dim, group or f"vary.{a.name}"))
        for m in a.members:
            where = f"{group}.{m.key}" if group else f"vary.{m.key}"
            if a.zipped:
                out.append((m.dim, where))
            if m.attribute in ("center", "normal"):
                out.append((f"{m.dim}_xyz", where))
    return out


def _check_store_names(source, axes) -> None:
    """Every dimension and coordinate name (:func:`dimension_name`) a keyword ``ds.sel`` accepts,
    none the store's own, no two alike."""
    from .metrics import METRICS
    from .store import RESERVED_NAMES

    taken: dict[str, str] = {}
    for name, where in _store_names(axes):
        why = None
        if not name.isidentifier() or keyword.iskeyword(name):
            why = "is not a Python identifier"
        elif name in SEL_KEYWORDS:
            why = "is a keyword of Dataset.sel itself"
        elif name in RESERVED_NAMES or name in METRICS or name.startswith("image_"):
            why = "is a name the store uses itself"
        if why:
            _fail(source, f"{where}: its store name {name!r} {why} (a swept key is stored with '.' as '_', a "
                  "name ds.sel(name=value) takes; a [zip.NAME] group as NAME: letters, digits, _); choose another name")
        if name in taken:
            _fail(source, f"{taken[name]} and {where} would both be the store's {name!r} (spec keys are "
                  "stored with '.' as '_'); rename one")
        taken[name] = where


def _members(source, where, key, value) -> list[Member]:
    """The member(s) of one [vary]/[zip] entry: a list of values, or a detector table."""
    if isinstance(value, dict):  # right.center = [...] arrives as {"right": {"center": [...]}}
        out = []
        for attr, vals in value.items():
            if attr not in DETECTOR_ATTRIBUTES:
                _fail(source, f"{where}.{attr}: a detector moves by {', '.join(DETECTOR_ATTRIBUTES)}")
            out.append(_detector_member(source, f"{where}.{attr}", key, attr, vals))
        return out
    vals = _list(source, where, value)
    if key in RENDER_TIME:
        if key == "quality":
            vals = [_quality(source, where, v) for v in vals]
        else:
            vals = [_integer(source, where, v, 1, MAX_SPP if key == "spp" else MAX_EVENTS) for v in vals]
        return [Member(key, tuple(vals), "render")]
    if key == "resolution":
        _fail(source, f"{where}: sweep the scene parameter res (render.resolution fixes it)")
    kinds = {type(v) for v in vals}
    if not all(_scalar(v) for v in vals):
        _fail(source, f"{where} = {value!r}; scene parameter values are numbers or strings")
    bad = [v for v in vals if _number(v) and not _finite(v)]
    if bad:
        _fail(source, f"{where}: value {bad[0]!r}; scene parameter values are finite numbers or strings")
    if len({float if k is int else k for k in kinds}) > 1:
        _fail(source, f"{where} = {value!r}; mixes numbers and strings")
    if len(set(vals)) < len(vals):
        _fail(source, f"{where} = {value!r}; a value appears twice")
    return [Member(key, tuple(vals), "scene")]


def _detector_member(source, where, detector, attr, value) -> Member:
    vals = _list(source, where, value)
    out = []
    for v in vals:
        if attr == "radius":
            if not _number(v) or not (v > 0 and _finite(v)):
                _fail(source, f"{where}: radius {v!r}; give numbers > 0 (mm)")
            out.append(float(v))
        else:
            if not (isinstance(v, list) and len(v) == 3 and all(_number(c) and _finite(c) for c in v)):
                _fail(source, f"{where}: {v!r}; a {attr} is a list of 3 numbers ({'mm' if attr == 'center' else 'unit vector'})")
            vec = tuple(float(c) for c in v)
            if attr == "normal" and not any(vec):
                _fail(source, f"{where}: normal {list(vec)} is zero")
            out.append(vec)
    if len(set(out)) < len(out):
        _fail(source, f"{where}: a value appears twice")
    return Member(f"{detector}.{attr}", tuple(out), "detector", detector, attr)


def _list(source, where, value) -> list:
    if not isinstance(value, list):
        _fail(source, f"{where} = {value!r}; a swept parameter is a list of values ([a, b, ...])")
    if not value:
        _fail(source, f"{where} is an empty list; give at least one value")
    return value


def _scalar(v) -> bool:
    return isinstance(v, str) or _number(v)


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _finite(v) -> bool:
    try:
        return math.isfinite(v)
    except OverflowError:  # an int beyond float (10**400) is not a usable number either
        return False


def _integer(source, where, v, lo, hi) -> int:
    if not (_number(v) and _finite(v) and float(v) == int(v)) or v < lo or (hi is not None and v > hi):
        rng = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        _fail(source, f"{where} = {v!r}; must be a whole number {rng}")
    return int(v)


def _quality(source, where, v) -> str:
    from ..options import QUALITIES

    if v not in QUALITIES:
        _fail(source, f"{where} = {v!r}; choose one of {', '.join(QUALITIES)}")
    return v


def _surface(source, s, base: Path):
    if s is None:
        return None
    bad = [k for k in s if k not in ("object", "height_map", "pixel_mm", "flat")]
    if bad:
        _fail(source, f"unknown key surface.{bad[0]}; [surface] has: object, height_map, pixel_mm, flat")
    if ("object" in s) == ("height_map" in s):
        _fail(source, f"[surface]: give either object ({', '.join(SURFACE_OBJECTS)}) or height_map (+ pixel_mm)")
    out = {"flat": s.get("flat", "flat_plate")}
    if not isinstance(out["flat"], str) or not out["flat"]:
        _fail(source, f"surface.flat = {out['flat']!r}; the flat reference scene's name or XML path")
    if out["flat"].lower().endswith(".xml"):
        out["flat"] = str((base / out["flat"]).resolve())
    if "object" in s:
        if not isinstance(s["object"], str) or s["object"] not in SURFACE_OBJECTS:
            _fail(source, f"surface.object = {s['object']!r}; the package knows the true gradient of "
                  f"{', '.join(SURFACE_OBJECTS)} (else give height_map and pixel_mm)")
        out["object"] = s["object"]
    else:
        if not isinstance(s["height_map"], str) or not s["height_map"]:
            _fail(source, f"surface.height_map = {s['height_map']!r}; the height map's path (.npy, .tif, .csv)")
        path = Path(s["height_map"])
        path = path if path.is_absolute() else base / path
        if not path.is_file():
            _fail(source, f"surface.height_map {str(path)!r} does not exist")
        from ..heightmap import load_heightmap

        try:  # readable, 2-D, finite: checked now, not on every worker
            load_heightmap(path)
        except EloInputError as exc:
            _fail(source, f"surface.height_map: {exc}")
        if not (_number(s.get("pixel_mm")) and _finite(s["pixel_mm"]) and s["pixel_mm"] > 0):
            _fail(source, f"surface.pixel_mm = {s.get('pixel_mm')!r}; the height map's pixel size in mm (> 0)")
        out["height_map"] = str(path.resolve())
        out["pixel_mm"] = float(s["pixel_mm"])
    return out


def check_parameters(spec: SweepSpec) -> None:
    """Every fixed and swept scene parameter is declared by the scene file (read from the XML,
    before anything is loaded). Raises EloInputError, without the spec's name (the caller adds it)."""
    from ..scene_files import declared_parameters, resolve_scene_path

    path = resolve_scene_path(spec.scene)
    declared = set(declared_parameters(path, {k: str(v) for k, v in spec.point(0).load.items()}))
    for name in list(spec.fixed) + [m.key for a in spec.axes for m in a.members if m.target == "scene"]:
        if name not in declared:
            # the caller (sweeps.validate) names the spec, as for the scene's own errors
            raise EloInputError(f"unknown parameter {name!r}: {path.name} declares {', '.join(sorted(declared))}; "
                                f"render settings: {', '.join(RENDER_TIME)}; detector moves: "
                                f"<detector>.{{{','.join(DETECTOR_ATTRIBUTES)}}}")


def check_against_scene(spec: SweepSpec, scene) -> None:
    """The checks that need the loaded scene (an :class:`~elo_mitsuba.EloScene` of the first
    point): every swept and fixed name is a parameter of the scene, every moved detector
    exists, kept channels exist, the asked-for metrics apply. Raises EloInputError."""
    from .metrics import METRICS

    src = spec.source
    declared = set(scene.params)
    for name in list(spec.fixed) + [m.key for a in spec.axes for m in a.members if m.target == "scene"]:
        if name not in declared:
            _fail(src, f"unknown parameter {name!r}: {scene.path.name} declares {', '.join(sorted(declared))}; "
                  f"render settings: {', '.join(RENDER_TIME)}; detector moves: <detector>.{{{','.join(DETECTOR_ATTRIBUTES)}}}")
    dets = scene.detector_names
    for a in spec.axes:
        for m in a.members:
            if m.target == "detector" and m.detector != ALL_DETECTORS and m.detector not in dets:
                _fail(src, f"unknown detector {m.detector!r} in {m.key}; the scene's detectors: {', '.join(dets)} "
                      f"(or {ALL_DETECTORS!r} for all)")
            if m.target == "detector" and f"{dets[0]}.to_world" not in scene.mi_params:
                _fail(src, f"{m.key}: the scene's detectors are not disks; they cannot be moved")
    events = [spec.events] + [v for a in spec.axes for m in a.members if m.key == "events" for v in m.values]
    if spec.channels and spec.channels != "all":
        allowed = set(dets) | set(event_channels(dets, min(events))) if min(events) > 1 else set(dets)
        bad = [c for c in spec.channels if c not in allowed]
        if bad:
            _fail(src, f"keep.channels: unknown channel {bad[0]!r}; channels: {', '.join(sorted(allowed))}")
    ctx = {"events": min(events), "surface": spec.surface is not None, "detectors": dets}
    for name in spec.metrics or []:
        why = METRICS[name].unavailable(ctx)
        if why:
            _fail(src, f"metric {name!r} {why}")


def _dump_toml(table: dict, prefix: str = "") -> str:
    """A small TOML writer for the specs this module reads (dict specs are stored as text)."""
    lines, tables = [], []
    for k, v in table.items():
        if isinstance(v, dict):
            tables.append((k, v))
        else:
            lines.append(f"{json.dumps(k) if not k.isidentifier() else k} = {json.dumps(v)}")
    out = ([f"[{prefix}]"] if prefix and lines else []) + lines
    for k, v in tables:
        out.append(_dump_toml(v, f"{prefix}.{k}" if prefix else k))
    return "\n".join(out)

