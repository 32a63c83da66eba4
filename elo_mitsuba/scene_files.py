"""Scene files: the shipped scenes, their parameters, Mitsuba's loader errors, the scene writer.

Scenes are Mitsuba XML files (``scenes_xml/``, installed as ``elo_mitsuba.scenes``) whose
``<default name=... value=...>`` parameters the user sets with ``-D name=value`` (CLI) or keyword
arguments (:func:`elo_mitsuba.load_scene`). This module finds a scene by name or path, lists the
parameters a file (and the files it includes) declares, translates Mitsuba's multi-line loader
errors into one line, and writes new scenes around a user's mesh.
"""

from __future__ import annotations

import math
import os
import re
import xml.etree.ElementTree as ET
from importlib import resources
from pathlib import Path
from typing import Mapping

from .constants import DEFAULT_MATERIAL, TABLE1_LAYOUTS
from .schema import MAX_LENGTH_MM
from .errors import EloInputError
from .files import atomic_write, check_output
from .mesh import check_ply_indices, ply_header, write_mesh


def scenes_dir() -> Path:
    """The shipped scenes (scenes_xml/, installed as the package ``elo_mitsuba.scenes``)."""
    return Path(str(resources.files("elo_mitsuba.scenes")))


def shipped_scenes() -> dict[str, Path]:
    """Names and paths of the scenes shipped in ``scenes_xml/`` (``elo_mitsuba.scenes``)."""
    return {p.stem: p for p in sorted(scenes_dir().glob("*.xml"))}


def resolve_scene_path(scene: str | Path) -> Path:
    """A path to an XML file, or the name of a shipped scene (``flat_plate``, ``athene_flat``, ...)."""
    if not isinstance(scene, (str, os.PathLike)):
        raise EloInputError(f"scene {scene!r} ({type(scene).__name__}): give an XML path or a shipped scene name "
                            f"({', '.join(shipped_scenes())})")
    if not str(scene).strip():  # Path("") is the working folder
        raise EloInputError(f"scene {str(scene)!r} is empty; give an XML path or a shipped scene name "
                            f"({', '.join(shipped_scenes())})")
    path = Path(scene)
    if path.is_file():
        return path
    shipped = shipped_scenes()
    if str(scene) in shipped:
        return shipped[str(scene)]
    if path.is_dir():
        raise EloInputError(f"scene {str(scene)!r} is a folder; give an XML file in it or a shipped scene name")
    if path.suffix.lower() == ".xml" or path.parent != Path("."):
        raise EloInputError(f"scene file {str(scene)!r} does not exist")
    names = ", ".join(shipped) or "(none installed)"
    raise EloInputError(f"scene {str(scene)!r} is neither an XML file nor a shipped scene ({names})")


#: Largest float32: Mitsuba reads every number of a scene as float32, so 1e40 becomes inf.
_FLOAT32_MAX = 3.4028234663852886e38
#: The numeric attributes of Mitsuba's XML elements, by tag: a literal there must be a finite
#: number (Mitsuba takes "nan" and "inf" and fails far from them, and reads an empty float as 0).
_NUMBER_ATTRIBUTES = {
    "float": ("value",), "point": ("value", "x", "y", "z"), "vector": ("value", "x", "y", "z"),
    "rgb": ("value",), "translate": ("value", "x", "y", "z"), "scale": ("value", "x", "y", "z"),
    "rotate": ("value", "x", "y", "z", "angle"), "lookat": ("origin", "target", "up"), "matrix": ("value",),
}


def not_finite(value) -> bool:
    """True for a value that reads as a number but is not finite (``inf``, ``-inf``, ``nan``), also in
    Mitsuba's float32 (beyond 3.4e38: -D dh=1e40 made the detectors' geometry inf).

    >>> not_finite("nan"), not_finite("1e40"), not_finite("272"), not_finite("Ti-6Al-4V")
    (True, True, False, False)
    """
    try:
        return not abs(float(str(value))) <= _FLOAT32_MAX
    except ValueError:
        return False  # text (a material's name, a file): not a number at all


