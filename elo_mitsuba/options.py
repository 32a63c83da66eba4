"""The options of the ``elo`` integrator, validated once, and the quality presets that set them.

:class:`EloOptions` is the one description of how a render estimates the detector signals: the
integrator reads it from the scene file (:meth:`EloOptions.from_props`), the Python API and the
CLI change it only through :meth:`EloOptions.replace` and ``integrator.configure(options)``, and
the output header records it whole (:meth:`EloOptions.as_dict`). A value outside its range is
refused with one line naming the option, the value and what is allowed, before any work starts.

:func:`quality_options` turns a preset of :data:`QUALITY_PRESETS` (measured in
``benchmarks/RESULTS.md``) into options and a sample count for a scene's resolution, events and
beam profile.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from .constants import BEAM_CURRENT_A, TRANSIMPEDANCE_V_PER_A
from .errors import EloInputError

UNITS = ("fraction", "voltage")
STRATEGIES = ("independent", "stratified", "quadrature")
VISIBILITY = ("sampled", "triangle")
#: Most triangles of one detector in the quadrature (the loop over them is unrolled).
MAX_QUADRATURE_TRIANGLES = 256
#: Most paths per pixel ``bounce_min`` may ask for.
MAX_BOUNCE_MIN = 4096
#: Most scattering events: each is unrolled into the kernel, whose compile time grows with
#: events^2 (2 cores: events 8 about 80 s, 10 about 2 min; elo_mitsuba.budget); in the shipped
#: scenes events above 4 add < 0.1 % of the signal.
MAX_EVENTS = 10
#: Most strata per side of the far-field control variate (its s x s samples run in a loop).
MAX_FAR_FIELD = 32
#: The bounce filter's angle (the option's default, and the presets'): windows stop where the 1st
#: event's normals differ by more.
FILTER_ANGLE_DEG = 1.0


def _option(default, doc: str, kind: str, *, xml: bool = True, choices=None, bounds=None):
    """A dataclass field carrying its documentation, its kind and its allowed values."""
    return field(default=default, metadata={"doc": doc, "kind": kind, "xml": xml, "choices": choices,
                                            "bounds": bounds})


@dataclass(frozen=True)
class EloOptions:
    """How the ``elo`` integrator estimates N_d/N_0 (all fields validated on construction).

    The fields are the integrator's XML parameters (``<integer name="events" value="2"/>``, ...),
    except ``occlusion_analysis`` and ``count_rays`` (Python only). See
    :data:`elo_mitsuba.plugins.integrator_elo` for what each strategy does.
    """

    events: int = _option(1, "scattering events counted (1 = first event only); Mitsuba's max_depth = events + 1",
                          "int", bounds=(1, MAX_EVENTS))
    detector_sampling: str = _option("independent", "how the 1st event's detector integral (Eq. 5) is "
                                     "estimated", "str", choices=STRATEGIES)
    detector_samples: int = _option(1, "points sampled on each detector per event (independent, stratified)",
                                    "int", bounds=(1, None))
    bounce_detector_samples: int | None = _option(None, "points per detector at events >= 2 (default: "
                                                  "detector_samples)", "int", bounds=(1, None))
    front_only: str = _option("", "detectors shielded on their back, collecting on the front face only "
                              "(comma-separated ids, '*' = all; default: every detector collects on both faces)",
                              "text")
    quadrature_triangles: int = _option(8, "triangles per detector in the quadrature of Appendix A", "int",
                                        bounds=(4, MAX_QUADRATURE_TRIANGLES))
    quadrature_visibility: str = _option("sampled", "occlusion in the quadrature: one sampled ray per detector, "
                                         "or one ray per triangle", "str", choices=VISIBILITY)
    bounce_samples: int = _option(1, "continuation paths per sample (splitting, stratified: about q k of them sample g_BSE's "
                                  "lobe, q its probability, the rest its diffuse part, each group spread over its sample "
                                  "space)", "int",
                                  bounds=(1, None))
    bounce_fraction: float = _option(1.0, "fraction f of the samples that trace events >= 2 (blocks of 32 "
                                     "lanes, weight 1/f)", "float", bounds=(0.0, 1.0))
    bounce_filter: float = _option(0.0, "half-width (mm) of the normal-guided window average of events >= 2 "
                                   "(0 = off; with far_table the 2nd event's residual about the tabulated mean is "
                                   "averaged, the mean stays per pixel)", "float", bounds=(0.0, None))
    bounce_filter_angle: float = _option(FILTER_ANGLE_DEG, "normals differing by more than this (deg) stop the "
                                         "window (with far_table: the window of the residual about its mean)",
                                         "float", bounds=(0.0, 90.0))
    bounce_share: float = _option(0.0, "side (mm) of the blocks in which pixels of matching geometry share their "
                                  "events >= 2 (same normal within 1 deg, 64 probe rays meeting surfaces at the same "
                                  "distance within a factor 1.65; 0 = off; plugins/_geometry_classes.py), their paths one point set "
                                  "per class; for relief that scatters onto itself, instead of bounce_filter", "float",
                                  bounds=(0.0, None))
    bounce_min: float = _option(0.0, "paths per pixel below which a second pass tops events >= 2 up (0 = off)",
                                "float", bounds=(0.0, MAX_BOUNCE_MIN))
    far_field: int = _option(0, "far-field control variate of events >= 2: s x s cheap g_BSE samples per sample "
                             "against a cached wall response (0 = off; plugins/_far_field.py); unbiased, but a "
                             "single event's image can then hold values <= 0 where its residual outweighs the "
                             "variate (0.3-0.4 % of e2 pixels on relief at s = 8)", "int",
                             bounds=(0, MAX_FAR_FIELD))
    far_table: bool = _option(False, "far-field control variate of events >= 2 with its mean tabulated once per "
                              "geometry (M(p, n) = int g_BSE L over the table's bins, bilinear in the nodes and the "
                              "normal) instead of sampled: no cheap samples, no ray per pixel; directions that meet "
                              "the relief again carry the variate too (plugins/_far_field.py)", "bool")
    far_roulette: float = _option(1.0, "probability q that a far-field path traces its events >= 3 (Russian "
                                  "roulette, blocks of 32 lanes, weight 1/q; 1 = always, as the presets: q < 1 "
                                  "did not pay; needs far_field >= 1)", "float", bounds=(0.0, 1.0))
    far_field_later: bool = _option(False, "the far-field table also holds events >= 3 and every cheap sample looks "
                                    "them up (their variate, as before issue 26's item 3: < 3 % less error in them "
                                    "for ~1.5x the time at events 4; benchmarks/events_cost.py compares)", "bool",
                                    xml=False)
    units: str = _option("fraction", "N_d/N_0 ('fraction') or detector voltage U_d = N_d/N_0 I_b T "
                         "('voltage', Eq. 9)", "str", choices=UNITS)
    beam_current: float = _option(BEAM_CURRENT_A, "beam current I_b (A) of Eq. 9", "float", bounds=(0.0, None))
    transimpedance: float = _option(TRANSIMPEDANCE_V_PER_A, "amplifier transimpedance T (V/A) of Eq. 9",
                                    "float", bounds=(0.0, None))
    occlusion_analysis: bool = _option(True, "skip shadow rays that provably cannot be blocked", "bool",
                                       xml=False)
    count_rays: bool = _option(False, "count the rays cast per sample (integrator.ray_counts; benchmarks)",
                               "bool", xml=False)

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = _coerce(f, getattr(self, f.name))
            object.__setattr__(self, f.name, value)
        if self.bounce_detector_samples is None:
            object.__setattr__(self, "bounce_detector_samples", self.detector_samples)
        gain = self.beam_current * self.transimpedance  # volts per unit of N_d/N_0 (Eq. 9)
        if not VOLTS_PER_SIGNAL[0] <= gain <= VOLTS_PER_SIGNAL[1]:
            raise EloInputError(f"elo: beam_current={self.beam_current!r} A x transimpedance="
                                f"{self.transimpedance!r} V/A = {gain:.3g} V per unit signal (Eq. 9); must be "
                                f"{VOLTS_PER_SIGNAL[0]:g} to "
                                f"{VOLTS_PER_SIGNAL[1]:g} V so that the images stay float32 numbers")
        if self.bounce_share > 0 and self.bounce_filter > 0:
            raise EloInputError(f"elo: bounce_share={self.bounce_share:g} mm and bounce_filter={self.bounce_filter:g} mm "
                                "both average events >= 2 and only one applies; set one of them to 0")
        if self.far_table and self.far_field > 0:
            raise EloInputError(f"elo: far_table=True tabulates the far field's mean; far_field={self.far_field} "
                                "(its s x s sampled mean) would be recorded but not applied; set far_field=0")
        if self.far_table and self.far_field_later:
            raise EloInputError("elo: far_table=True tabulates the 2nd event's mean only; far_field_later=True "
                                "would be recorded but not applied; drop it")
        if self.far_field_later and self.far_field == 0:
            raise EloInputError("elo: far_field_later=True applies to the far field's table only and would be "
                                "recorded but not applied with far_field=0; set far_field >= 1")
        if self.far_roulette < 1.0 and self.far_field == 0:
            raise EloInputError(f"elo: far_roulette={self.far_roulette!r} applies to the far field's paths only and "
                                "would be recorded but not applied with far_field=0; set far_field >= 1, or "
                                "far_roulette=1")

    # -- construction --
    @classmethod
    def from_props(cls, props) -> "EloOptions":
        """The options a scene file gives (``mi.Properties`` of ``<integrator type="elo">``)."""
        given = {}
        for f in dataclasses.fields(cls):
            if f.metadata["xml"] and f.name in props:
                given[f.name] = props.get(f.name)
        options = cls(**given)
        check_combination(given, base=options, prefix="elo: ")  # the scene's own settings (presets: at render)
        return options

    def replace(self, **changes) -> "EloOptions":
        """A copy with ``changes`` applied and validated; unknown names are refused."""
        unknown = [k for k in changes if k not in _FIELDS]
        if unknown:
            raise EloInputError(f"elo: no option {unknown[0]!r}; options are {', '.join(_FIELDS)}")
        options = dataclasses.replace(self, **changes)
        check_combination(changes, base=options)
        return options

    def as_dict(self) -> dict[str, Any]:
        """Every option by name (what the output header records)."""
        return {f: getattr(self, f) for f in _FIELDS}


def _coerce(f: dataclasses.Field, value):
    """``value`` as the field's kind, or :class:`EloInputError` naming option, value and range."""
    kind, name = f.metadata["kind"], f.name
    if value is None and f.default is None:
        return None
    if kind == "bool":
        if not isinstance(value, bool):
            raise EloInputError(f"elo: {name}={value!r}; must be true or false")
        return value
    if kind == "text":
        if not isinstance(value, str):
            raise EloInputError(f"elo: {name}={value!r}; must be text")
        return value.strip()
    if kind == "str":
        value = str(value)
        choices = f.metadata["choices"]
        if value not in choices:
            raise EloInputError(f"elo: {name}={value!r}; allowed: {', '.join(choices)}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) and not hasattr(value, "__float__"):
        raise EloInputError(f"elo: {name}={value!r}; must be a number")
    try:
        number = float(value)
    except OverflowError:  # an int beyond float (10**400)
        raise EloInputError(f"elo: {name}={value!r}; must be a finite number") from None
    except (TypeError, ValueError):  # an array of several numbers
        raise EloInputError(f"elo: {name}={' '.join(repr(value).split())}; must be one number") from None
    if kind == "int":
        if not (math.isfinite(number) and number == int(number)):
            raise EloInputError(f"elo: {name}={value!r}; must be a whole number")
        number = int(number)
    lo, hi = f.metadata["bounds"]
    if not _in_range(name, number, lo, hi):
        finite = "" if math.isfinite(number) else "a finite number "  # inf is >= 0 but still refused
        raise EloInputError(f"elo: {name}={value!r}{_UNIT.get(name, '')}; must be {finite}"
                            f"{_range_text(name, kind, lo, hi)}")
    return number


#: I_b T (V) allowed in Eq. 9: a float32 image of N_d/N_0 (1e-12 to 1 in practice) times it stays
#: within float32's normal numbers (1.2e-38 to 3.4e38); 1e300 wrote Inf after the render, and
#: 1e-300 would have written zeros. Real chains give 1e-2 to 1e4 V (3 mA x 1e5 V/A = 300 V).
VOLTS_PER_SIGNAL = (1e-20, 1e20)
#: Bounds that are open (the value may not equal them), by option.
_OPEN = {"bounce_fraction": "lo", "far_roulette": "lo", "bounce_filter_angle": "both", "beam_current": "lo",
         "transimpedance": "lo"}
_UNIT = {"bounce_filter": " mm", "bounce_share": " mm", "bounce_filter_angle": " deg"}
_NOTE = {"events": " (1 = first event only; each event is unrolled into the kernel, whose compile time grows "
                   "with events^2: 10 take about 2 min on 2 cores)", "bounce_filter": " (0 = off)", "bounce_share": " (0 = off)",
         "bounce_min": " (0 = off)"}


def _in_range(name, x, lo, hi) -> bool:
    if not math.isfinite(x):
        return False
    open_ = _OPEN.get(name, "")
    if lo is not None and (x <= lo if open_ in ("lo", "both") else x < lo):
        return False
    return hi is None or (x < hi if open_ == "both" else x <= hi)


def _range_text(name, kind, lo, hi) -> str:
    open_ = _OPEN.get(name, "")
    if hi is None:
        text = f"> {lo:g}" if open_ else f">= {lo:g}"
    else:
        left = "(" if open_ in ("lo", "both") else "["
        right = ")" if open_ == "both" else "]"
        text = f"in {left}{lo:g}, {hi:g}{right}"
    return text + _NOTE.get(name, "")


_FIELDS = tuple(f.name for f in dataclasses.fields(EloOptions))


#: Options that only scale volts (Eq. 9), and those that set how many points a detector is sampled at.
_VOLT_OPTIONS = ("beam_current", "transimpedance")
SAMPLE_OPTIONS = ("detector_samples", "bounce_detector_samples")


def check_combination(given: Mapping[str, Any], *, base: EloOptions | None = None, qualities=None,
                      events: int | None = None, bounce_possible: bool = True, prefix: str = "",
                      flags: Mapping[str, str] | None = None) -> None:
    """Refuse settings that a render would record but not apply: the one rule for every entry
    point (``EloOptions.replace`` and so ``EloScene.configure``, the render command, sweeps).

    Parameters
    ----------
    given : mapping
        The options being set, by name (their values are validated by :class:`EloOptions`).
    base : EloOptions, optional
        The options they are set on (default: the defaults); ``units`` and ``detector_sampling``
        not in ``given`` come from it.
    qualities : iterable of str, optional
        The quality presets the settings will be rendered with (a preset of
        :data:`QUALITY_PRESETS` integrates the 1st event by the quadrature); default: the options
        as they are.
    events : int, optional
        The most events rendered (None: not known yet, events >= 2 may come).
    bounce_possible : bool
        Whether the scene can scatter an electron twice.
    prefix, flags : str, mapping
        How the message names an option: ``{prefix}{name}={value!r}``, or the command-line flag of
        ``flags[name]`` (with ``flags["quality"]`` and ``flags["events"]`` for the advice).

    Raises
    ------
    EloInputError
        ``beam_current``/``transimpedance`` without ``units="voltage"`` (they scale volts only);
        ``detector_samples``/``bounce_detector_samples`` where neither is used: the 1st event
        integrated by the triangle quadrature and no events >= 2 that sample the detectors.
    """
    flags = dict(flags or {})
    base = base if base is not None else EloOptions()

    def say(name, value):
        if name in flags:
            return f"{flags[name]} {value}"
        return f"{prefix}{name}={value!r}" if name in _FIELDS else f"{name} {value!r}"

    units = given.get("units", base.units)
    volts = [k for k in _VOLT_OPTIONS if k in given]
    if volts and units != "voltage":
        raise EloInputError(f"{say(volts[0], given[volts[0]])} scales volts only (Eq. 9: U_d = N_d/N_0 I_b T) and "
                            f"would be recorded but not applied; add {say('units', 'voltage')}")
    samples = [k for k in SAMPLE_OPTIONS if k in given]
    if not samples:
        return
    later = ("bounce_detector_samples" in given and bounce_possible and (events is None or events >= 2))
    own = given.get("detector_sampling", base.detector_sampling)
    for quality in (list(qualities) if qualities is not None else [None]):
        preset = quality in QUALITY_PRESETS
        if later or ("detector_samples" in given and not preset and own != "quadrature"):
            continue
        why = (f"{say('quality', quality)} integrates the 1st event by the triangle quadrature" if preset else
               f"{say('detector_sampling', 'quadrature')} integrates the 1st event by the triangle quadrature"
               if "detector_samples" in given else "the 1st event uses detector_samples")
        if "bounce_detector_samples" not in given:
            later_text = "events >= 2 use bounce_detector_samples"
        else:
            later_text = "this render has no events >= 2" if bounce_possible else "this scene cannot scatter twice"
        advice = (f"use {say('quality', 'scene')} (sampled detectors) or {say('events', 2)} in a scene that "
                  "scatters twice" if flags else
                  f"set {prefix}detector_sampling='independent' or 'stratified' with it (not with a quality "
                  f"preset), or {prefix}bounce_detector_samples for events >= 2")
        raise EloInputError(f"{say(samples[0], given[samples[0]])} would change nothing: {why}, and {later_text}; "
                            f"{advice}")


def check_scene_options(scene_options: Mapping[str, Any], qualities, where: str) -> None:
    """Refuse to render under a quality preset a scene file that sets the sampling the preset
    sets or makes unused (``scene_options``: what its ``<integrator>`` gives; ``where``: the file):
    the file would say one thing and the render do another.

    >>> check_scene_options({"events": 2}, ["default"], "a.xml")
    >>> check_scene_options({"detector_samples": 16}, ["scene", "draft"], "a.xml")
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: a.xml sets detector_samples=16, which quality 'draft' would override or not use; render with quality 'scene' (--quality scene) to use the file's
    """
    own = [f"{k}={v!r}" for k, v in scene_options.items() if k in PRESET_FIELDS + SAMPLE_OPTIONS]
    for quality in qualities:
        if quality in QUALITY_PRESETS and own:
            raise EloInputError(f"{where} sets {', '.join(own)}, which quality {quality!r} would override or not "
                                "use; render with quality 'scene' (--quality scene) to use the file's")


def parameter_table() -> str:
    """The integrator's XML parameters as a text table (name, type, default, meaning)."""
    rows = []
    for f in dataclasses.fields(EloOptions):
        if not f.metadata["xml"]:
            continue
        allowed = f.metadata["choices"]
        kind = f.metadata["kind"] if not allowed else " | ".join(allowed)
        default = "detector_samples" if f.default is None else repr(f.default)
        rows.append((f.name, kind, default, f.metadata["doc"]))
    width = [max(len(r[i]) for r in rows) for i in range(3)]
    return "\n".join(f"    {n:<{width[0]}}  {k:<{width[1]}}  {d:<{width[2]}}  {doc}" for n, k, d, doc in rows)


# ---- quality presets ----------------------------------------------------------------------------
#: Quality presets (measured in benchmarks/RESULTS.md). The 1st event uses the triangle
#: quadrature of Appendix A (``quadrature_triangles``; deterministic with a single-ray beam, so one
#: sample per pixel suffices; ``spp_blur`` samples when the beam has a profile, fwhm > 0). Events
#: >= 2 get ``bounce_budget`` continuation paths per window of ``bounce_filter`` mm half-width
#: (a normal-guided average, see the elo integrator; 0 = per pixel), spread over the pixels by
#: ``bounce_fraction`` / ``bounce_samples`` for the scene's resolution; pixels where the window
#: must shrink (edges, flanks) are topped up to ``bounce_min`` paths. On a scene with relief that
#: can scatter onto itself (a scattering surface that is not one plane: an object in a chamber)
#: events >= 2 vary along a flank whose normals agree, where the window average of the whole
#: event is biased (+9 % in e2 on the corrugated sheet in the chamber): there the presets give
#: every pixel ``relief_paths`` continuation paths instead (``near_relief_paths`` where the near
#: relief makes those events), unless the far field's mean is tabulated and only events 1 + 2 are
#: traced; ``draft``, ``default`` and ``reference`` then share those events between the pixels of
#: matching geometry in blocks of :data:`SHARE_BLOCK_MM` or ``near_share_mm`` (``bounce_share``). Events >= 2 get the far-field control variate with
#: its mean tabulated (``far_table``, plugins/_far_field.py) wherever less than
#: :data:`NEAR_SHARE_MAX` of the 2nd event's electrons meet the relief again (``near_share``):
#: measured at 128^2, `default`, athene_flat 0.30 -> 0.27 % total in 0.57 -> 0.34 s (against the
#: sampled mean, ``far_field``), melt_chamber 2.5 -> 1.4 % in 0.14 -> 0.20 s (no variate before);
#: corrugated_chamber (43 % of them meet the facing flank) 6.1 -> 6.2 % (benchmarks/RESULTS.md, Far
#: field). With the mean tabulated the filter averages only the 2nd event's residual about it (the
#: mean keeps each pixel's position and normal), over windows of normals within
#: :data:`RESIDUAL_FILTER_ANGLE_DEG`, also on relief. ``default``'s budget is 2400 paths per window
#: (400, then 1600; 2400 since the heat shield of shield_chamber has its rims, whose thin bright
#: edge near the field raised that scene's e2 noise at 1500^2 from 2.5 to 3.3 %, above issue 26's
#: 3 %: 2.7 % now, for 6-10 % more time on the flat chamber scenes). At 1500^2, before -> now (benchmarks/RESULTS.md, Far field, "The residual filter";
#: the render's own estimate, worst detector): melt_chamber 1.37 -> 0.12 % total in 6.6-7.0 ->
#: 1.8-2.0 s; athene_flat 0.25 -> 0.13 % (e2 3.7 -> 1.8 %) and shield_chamber 0.26 -> 0.13 % (e2
#: 5.3 -> 2.6 %) for about 0.1-0.3 s more. The filter's bias on melt_chamber (128^2, against the
#: per-pixel estimator): 0.17-0.19 % of e2 RMS per pixel, at most 3.2 % of e2 at the melt tracks
#: (the whole event filtered: 0.34-0.90 %, up to 8.5 %). ``reference`` is ``default``'s estimators
#: with 4x its paths and 6x the 1st event's triangles: the most accurate preset, its bias that of
#: the averages (measured against ``unbiased``: benchmarks/RESULTS.md, Far field, "`reference` on
#: the averages"). ``unbiased`` averages nothing between pixels (128 paths per pixel of their
#: own): the ground truth that the averages' bias is measured against, and slow (at 1500^2 its
#: per-pixel noise on the chamber scenes is 4x ``default``'s in 27x the time, athene_flat).
#: ``scene`` keeps the scene file's own settings.
QUALITY_PRESETS = {
    "draft": {"spp": 1, "spp_blur": 4, "quadrature_triangles": 4, "bounce_filter": 1.0, "bounce_budget": 100,
              "bounce_min": 0.0, "relief_paths": 4, "near_relief_paths": 2, "near_share_mm": 16.0},
    "default": {"spp": 1, "spp_blur": 16, "quadrature_triangles": 4, "bounce_filter": 1.0, "bounce_budget": 2400,
                "bounce_min": 2.0, "relief_paths": 16, "near_relief_paths": 3, "near_share_mm": 16.0},
    "reference": {"spp": 1, "spp_blur": 256, "quadrature_triangles": 24, "bounce_filter": 1.0, "bounce_budget": 9600,
                  "bounce_min": 8.0, "relief_paths": 32, "near_relief_paths": 24, "near_share_mm": 12.0},
    "unbiased": {"spp": 1, "spp_blur": 256, "quadrature_triangles": 24, "bounce_filter": 0.0,
                 "bounce_budget": 128, "bounce_min": 0.0, "relief_paths": 128,
                 "near_relief_paths": 128, "near_share_mm": 0.0},
}
QUALITIES = tuple(QUALITY_PRESETS) + ("scene",)
#: The options a preset sets (:func:`quality_options`); ``scene`` restores them from the scene file.
PRESET_FIELDS = ("detector_sampling", "quadrature_triangles", "bounce_filter", "bounce_filter_angle", "bounce_share",
                 "bounce_min",
                 "bounce_samples",
                 "bounce_fraction", "far_field", "far_table", "far_roulette", "far_field_later")
#: What each preset promises: the per-pixel RMS relative error of a detector's total (events
#: counted) on its WORST scene of benchmarks/RESULTS.md (section ``presets``); ``render`` warns
#: when a render's own error estimate is above it.
QUALITY_ACCURACY = {"draft": 0.04, "default": 0.032, "reference": 0.012, "unbiased": 0.025}  # corrugated_chamber: 3.34, 2.65, 1.0, 1.96 %
#: The presets use the far field's variate (``far_table``) on scenes where less than this share of
#: the 2nd event's electrons (g_BSE-weighted) meet a surface again within the far field's near
#: distance: those directions carry the variate too, where it only adds noise. Measured shares
#: (plugins/_far_field.near_share): 0 on the flat scenes, 0.09 % on melt_chamber, 43 % on
#: corrugated_chamber; the threshold lies between them and was not tuned on a scene in between.
NEAR_SHARE_MAX = 0.1
#: The presets' filter angle on relief where the filter averages only the residual about the far
#: field's tabulated mean (``far_table``, events 1 + 2): the mean keeps each pixel's own normal.
RESIDUAL_FILTER_ANGLE_DEG = 20.0
#: The presets' block (mm) of ``bounce_share`` on relief that keeps per-pixel paths (no residual
#: filter) where the far field makes the later events (its mean tabulated: melt_chamber at events
#: 3): pixels of matching geometry in a block share their events >= 2
#: (plugins/_geometry_classes.py), their paths one point set per class (plugins/_strata.py,
#: spread_point). Bias against the per-pixel estimator, melt_chamber 256^2, events 3 (``python -m
#: benchmarks.geometry_share --bias 8,6 --scene melt_chamber --events 3 --bias-res 256``,
#: 2026-12-06 16:00, with the classes' tilt): e2 0.08-0.41 %, e3 0.00-1.64 % (one render's noise
#: 2.4-5.6 % and 8-18 %; before the tilt e2 0.35-0.44 %); in 8 mm blocks without the tilt e2
#: 0.70-0.80 %: there the far field, which the view factors do not model, varies across the block. Under a beam profile the classes also probe its footprint (1.5 sigma along +-x, +-y).
SHARE_BLOCK_MM = 4.0
#: Where the near relief makes the later events (``near_share`` >= :data:`NEAR_SHARE_MAX`, no
#: tabulated far mean: corrugated_chamber's facing flanks) the presets share them in blocks of their
#: ``near_share_mm`` with ``near_relief_paths`` paths a pixel: each pixel takes its view factor of
#: the detector times its class's ratio of events to view factors, times the tilt across the block
#: that the classes of its normal share (the beam's incidence on a flank changes across the field;
#: plugins/_geometry_classes.py), and where a sample has at most 4 paths the class's point set also
#: picks their components (plugins/_strata.py, spread_pick). corrugated_chamber at 1500^2, before
#: (8 mm blocks, no tilt, components counted per sample) -> now, interleaved in one process on the
#: shared 2-core AMD EPYC (2026-12-06; noise: the render's own estimate, worst detector; bias: the
#: classes' RMS per pixel of the total from 64 unshared renders, worst detector, which the estimate
#: cannot see; benchmarks/RESULTS.md, Far field, "A tilt across the blocks"):
#: draft 4 paths in 8 mm -> 2 in 16 mm: noise 0.58 -> 0.44 %, bias 0.22 -> 0.19 %, 1.7-2.5 -> 1.6-1.9 s;
#: default 8 -> 4 in 16 mm: 0.32 -> 0.25 %, bias 0.22 -> 0.19 %, 2.6-3.7 -> 2.0-2.6 s;
#: reference 32 in 8 mm -> 24 in 12 mm: 0.12 -> 0.11 %, bias 0.22 -> 0.14 %, 9.2-13.8 -> 7.2-7.9 s.
#: ``default`` then went 4 -> 3 paths (2 + 1 in the error estimate's halves, :func:`half_budgets`)
#: for issue 26's 1.5 s: noise 0.245 -> 0.33 % (about 0.38 % with the bias), e2 0.85 -> 1.16 %,
#: 1.86-2.26 -> 1.58-1.92 s interleaved in one process (2026-12-06 20:20, load about 1); at 128^2
#: 2.11-2.24 -> 2.52-2.81 % over 6 seeds.
#: Most continuation paths per sample a preset asks for (the loop is unrolled in the kernel).
MAX_BOUNCE_SAMPLES = 8
#: ... where the presets give relief per-pixel paths shared by geometry classes (``bounce_share``):
#: a sample's paths stratify g_BSE's directions together and a class's samples form one point set,
#: so fewer samples with more paths each do better for the same paths. corrugated_chamber, 1500^2,
#: ``reference`` (32 paths a pixel), interleaved in one process (2026-12-06): 8 x 4 samples 0.203 %
#: total (e2 0.73 %) in 11.5-11.6 s, 16 x 2 0.196 % (e2 0.69 %) in 10.9-11.5 s; ``default`` (16):
#: 8 x 2 and 16 x 1 both 0.321 % (e2 1.12 %) in 5.9 s.
RELIEF_MAX_BOUNCE_SAMPLES = 16
#: Most samples per pixel a preset takes for its continuation paths (so at most
#: MAX_BOUNCE_SPP x MAX_BOUNCE_SAMPLES = 512 paths per pixel where the window is one pixel): at 256
#: spp (athene_flat 12^2, `default`'s 1600 paths per pixel) a re-render's e2 differed from a fresh
#: one's in the last bit in 1 of 3 runs (summation order; tests/test_rerender.py), at 64 spp never.
MAX_BOUNCE_SPP = 64


def filter_window_levels(half_width_mm: float, pixel_mm: float, size_px: int | None = None) -> int | None:
    """The tile level k of the bounce filter: windows of 3 x 2^k pixels (3 x 3 tiles of 2^k)
    for a half-width of ``half_width_mm``; None where the half-width is below one pixel (no
    filtering). The one rule for the filter (plugins/_bounce_filter.py) and the presets' budget.

    ``size_px`` (the image's larger side) caps k where one tile already holds the whole image:
    larger tiles would only add padding (a 16 px scan of a 1e-6 mm field asked for tiles of 2^23
    pixels, 256 TiB of scratch)."""
    radius = half_width_mm / pixel_mm  # half-width in pixels
    if not radius >= 1.0:
        return None
    level = max(0, int(round(math.log2((2.0 * radius + 1.0) / 3.0))))
    if size_px is not None:
        level = min(level, max(0, math.ceil(math.log2(size_px))))
    return level


def quality_options(quality: str, base: EloOptions, *, pixel_mm: float, fwhm_mm: float,
                    traced_events: int, relief: bool = False, near_share: float = 0.0,
                    size_px: int | None = None) -> tuple[EloOptions, int]:
    """The options and spp of a preset for a scene.

    Parameters
    ----------
    quality : str
        A name of :data:`QUALITY_PRESETS`.
    base : EloOptions
        The options to start from (events, units, detector_samples, ... are kept).
    pixel_mm : float
        Pixel pitch along x (field / width), for the window of ``bounce_filter``.
    fwhm_mm : float
        Beam profile FWHM; > 0 takes the preset's ``spp_blur`` samples.
    traced_events : int
        Events the scene can produce (1 when nothing can scatter an electron twice).
    relief : bool
        The scene has relief that can scatter onto itself (a scattering surface that is not one
        plane): no bounce filter, ``relief_paths`` continuation paths per pixel.
    near_share : float
        The share of the 2nd event's electrons that meet a surface again near where the beam hit
        (plugins/_far_field.near_share); the far field's variate only below :data:`NEAR_SHARE_MAX`.
    size_px : int, optional
        The image's larger side in pixels (caps the filter's window, :func:`filter_window_levels`).

    Returns
    -------
    options : EloOptions
    spp : int
    """
    if quality not in QUALITY_PRESETS:
        raise EloInputError(f"quality {quality!r}; choose one of {', '.join(QUALITIES)}")
    preset = QUALITY_PRESETS[quality]
    spp = int(preset["spp_blur"] if fwhm_mm > 0 else preset["spp"])
    bounce_filter, bounce_min = float(preset["bounce_filter"]), float(preset["bounce_min"])
    far_table = traced_events > 1 and near_share < NEAR_SHARE_MAX
    # on relief the filter averages only the residual about the tabulated mean, which keeps each
    # pixel's normal, so windows may span the relief's normals (plugins/integrator_elo.py)
    residual = relief and bounce_filter > 0 and far_table and traced_events == 2
    angle = RESIDUAL_FILTER_ANGLE_DEG if residual else FILTER_ANGLE_DEG
    share = 0.0
    if relief and bounce_filter > 0 and not residual:
        # the window average of the whole later events is biased on relief: per-pixel paths,
        # shared by the pixels of matching geometry (and beam footprint) in a block
        # where the near relief makes the later events (no tabulated far mean), the view factors
        # carry them across larger blocks, whose larger classes need fewer paths a pixel
        share = SHARE_BLOCK_MM if far_table else float(preset["near_share_mm"])
        bounce_filter, bounce_min = 0.0, 0.0
        per_pixel = float(preset["relief_paths" if far_table else "near_relief_paths"])
    else:
        level = filter_window_levels(bounce_filter, pixel_mm, size_px)
        window = 1 if level is None else 3 << level  # the filter's window, in pixels along x and y
        per_pixel = preset["bounce_budget"] / window**2  # continuation paths per pixel
    per_sample_max = RELIEF_MAX_BOUNCE_SAMPLES if share else MAX_BOUNCE_SAMPLES
    # at most MAX_BOUNCE_SPP samples per pixel for the continuation paths (where the window is one
    # pixel, 1600 paths would take 256 spp, whose re-renders differed in the last bit of e2)
    per_pixel = min(per_pixel, max(spp, MAX_BOUNCE_SPP) * per_sample_max)
    if traced_events > 1 and per_pixel > spp * per_sample_max:
        # a power of two: a pixel's samples then never straddle two of Dr.Jit's thread blocks,
        # whose atomic adds into one pixel would come in varying order (last-bit differences)
        spp = 1 << math.ceil(math.log2(per_pixel / per_sample_max))
    per_sample = per_pixel / spp
    bounce_samples = max(1, math.ceil(per_sample))
    if spp > 1:
        # every sample traces (bounce_fraction 1, up to 1/k more paths than the budget): the block
        # pattern of bounce_fraction < 1 is one random shift per render, common to all pixels,
        # which the error estimate's two halves see only as a whole (its estimate then scattered
        # 0.76-1.6x in variance on athene_flat, against 0.9-1.0x with every sample tracing)
        per_sample = float(bounce_samples)
    options = base.replace(detector_sampling="quadrature", quadrature_triangles=preset["quadrature_triangles"],
                           bounce_filter=bounce_filter, bounce_filter_angle=angle, bounce_share=share,
                           bounce_min=bounce_min,
                           bounce_samples=bounce_samples,
                           bounce_fraction=min(1.0, per_sample / bounce_samples), far_field=0,
                           far_table=far_table, far_roulette=1.0, far_field_later=False)
    return options, spp


def half_budgets(options: EloOptions) -> tuple[EloOptions, EloOptions]:
    """The options of the two independent halves of a render at 1 spp (the error estimate,
    :mod:`elo_mitsuba.error_estimate`): each half about half the continuation paths per sample
    (``bounce_fraction`` x ``bounce_samples``) and half the top-up (``bounce_min``); the 1st event
    is unchanged (with the quadrature and a single-ray beam it is deterministic), so the halves
    together have the budget of the whole. Where the pixels of a class share their paths
    (``bounce_share``) each sample traces whole paths in both halves, ceil(k/2) and floor(k/2) of
    its k: a fraction of them would skip blocks of lanes and break the class's point set
    (corrugated_chamber 1500^2, 3 paths a pixel as 1.5 in 3 of 4 blocks per half: noise 0.52 %;
    as 2 + 1: 0.33 %). Unequal halves are weighed by their paths (:func:`paths_per_sample`)."""
    k_all, fraction = options.bounce_samples, options.bounce_fraction
    if options.bounce_share > 0 and fraction == 1.0 and k_all >= 2:
        return tuple(options.replace(bounce_samples=k, bounce_min=options.bounce_min / 2.0)
                     for k in ((k_all + 1) // 2, k_all // 2))
    per_sample = fraction * k_all / 2.0
    k = max(1, math.ceil(per_sample))
    half = options.replace(bounce_samples=k, bounce_fraction=per_sample / k, bounce_min=options.bounce_min / 2.0)
    return half, half


def paths_per_sample(options: EloOptions) -> float:
    """Continuation paths a sample traces, expected (``bounce_fraction`` x ``bounce_samples``)."""
    return options.bounce_fraction * options.bounce_samples
