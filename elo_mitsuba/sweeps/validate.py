"""Every point of a sweep checked against the scene before the store is created, without rendering.

A spec's values are checked when it is parsed (:mod:`.spec`: types, ranges, finiteness); what only
the scene can tell is checked here, for every value in any position, not only the first point's:

* each distinct combination of load-time parameters (``dh``, ``layout``, ``material``, ``fwhm``,
  ...) is loaded once (a load costs ~0.1 s and compiles nothing); beyond
  :data:`MAX_LOAD_PROBES` combinations, each value of each swept axis is loaded once, with the
  first point's other values (the first :data:`MAX_VALUE_PROBES` of an axis);
* each distinct combination of detector moves is applied to the first point's scene
  (``set_detector``, ~25 ms, the same code a worker runs); beyond :data:`MAX_MOVE_PROBES`, each
  value of each moving axis once;
* the integrator options (``[integrator]``) on that scene, with the combination rules of the
  render command (:func:`~elo_mitsuba.options.check_combination`);
* the test surface: its flat reference scene loads, is flat, and the object scene has the relief
  the surface names (a flat plate with the corrugated sheet's true gradient is refused).

What is still checked only while rendering: a combination of a load-time value and a detector move
that is valid apart (e.g. a low ``dh`` with a large ``detectors.radius``); such a point is stored
as failed with its one-line error, and the others go on.
"""

from __future__ import annotations

import itertools
import json
import math

from ..errors import EloInputError
from .spec import ALL_DETECTORS, SURFACE_OBJECTS, SweepSpec, check_against_scene, check_parameters

#: Most distinct load-time combinations loaded one by one (each ~0.1 s).
MAX_LOAD_PROBES = 32
#: Most distinct detector-move combinations applied one by one (each ~25 ms).
MAX_MOVE_PROBES = 128
#: Beyond the combinations: the first this many values of each axis (a list of thousands of
#: values is checked in part; the rest fail, if at all, as stored failed points).
MAX_VALUE_PROBES = 256


def _values_text(spec: SweepSpec, picks: dict) -> str:
    """``dh = -50, right.radius = 20`` for the axis indices ``picks`` ({axis number: index}): the
    keys as the spec writes them (the line to fix), not the store's names (:func:`.spec.dimension_name`,
    whose own checks are :func:`.spec.load_spec`'s)."""
    parts = []
    for a, i in sorted(picks.items()):
        for m in spec.axes[a].members:
            v = m.values[i]
            parts.append(f"{m.key} = {list(v) if isinstance(v, tuple) else v!r}")
    return ", ".join(parts)


def _probes(spec: SweepSpec, axes: list[int], limit: int):
    """Axis-index picks to try: every combination over ``axes`` when there are at most ``limit``,
    else each index of each axis alone (the others at the first point's)."""
    sizes = [len(spec.axes[a]) for a in axes]
    if math.prod(sizes) <= limit:
        for combo in itertools.product(*(range(n) for n in sizes)):
            yield dict(zip(axes, combo))
    else:
        for a, n in zip(axes, sizes):
            for i in range(min(n, MAX_VALUE_PROBES)):
                yield {a: i}


def _point(spec: SweepSpec, picks: dict):
    """The load, render and move settings of the point with ``picks`` (others at index 0)."""
    idx = [0] * len(spec.axes)
    for a, i in picks.items():
        idx[a] = i
    flat = 0
    for n, i in zip(spec.shape, idx):
        flat = flat * n + i
    return spec.point(flat)


def check_first_point(spec: SweepSpec):
    """The first point's scene, loaded (no moves applied), with the names, integrator options and
    test surface of ``spec`` checked against it; the cheap part, before the cost estimate."""
    from ..render import load_scene

    first = spec.point(0)
    try:
        check_parameters(spec)
        probe = load_scene(spec.scene, **first.load)
    except EloInputError as exc:
        raise EloInputError(f"{spec.source}: {exc}") from None
    check_against_scene(spec, probe)
    _check_integrator(spec, probe)
    if spec.surface is not None:
        _check_surface(spec, probe, first)
    return probe