def _check_numbers(path: Path, node) -> None:
    """A literal number of a scene element that Mitsuba would take and fail far from, or read as 0:
    refused in one line naming the element (values with a ``$parameter`` are checked as parameters)."""
    for attribute in _NUMBER_ATTRIBUTES.get(node.tag, ()):
        raw = node.get(attribute)
        if raw is None or "$" in raw:
            continue
        name = f" name={node.get('name')!r}" if node.get("name") else ""
        element = f"<{node.tag}{name} {attribute}={raw!r}>"
        parts = [p for p in re.split(r"[\s,]+", raw.strip()) if p]
        if not parts:
            raise EloInputError(f"{path}: {element} is empty (Mitsuba would read it as 0); give it a number")
        bad = [p for p in parts if not_finite(p)]
        if bad:
            what = "beyond float32 (Mitsuba's numbers reach 3.4e38)" if math.isfinite(float(bad[0])) else \
                "not a finite number"
            raise EloInputError(f"{path}: {element} holds {bad[0]!r}, {what}; Mitsuba would take it and fail far "
                                "from it")


def declared_parameters(path: Path, values: Mapping[str, str] | None = None) -> dict[str, str]:
    """The ``<default name=... value=...>`` parameters of a scene file and the files it includes.

    ``values`` (the user's -D settings) decide which file an ``<include filename="...$name...">``
    pulls in, as Mitsuba's loader does.
    """
    values = dict(values or {})
    declared: dict[str, str] = {}
    _collect_defaults(Path(path), values, declared, depth=0)
    return declared


def _collect_defaults(path: Path, values: dict, declared: dict, depth: int, chain: tuple = ()) -> None:
    chain = (*chain, path.resolve())
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise EloInputError(f"{path}: malformed XML ({exc})") from None
    except OSError as exc:
        raise EloInputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if root.tag != "scene":
        raise EloInputError(f"{path}: root element is <{root.tag}>, expected <scene>")
    own: dict[str, str] = {}  # this file's defaults: Mitsuba takes the first of two and ignores the other silently
    for node in root.iter():
        if node.tag == "default" and node.get("name"):
            name = node.get("name")
            if name in own:
                raise EloInputError(f"{path}: <default name={name!r}> is declared twice (value {own[name]!r}, then "
                                    f"{node.get('value')!r}); Mitsuba would use the first and ignore the second: "
                                    "keep one")
            own[name] = node.get("value")
            if not (node.get("value") or "").strip() and node.get("name") not in values:
                raise EloInputError(f"{path}: <default name={node.get('name')!r}> has no value (Mitsuba would read "
                                    f"it as 0); give it one, or pass -D {node.get('name')}=...")
            if not_finite(node.get("value")) and node.get("name") not in values:
                raise EloInputError(f"{path}: <default name={node.get('name')!r}> is {node.get('value')!r}, not a finite "
                                    f"number: the scene's parameters are lengths (mm), angles and counts; give it "
                                    f"one, or pass -D {node.get('name')}=...")
            declared.setdefault(node.get("name"), node.get("value"))
        elif node.tag == "include" and node.get("filename") and depth < 8:
            pattern = node.get("filename")
            known = {**declared, **values}
            name = re.sub(r"\$(\w+)", lambda m: str(known.get(m.group(1), m.group(0))), pattern)
            inc = (path.parent / name)
            if inc.is_file() and inc.resolve() in chain:
                raise EloInputError(f"{path}: includes {name!r}, which includes it again "
                                    f"({' -> '.join(p.name for p in (*chain, inc.resolve()))}): an include cycle")
            if inc.is_file():
                _collect_defaults(inc, values, declared, depth + 1, chain)
            else:
                _refuse_value_without_file(path, pattern, values)
                if "$" not in name:  # Mitsuba would fail on it; say why before "not declared" errors
                    where = ("" if Path(name).is_absolute() else
                             f" (an include is relative to the scene's folder {path.parent})")
                    hint = (f"a copied scene needs its {Path(name).parts[0]}/ folder too, or write a self-contained "
                            "copy: elo-mitsuba new-scene NAME.xml --from SCENE"
                            if len(Path(name).parts) > 1 and not Path(name).is_absolute() else "check its name")
                    raise EloInputError(f"{path}: included file {name!r} not found{where}; {hint}")
        elif node.tag == "shape" and node.get("type") == "ply" and depth < 8:
            _check_ply(path, node, {**declared, **values})
        elif node.tag == "sampler":
            _check_sample_count(path, node, {**declared, **values})
        elif node.tag in _NUMBER_ATTRIBUTES:
            _check_numbers(path, node)


def _check_ply(path: Path, node, known: Mapping) -> None:
    """A ``<shape type="ply">`` whose file is missing, not a PLY, or one whose indices Mitsuba would
    corrupt (:func:`~elo_mitsuba.mesh.check_ply_indices`): say which file, in one line (Mitsuba's own
    message on binary garbage is a UTF-8 decode error; on the indices it says nothing)."""
    for child in node:
        if child.tag == "string" and child.get("name") == "filename" and child.get("value"):
            name = re.sub(r"\$(\w+)", lambda m: str(known.get(m.group(1), m.group(0))), child.get("value"))
            if "$" in name:
                return
            mesh = path.parent / name
            if not mesh.is_file():
                raise EloInputError(f"{path}: mesh file {name!r} not found (relative to {path.parent})")
            try:
                check_ply_indices(mesh)
                counts = ply_header(mesh)
            except EloInputError as e:
                raise EloInputError(f"{path}: {e}") from None
            if not counts["vertices"] or not counts["faces"]:  # Mitsuba's loader fails on it with a JIT error
                raise EloInputError(f"{path}: mesh file {name!r} has {counts['vertices']} vertices and "
                                    f"{counts['faces']} triangles; a surface needs triangles")


def _check_sample_count(path: Path, node, known: Mapping) -> None:
    """A sampler's ``sample_count`` below 1 is refused before Mitsuba loads it: its ``multijitter``
    divides by the count while loading (SIGFPE, no message) and ``independent`` renders nothing."""
    for child in node:
        if child.tag == "integer" and child.get("name") == "sample_count":
            text = re.sub(r"\$(\w+)", lambda m: str(known.get(m.group(1), m.group(0))), child.get("value", ""))
            try:
                count = int(text)
            except ValueError:
                return  # not a number: Mitsuba's own message names it
            if count < 1:
                where = f" (-D spp={count})" if "$" in child.get("value", "") else ""
                raise EloInputError(f"{path}: the sampler's sample_count is {count}{where}: the samples per pixel "
                                    "must be >= 1")


def _refuse_value_without_file(path: Path, pattern: str, values: Mapping) -> None:
    """A user's value that selects an included file (``layouts/$layout.xml``) which does not
    exist: name the parameter and the values that do."""
    params = re.findall(r"\$(\w+)", pattern)
    given = [p for p in params if p in values]
    if len(params) != 1 or not given:
        return
    glob = re.sub(r"\$\w+", "*", pattern)
    stem_prefix, suffix = Path(glob).name.split("*", 1)
    allowed = sorted(f.name[len(stem_prefix):len(f.name) - len(suffix)]
                     for f in (path.parent / Path(glob).parent).glob(Path(glob).name))
    if allowed:
        raise EloInputError(f"{path}: parameter {given[0]}={values[given[0]]!r} is not available; allowed: "
                            f"{', '.join(allowed)}")


def layout_name(layout: str | int) -> str:
    """The Table 1 name of a detector layout given as ``"zeta50"``, ``"50"``, ``50`` or
    ``"zeta50deg"``: ``"zeta50"`` (the name a scene's ``layout`` parameter takes).

    >>> layout_name(50), layout_name("ZETA75deg")
    ('zeta50', 'zeta75')
    """
    key = str(layout).lower().removeprefix("zeta").removesuffix("deg").strip()
    try:
        zeta = int(float(key))
    except ValueError:
        zeta = None
    if zeta not in TABLE1_LAYOUTS:
        allowed = ", ".join(f"zeta{z}" for z in TABLE1_LAYOUTS)
        raise EloInputError(f"unknown detector layout {layout!r}; Table 1 layouts are {allowed}")
    return f"zeta{zeta}"


def layout_parameters(layout: str | int) -> dict[str, float]:
    """-D parameters of a Table 1 detector layout: ``"zeta50"``, ``"50"`` or ``50``."""
    dh, dw = TABLE1_LAYOUTS[int(layout_name(layout).removeprefix("zeta"))]
    return {"dh": dh, "dw": dw}