def check_points(spec: SweepSpec) -> None:
    """Check every point's load-time values and detector moves against the scene (see the module
    docstring). Raises EloInputError naming the spec, the offending value(s) and what is wrong."""
    from ..render import load_scene
    from .worker import LoadedScene

    src = spec.source
    first = spec.point(0)

    # load-time values, in every position
    load_axes = [a for a, ax in enumerate(spec.axes) if any(m.target == "scene" for m in ax.members)]
    seen = {first.load_key}
    for picks in _probes(spec, load_axes, MAX_LOAD_PROBES):
        point = _point(spec, picks)
        if point.load_key in seen:
            continue
        seen.add(point.load_key)
        try:
            load_scene(spec.scene, **point.load)
        except EloInputError as exc:
            raise EloInputError(f"{src}: {_values_text(spec, picks)}: {exc}") from None

    # detector moves, in every position, on the first point's scene
    move_axes = [a for a, ax in enumerate(spec.axes) if any(m.target == "detector" for m in ax.members)]
    if move_axes:
        loaded = LoadedScene(spec.scene, first.load, spec.integrator)
        done = set()
        for picks in _probes(spec, move_axes, MAX_MOVE_PROBES):
            point = _point(spec, picks)
            key = json.dumps(point.moves, sort_keys=True, default=str)
            if key in done:
                continue
            done.add(key)
            try:
                loaded.prepare(point.moves)
            except EloInputError as exc:
                raise EloInputError(f"{src}: {_values_text(spec, picks)}: {exc}") from None


def _check_integrator(spec: SweepSpec, probe) -> None:
    """``[integrator]`` on the scene, and the combinations the render command refuses."""
    src = spec.source
    if spec.integrator:
        try:
            probe.configure(**spec.integrator)
        except EloInputError as exc:
            raise EloInputError(f"{src}: [integrator]: {exc}") from None
    qualities = {spec.quality} | {v for a in spec.axes for m in a.members if m.key == "quality" for v in m.values}
    events = [spec.events] + [v for a in spec.axes for m in a.members if m.key == "events" for v in m.values]
    from ..options import QUALITY_PRESETS, check_combination, check_scene_options  # the rules of every entry point

    try:
        check_combination(spec.integrator, base=probe.options, qualities=sorted(qualities), events=max(events),
                          bounce_possible=bool(probe.integrator.bounce_possible), prefix="integrator.")
        check_scene_options(probe.integrator.scene_options, sorted(qualities), where=str(probe.path))
        if qualities & set(QUALITY_PRESETS):  # the presets' quadrature takes discs, rectangles and meshes only
            from ..plugins._detectors import quadrature_geometry

            quadrature_geometry(probe.integrator.detectors, 4)
    except EloInputError as exc:
        raise EloInputError(f"{src}: {exc}") from None


def _check_surface(spec: SweepSpec, probe, first) -> None:
    """The flat reference loads, is flat, knows the moved detectors; the object scene has the
    relief the surface names."""
    from ..render import load_scene
    from ..scene_files import declared_parameters, resolve_scene_path

    src, surface = spec.source, spec.surface
    relief = list(getattr(probe.integrator, "relief", []) or [])
    obj = surface.get("object")
    if obj is not None:
        others = [o for o in SURFACE_OBJECTS if o != obj]
        if not relief or (obj not in relief and any(o in relief for o in others)):
            raise EloInputError(
                f"{src}: surface.object = {obj!r} contradicts the scene {probe.path.name}: it has "
                f"{'no relief under the beam (a flat surface)' if not relief else 'the relief ' + ', '.join(relief)}; "
                f"the gradient metrics would compare its images with another surface's gradient")
    try:
        path = resolve_scene_path(surface["flat"])
        declared = declared_parameters(path, {k: str(v) for k, v in first.load.items()})
        flat = load_scene(path, **{k: v for k, v in first.load.items() if k in declared})
    except EloInputError as exc:
        raise EloInputError(f"{src}: surface.flat = {surface['flat']!r}: {exc}") from None
    if getattr(flat.integrator, "relief", None):
        raise EloInputError(f"{src}: surface.flat = {surface['flat']!r} is not flat (relief "
                            f"{', '.join(flat.integrator.relief)}); the STSA correction needs a flat plate")
    moved = {m.detector for a in spec.axes for m in a.members if m.target == "detector"} - {ALL_DETECTORS}
    missing = sorted(moved - set(flat.detector_names))
    if missing:
        raise EloInputError(f"{src}: surface.flat = {surface['flat']!r} has no detector {missing[0]!r} "
                            f"(its detectors: {', '.join(flat.detector_names)}); the sweep moves it")