def scene_values(detector_layout: str | int | None, params: Mapping, *, names: Mapping[str, str] | None = None) -> dict:
    """The scene parameters of a Table 1 ``detector_layout`` (sets dh and dw) and ``params``;
    a parameter given both ways is refused, as is ``layout`` (whose file sets only the dh and dw
    that the layout replaces): one of them would be silently ignored. So is a ``layout``
    parameter in ``params`` together with ``dh`` or ``dw``: the layout's file sets them, and the
    header would name a layout whose geometry the render does not have. ``names`` maps a
    parameter to how the message names it (the CLI's ``--layout``, ``-D dh``, a spec's
    ``fixed.layout``).

    >>> scene_values(None, {"layout": "zeta50", "dh": 100})
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: layout=zeta50 sets dh and dw; dh=100 contradicts it: give the layout or dh/dw, not both
    """
    names = dict(names or {})
    if detector_layout is None:
        clash = [k for k in ("dh", "dw") if k in params and "layout" in params]
        if clash:
            k = clash[0]
            raise EloInputError(f"{names.get('layout', 'layout')}={params['layout']} sets dh and dw; "
                                f"{names.get(k, k)}={params[k]} contradicts it: give the layout or dh/dw, not both")
        return dict(params)
    values = layout_parameters(detector_layout)
    clash = [k for k in params if k in values or k == "layout"]
    if clash:
        k = clash[0]
        raise EloInputError(
            f"{names.get('detector_layout', 'detector_layout')} {detector_layout} sets dh and dw; "
            f"{names.get(k, k)}={params[k]} contradicts it: give the layout or dh/dw, not both")
    return {**values, **params}


def check_detector_placement(name: str, center, normal, radius: float, where: str = "") -> None:
    """The rule every detector obeys, wherever it comes from (a scene, a moved detector, a
    calibration): its disc lies wholly above the build plane z = 0 (its lowest rim point is
    r sin(tilt) below its centre) and its front face sees the origin. Raises
    :class:`EloInputError` naming the detector (prefixed by ``where``)."""
    import math

    import numpy as np

    at = f"{where}: " if where else ""
    c = np.asarray(center, dtype=float).reshape(3)
    n = np.asarray(normal, dtype=float).reshape(3)
    n = n / np.linalg.norm(n)
    if c[2] <= 0:
        raise EloInputError(f"{at}detector {name!r} has its centre at z={c[2]:g} mm, at or below the build plane "
                            "z=0; detectors must be above the plate")
    if not np.abs(c).max() <= MAX_LENGTH_MM:  # a header could not hold it, nor a reader use it (-D dh=1e12)
        raise EloInputError(f"{at}detector {name!r} has its centre at ({', '.join(f'{v:.4g}' for v in c)}) mm; "
                            f"each coordinate must be within {MAX_LENGTH_MM:g} mm of the origin (the longest length "
                            "a header holds): lower dh or dw")
    low = c[2] - float(radius) * math.sqrt(max(0.0, 1.0 - float(n[2]) ** 2))
    if low <= 0:
        raise EloInputError(f"{at}detector {name!r} (centre z={c[2]:g} mm, radius {float(radius):g} mm) reaches down "
                            f"to z={low:.3g} mm, through the build plane z=0; raise it (dh) or move it inwards (dw)")
    if np.dot(n, -c) <= 0:
        raise EloInputError(f"{at}detector {name!r} faces away from the scan field (normal "
                            f"{np.round(n, 3).tolist()}); its front face must see the origin")


def check_detectors_apart(geometry: Mapping[str, Mapping], where: str = "") -> None:
    """Refuse two detector discs that share points (``geometry``: name -> ``center``, ``normal``,
    ``radius``): two plates cannot fill the same space, and both would count the electrons
    arriving there. Discs that touch along a line of zero length, or lie one behind another, pass.

    >>> disc = {"center": (127, 0, 272), "normal": (-127, 0, -272), "radius": 25}
    >>> check_detectors_apart({"right": disc, "back": {**disc, "center": (0, 127, 272)}})
    >>> check_detectors_apart({"right": disc, "back": {**disc, "center": (127, 10, 272)}})
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: detectors 'right' and 'back' intersect (centres 10 mm apart, radii 25 and 25 mm): two plates cannot occupy the same space; move one
    """
    import numpy as np

    at = f"{where}: " if where else ""
    names = list(geometry)
    discs = []
    for name in names:
        g = geometry[name]
        n = np.asarray(g["normal"], dtype=float).reshape(3)
        discs.append((np.asarray(g["center"], dtype=float).reshape(3), n / np.linalg.norm(n), float(g["radius"])))
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            (c1, n1, r1), (c2, n2, r2) = discs[i], discs[j]
            if _discs_intersect(c1, n1, r1, c2, n2, r2):
                raise EloInputError(
                    f"{at}detectors {names[i]!r} and {names[j]!r} intersect (centres {np.linalg.norm(c2 - c1):.3g} mm "
                    f"apart, radii {r1:g} and {r2:g} mm): two plates cannot occupy the same space; move one")


def _discs_intersect(c1, n1, r1, c2, n2, r2) -> bool:
    """Whether two discs (centre, unit normal, radius) share a segment of positive length or, in
    one plane, an area: their chords on the line where their planes meet overlap."""
    import numpy as np

    scale = max(r1, r2)
    u = np.cross(n1, n2)
    if np.linalg.norm(u) < 1e-9:  # parallel planes: only coplanar discs can meet
        return abs(np.dot(n1, c2 - c1)) < 1e-6 * scale and np.linalg.norm(c2 - c1) < r1 + r2
    u = u / np.linalg.norm(u)
    d1, d2, k = np.dot(n1, c1), np.dot(n2, c2), np.dot(n1, n2)
    p0 = ((d1 - d2 * k) * n1 + (d2 - d1 * k) * n2) / (1.0 - k * k)  # a point on both planes
    chords = []
    for c, r in ((c1, r1), (c2, r2)):
        t = np.dot(c - p0, u)
        half_squared = r * r - np.sum((p0 + t * u - c) ** 2)
        if half_squared <= 0:
            return False
        h = np.sqrt(half_squared)
        chords.append((t - h, t + h))
    return min(chords[0][1], chords[1][1]) - max(chords[0][0], chords[1][0]) > 1e-9 * scale


def detector_up(center, normal) -> list[float]:
    """The ``up`` vector of the look-at that orients a detector disc about its normal: the azimuthal
    direction z x centre, as parts/detectors.xml orients the four detectors (lookat up = +y for the
    right one, then turned about z). A disc is symmetric, but its samples are drawn in its own
    frame: a detector moved to where the scene placed it renders as the scene does only in the
    same frame. On the z-axis, or where that direction is (nearly) the normal, +y, else +x.

    >>> detector_up((127, 0, 272), (-127, 0, -272))
    [0.0, 1.0, 0.0]
    >>> detector_up((0, 127, 272), (0, -127, -272))
    [-1.0, 0.0, 0.0]
    """
    import numpy as np

    c = np.asarray(center, dtype=float).reshape(3)
    c = c / max(float(np.abs(c).max()), 1e-300)  # a direction: scaled so that no norm overflows
    n = np.asarray(normal, dtype=float).reshape(3)
    n = n / np.abs(n).max()
    n = n / np.linalg.norm(n)
    for up in (np.array([-c[1], c[0], 0.0]), np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])):
        length = np.linalg.norm(up)
        if length > 1e-9 and abs(np.dot(up / length, n)) < 0.999:
            return (up / length + 0.0).tolist()
    raise AssertionError("no up vector: +x and +y cannot both lie along one normal")


def explain_mitsuba_error(exc: Exception, path: Path, values: Mapping[str, str] | None = None) -> str:
    """One line from Mitsuba's multi-line loader error: where, and the innermost message.

    ``values`` (the user's -D settings): a value Mitsuba could not parse is named by its parameter.
    """
    text = str(exc)
    m = re.search(r'could not parse (\w[\w ]*?) value "([^"]*)"', text)
    if m:
        names = [k for k, v in (values or {}).items() if str(v) == m.group(2)]
        if names:
            return (f"{path}: parameter {names[0]}={m.group(2)!r} is not a valid {m.group(1)} value "
                    f"(-D {names[0]}=...)")
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    where = ""
    m = re.search(r"\(line (\d+), col (\d+)\)", text)
    if m:
        where = f" line {m.group(1)}"
    # Mitsuba names the file of every include it was in; the innermost is where the cause is
    places = list(re.finditer(r"(?:While loading|Error while loading|At) (\S.*?) \(line (\d+), col \d+\): ", text))
    if places:
        inner, line = places[-1].group(1), places[-1].group(2)
        same = inner == "string" or Path(inner).resolve() == Path(path).resolve()
        where = f" line {line}" if same else f": in {inner} line {line}"
    # innermost Python error ("EloInputError: ...") if a plugin of ours refused a value
    for ln in reversed(lines):
        mm = re.match(r"^(?:\w+\.)*(\w*Error): (.*)$", ln)
        if mm and mm.group(2):
            return f"{path}{where}: {mm.group(2)}"
    if len(places) > 1:
        return f"{path}{where}: {text[places[-1].end():].strip().splitlines()[0]}"
    first = lines[0] if lines else type(exc).__name__
    if first.endswith(":") and len(lines) > 1:  # e.g. "unreferenced property ...:" + "- name" lines
        first = first + " " + " ".join(ln.lstrip("- ") for ln in lines[1:4])
    first = re.sub(r"^\[[\w.]+:\d+\]\s*", "", first)
    first = re.sub(r"^(At|While loading|Error while loading) .*?\(line \d+, col \d+\): ", "", first)
    first = re.sub(r"^(At|While loading) .*?: ", "", first)
    if "unused parameters" in text.lower():
        unused = ", ".join(re.findall(r"\$(\w+)=", text))
        return f"{path}: parameter(s) {unused} not used by this scene"
    return f"{path}{where}: {first}"


def portable_scene_text(source: Path) -> str:
    """The text of scene ``source`` with every relative file reference (``<include filename>``,
    ``<string name="filename">``) made absolute against its folder, so that a copy anywhere
    loads the same files; ``$parameters`` in the references are kept (``layouts/$layout.xml``)."""
    from xml.sax.saxutils import escape

    source = Path(source)

    def absolute(m):
        ref = m.group(2)
        if Path(ref).is_absolute():
            return m.group(0)
        return f'{m.group(1)}{escape((source.parent.resolve() / ref).as_posix(), {chr(34): "&quot;"})}"'

    text = source.read_text()
    text = re.sub(r'(<include\s+filename=")([^"]+)"', absolute, text)
    return re.sub(r'(<string\s+name="filename"\s+value=")([^"]+)"', absolute, text)


def write_scene_copy(scene_path, source="athene_flat", *, overwrite: bool = False) -> Path:
    """Write a copy of a shipped scene (or any scene file) that works from any folder: its
    includes and meshes referenced by absolute path (:func:`portable_scene_text`), the
    parameters and everything else unchanged, to edit as one's own."""
    src = resolve_scene_path(source)
    scene_path = check_output(scene_path, (".xml",), overwrite=overwrite, what="scene", inputs=[src])
    declared_parameters(src)  # a malformed or incomplete source would be copied broken
    text = portable_scene_text(src)
    header = (f"<!-- Written by 'elo-mitsuba new-scene' from {src.name}: includes and meshes by absolute path, so "
              "this file works from any folder. -->\n")
    return atomic_write(scene_path, lambda tmp: tmp.write_text(header + text))


def write_scene(scene_path, mesh_path, *, material: str | None = None, chamber: bool = False,
                face_normals: bool = True, field_mm: float | None = None, overwrite: bool = False) -> Path:
    """Write a Mitsuba scene that renders ``mesh_path`` like ``scenes_xml/melt_plate.xml``.

    The scene is the shipped melt-plate scene with its mesh replaced: same parameters (layout,
    dh, dw, wd, field, res, spp, events, fwhm, projection, material), the four detectors and the
    layouts included from the installed ``scenes_xml`` by absolute path. The mesh is referenced
    relative to the scene file when possible. ``material`` (default Ti-6Al-4V) becomes the
    default of the ``material`` parameter; it is validated here. ``chamber``: the object inside
    the ATHENE-like chamber instead (``scenes_xml/melt_chamber.xml``, events default 2).
    ``face_normals`` false: the renderer interpolates the mesh's vertex normals (a surface that
    knows its own normals, :func:`~elo_mitsuba.mesh.heightmap_to_mesh`) instead of using each
    triangle's. ``field_mm``: the default of the ``field`` parameter (the scan field, mm), e.g. the
    extent of the mesh (``elo-mitsuba mesh --scene`` writes the field its height map covers); default
    the template's 80 mm, which a smaller mesh would not fill (the beam would miss it).
    """
    from xml.sax.saxutils import escape

    from .physics.materials import get_material
    from .schema import LENGTH_RANGE, is_length

    material = DEFAULT_MATERIAL if material is None else material
    get_material(material)  # raises EloInputError for an unknown material
    if field_mm is not None and not is_length(field_mm):
        raise EloInputError(f"field_mm={field_mm!r}; the scan field must be a length of {LENGTH_RANGE}")
    scene_path = check_output(scene_path, (".xml",), overwrite=overwrite, what="scene")
    mesh_path = Path(mesh_path)
    try:
        mesh_ref = os.path.relpath(mesh_path.resolve(), scene_path.parent.resolve())
    except ValueError:  # other drive on Windows
        mesh_ref = str(mesh_path.resolve())
    src = scenes_dir()
    text = (src / ("melt_chamber.xml" if chamber else "melt_plate.xml")).read_text()
    text = text[text.index("<scene") :]
    replacements = {
        '<include filename="layouts/$layout.xml"/>':
            f'<include filename="{escape((src / "layouts").as_posix())}/$layout.xml"/>',
        '<include filename="parts/detectors.xml"/>':
            f'<include filename="{escape((src / "parts" / "detectors.xml").as_posix())}"/>',
        'value="meshes/melt_plate.ply"': f'value="{escape(Path(mesh_ref).as_posix(), {chr(34): "&quot;"})}"',
        'id="melt_plate"': 'id="object"',
        f'<default name="material" value="{DEFAULT_MATERIAL}"/>':
            f'<default name="material" value="{escape(material, {chr(34): "&quot;"})}"/>',
    }
    if field_mm is not None:
        replacements['<default name="field" value="80"/>'] = f'<default name="field" value="{float(field_mm):.6g}"/>'
    if not face_normals:
        replacements['<boolean name="face_normals" value="true"/>'] = '<boolean name="face_normals" value="false"/>'
    if chamber:
        replacements['<include filename="parts/chamber.xml"/>'] = (
            f'<include filename="{escape((src / "parts" / "chamber.xml").as_posix())}"/>')
    for old, new in replacements.items():
        if old not in text:  # the template changed: fail loudly rather than write a wrong scene
            raise RuntimeError(f"the scene template no longer contains {old!r}")
        text = text.replace(old, new)
    header = (
        "<!--\n"
        f"  Generated by elo-mitsuba mesh from {mesh_path.name}: the object (id 'object', material\n"
        f"  parameter default {material!r}) with the four detectors of the ATHENE set-up, "
        f"{'in the ATHENE-like chamber' if chamber else 'no chamber'}.\n"
        "  Parameters and conventions as scenes_xml/melt_plate.xml (see scenes_xml/README.md):\n"
        "  layout, dh, dw, wd, field, res, spp, events, fwhm, projection, material.\n"
        "-->\n"
    )
    return atomic_write(scene_path, lambda tmp: tmp.write_text(header + text))


def write_object_scene(folder, name: str, mesh, *, material: str | None = None, chamber: bool = False,
                       overwrite: bool = False) -> Path:
    """Write ``mesh`` (e.g. a surface of :mod:`elo_mitsuba.objects`) as ``folder/name.ply`` and a
    scene that renders it as ``folder/name.xml`` (:func:`write_scene`); returns the scene's path.
    A mesh that carries its surface's own vertex normals is rendered with them, interpolated.

    Examples
    --------
    >>> import tempfile
    >>> from elo_mitsuba.objects.hills import hills_mesh
    >>> write_object_scene(tempfile.mkdtemp(), "hills", hills_mesh(80.0, 16)).name
    'hills.xml'
    """
    folder = Path(folder)
    check_output(folder / f"{name}.xml", (".xml",), overwrite=overwrite, what="scene")  # before the mesh is written
    mesh_path = write_mesh(mesh, folder / f"{name}.ply", overwrite=overwrite)
    smooth = getattr(mesh, "metadata", {}).get("vertex_normals") is not None
    return write_scene(folder / f"{name}.xml", mesh_path, material=material, chamber=chamber,
                       face_normals=not smooth, overwrite=overwrite)
