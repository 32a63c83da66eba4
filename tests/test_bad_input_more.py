"""Issue 23, classes 7-9: more bad inputs, in the table style of tests/test_bad_input.py.

7. silent wrong results (NaN gradients, detectors under the plate, broken scene copies, Inf
   vertices) are refused; 8. contradictions are refused, not silently resolved, by every entry
   point; 9. parsing never tracebacks (garbage, pickled or empty files, a JSON list where an object
   belongs, text where numbers belong, a truncated EXR without the OpenEXR library's chatter).
Each case: exit status 2 (API: EloInputError), exactly one line naming what is wrong, no
traceback, no warning, nothing written or touched."""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import elo_mitsuba as em
from conftest import one_line_error, raw_exr
from elo_mitsuba.cli import main
from elo_mitsuba.exr import read_exr, write_exr
from elo_mitsuba.options import EloOptions, check_combination
from elo_mitsuba.scene_files import portable_scene_text, scene_values, scenes_dir

SENTINEL = b"written by the user"


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad_more")
    assert main(["render", "flat_plate", "-o", str(d / "flat.exr"), "--resolution", "8", "--quiet"]) == 0
    assert main(["render", "corrugated_sheet", "-o", str(d / "corr.exr"), "--resolution", "8", "--quiet"]) == 0
    assert main(["gradient", "--flat", str(d / "flat.exr"), str(d / "corr.exr"), "-o", str(d / "grad.exr")]) == 0
    (d / "exists.exr").write_bytes(SENTINEL)
    # 7: a gradient with NaN/Inf (written by another tool), detectors under the plate
    grad, gmeta = read_exr(d / "grad.exr")
    grad = {k: v.copy() for k, v in grad.items()}
    grad["dzdx"][2, 3], grad["dzdy"][1, 1] = np.nan, np.inf
    raw_exr(d / "nan_grad.exr", grad, json.dumps(gmeta))
    flat_images, fmeta = read_exr(d / "flat.exr")
    # flats of another beam pivot or projection (the images of the flat carry its beam's tilts)
    raw_exr(d / "flat_wd300.exr", flat_images, json.dumps({**fmeta, "work_distance_mm": 300.0}))
    raw_exr(d / "flat_ortho.exr", flat_images, json.dumps({**fmeta, "projection": "orthographic"}))
    raw_exr(d / "flat_volts.exr", {k: v * 300.0 for k, v in flat_images.items()}, json.dumps({**fmeta, "units": "V"}))
    good = {"detectors": {n: {k: g[k] for k in ("center", "normal", "radius")} for n, g in fmeta["detectors"].items()}}

    def calibration(name, **right):
        doc = json.loads(json.dumps(good))
        doc["detectors"]["right"].update(right)
        (d / name).write_text(json.dumps(doc))

    calibration("cal_below.json", center=[127, 0, -5])
    calibration("cal_through.json", center=[127, 0, 5])
    calibration("cal_away.json", normal=[0.42, 0, 0.9])
    # 9: text where numbers belong, a list where an object belongs
    calibration("cal_centre_text.json", center="127, 0, 272")
    calibration("cal_radius_text.json", radius="big")
    calibration("cal_gain_text.json", gain="x")
    doc = json.loads(json.dumps(good))
    doc["detectors"]["right"] = [127, 0, 272]
    (d / "cal_list.json").write_text(json.dumps(doc))
    src = scenes_dir()
    text = (src / "flat_plate.xml").read_text()
    (d / "truncated.xml").write_text(text[: len(text) // 2])
    np.save(d / "huge.npy", np.full((4, 4), 1e39))  # float64; float32 (PLY) holds up to 3.4e38
    np.save(d / "hm.npy", np.random.default_rng(0).random((4, 5)))
    (d / "empty.csv").write_text("")
    (d / "blank.csv").write_text("\n  \n")
    np.save(d / "pickled.npy", np.array([{"heights": 1}, None], dtype=object), allow_pickle=True)
    # detectors scaled beyond float32: NaN host geometry (numpy warned five times before the line)
    shutil.copytree(src, d / "sx", ignore=shutil.ignore_patterns("meshes", "*.py", "*.md"))
    detectors = d / "sx" / "parts" / "detectors.xml"
    detectors.write_text(detectors.read_text().replace('<scale value="25"/>', '<scale value="1e300"/>'))
    # detector plates that reflect diffusely (reflectance 0.5): ignored by the renderer until refused
    shutil.copytree(src, d / "sx_reflect", ignore=shutil.ignore_patterns("meshes", "*.py", "*.md"))
    plates = d / "sx_reflect" / "parts" / "plates_absorbing.xml"
    plates.write_text(plates.read_text().replace('name="reflectance" value="0"', 'name="reflectance" value="0.5"'))
    (d / "empty.npy").write_bytes(b"")
    np.save(d / "zero_size.npy", np.zeros((0,)))
    (d / "garbage.npy").write_bytes(b"\x00not an array")
    obj, ometa = read_exr(d / "corr.exr")
    raw_exr(d / "list_header.exr", obj, json.dumps([1, 2]))
    raw_exr(d / "list_header_grad.exr", read_exr(d / "grad.exr")[0], json.dumps(["field_mm", 80]))
    data = (d / "corr.exr").read_bytes()
    (d / "cut_pixels.exr").write_bytes(data[:-100])  # header whole, the pixel data cut short
    (d / "cut_header.exr").write_bytes(data[:300])
    (d / "magic_only.exr").write_bytes(data[:4])
    (d / "png.exr").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    shutil.copy(src / "flat_plate.xml", d / "plate_copy.xml")
    np.save(d / "tall.npy", np.linspace(0.0, 500.0, 64).reshape(8, 8))  # a relief reaching the detectors
    np.save(d / "bool.npy", np.eye(4, dtype=bool))
    disc = '<shape type="disk" id="{n}"><transform name="to_world"><scale value="{r}"/><lookat origin="{o}" ' \
           'target="0, 0, 0" up="0, 1, 0"/></transform><emitter type="area"{e}</emitter></shape>'
    origins = {"right": "127, 0, 272", "left": "-127, 0, 272", "back": "0, 127, 272", "front": "0, -127, 272"}

    def plate_scene(name, radius="25", emitter=">", sensor="", film="", shapes="", ids=None, bsdf="/>"):
        discs = "".join(disc.format(n=(ids or {}).get(n, n), o=o, r=radius if n == "right" else "25",
                                    e=emitter if n == "right" else ">") for n, o in origins.items())
        (d / name).write_text(
            '<scene version="3.0.0"><integrator type="elo"/><sensor type="elo_beam"><float name="field" value="80"/>'
            + sensor + '<film type="hdrfilm"><integer name="width" value="4"/><integer name="height" value="4"/>'
            + film + '<rfilter type="box"/></film></sensor><shape type="rectangle" id="plate"><transform '
            'name="to_world"><scale x="100" y="100"/></transform><bsdf type="elo_bse"' + bsdf + '</shape>' + discs + shapes
            + "</scene>")

    plate_scene("radiance.xml", emitter='><rgb name="radiance" value="5"/>')
    plate_scene("huge_detector.xml", radius="1e30")
    # the XML sweep (2026-12-05): settings the renderer would not apply, names it would collide on
    plate_scene("gun_moved.xml", sensor='<transform name="to_world"><translate x="5"/></transform>')
    plate_scene("film_crop.xml", film='<integer name="crop_width" value="2"/><integer name="crop_height" value="2"/>')
    plate_scene("id_collides.xml", ids={"back": "right.err"})
    (d / "cycle_a.xml").write_text('<scene version="3.0.0"><include filename="cycle_b.xml"/></scene>')
    (d / "cycle_b.xml").write_text('<scene version="3.0.0"><include filename="cycle_a.xml"/></scene>')
    (d / "cycle.xml").write_text('<scene version="3.0.0"><include filename="cycle_a.xml"/></scene>')
    (d / "missing_include.xml").write_text('<scene version="3.0.0"><include filename="nothere.xml"/></scene>')
    portable = portable_scene_text(scenes_dir() / "flat_plate.xml")
    (d / "empty_default.xml").write_text(re.sub(r'<default name="wd" value="[^"]*"/>', '<default name="wd" value=""/>',
                                                portable))
    # the scene-file sweep (2026-12-06): numbers Mitsuba takes and fails far from, or reads as 0;
    # emitters that are not detectors; errors inside an included file
    (d / "nan_default.xml").write_text(re.sub(r'<default name="wd" value="[^"]*"/>', '<default name="wd" value="nan"/>',
                                              portable))
    plate_scene("empty_float.xml", shapes='<shape type="rectangle" id="baffle"><transform name="to_world"><translate '
                                          'x="200" z="50"/></transform><bsdf type="diffuse"><float name="reflectance" '
                                          'value=""/></bsdf></shape>')
    plate_scene("nan_translate.xml", shapes='<shape type="rectangle" id="baffle"><transform name="to_world">'
                                            '<translate x="0" y="0" z="nan"/></transform><bsdf type="elo_bse"/></shape>')
    plate_scene("point_emitter.xml", shapes='<emitter type="point"><point name="position" value="0, 0, 100"/></emitter>')
    plate_scene("constant_emitter.xml", shapes='<emitter type="constant"/>')
    (d / "bad_part.xml").write_text('<scene version="3.0.0">\n<shape type="sphere" id="ball">\n'
                                    '<float name="bogus" value="1"/></shape></scene>')
    plate_scene("include_error.xml", shapes='<include filename="bad_part.xml"/>')
    for name, options in (("own_sampling", '<string name="detector_sampling" value="stratified"/>'
                                           '<integer name="detector_samples" value="16"/>'),
                          ("volts_unused", '<float name="beam_current" value="0.01"/>')):
        plate_scene(f"{name}.xml")
        (d / f"{name}.xml").write_text((d / f"{name}.xml").read_text().replace(
            '<integrator type="elo"/>', f'<integrator type="elo">{options}</integrator>'))
    (d / "no_faces.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                    "property float z\nelement face 0\nproperty list uchar int vertex_indices\n"
                                    "end_header\n0 0 1\n1 0 1\n0 1 1\n")
    (d / "bad_index.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                     "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                     "end_header\n0 0 1\n1 0 1\n0 1 1\n3 0 1 7\n")
    (d / "flat_zero.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                     "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                     "end_header\n0 0 1\n0 0 1\n0 0 1\n3 0 1 2\n")
    (d / "far_index.ply").write_text((d / "bad_index.ply").read_text().replace("3 0 1 7", "3 0 1 100000000"))
    for name in ("no_faces", "bad_index", "far_index", "flat_zero"):
        plate_scene(f"{name}.xml", shapes=f'<shape type="ply" id="bump"><string name="filename" value="{name}.ply"/>'
                                          '<bsdf type="elo_bse"/></shape>')
    plate_scene("instance.xml", shapes='<shape type="shapegroup" id="grp"><shape type="rectangle"><bsdf type="elo_bse"/>'
                                       '</shape></shape><shape type="instance" id="baffle"><ref id="grp"/><transform '
                                       'name="to_world"><translate x="500"/></transform></shape>')
    plate_scene("conductor_plates.xml")
    (d / "conductor_plates.xml").write_text((d / "conductor_plates.xml").read_text().replace(
        '<emitter type="area">', '<bsdf type="conductor"/><emitter type="area">', 1))
    plate_scene("lobe_text.xml", bsdf='><string name="lobe" value="false"/></bsdf>')
    plate_scene("lobe_25.xml", bsdf='><float name="lobe_width" value="25"/></bsdf>')
    (d / "no_sensor.xml").write_text('<scene version="3.0.0"><integrator type="elo"/></scene>')
    shutil.copy(Path(__file__).parents[1] / "examples" / "optimize_athene.toml", d / "design.toml")
    return d


INV = ["invert", "--flat", "{d}/flat.exr", "{d}/corr.exr", "-o", "{d}/h.exr"]
GRAD = ["gradient", "--flat", "{d}/flat.exr", "{d}/corr.exr", "-o", "{d}/g.exr"]
R = ["render", "flat_plate", "-o", "{d}/new.exr", "--quiet"]
MESH = ["-o", "{d}/m.ply", "--pixel-size", "0.05"]

#: (id, argv, a fragment of the one line)
CLI_CASES = [
    # -- 7: silent wrong results
    ("invert --init inf gradient", [*INV, "--init", "{d}/nan_grad.exr"], "channel 'dzdy' holds 1 infinite value(s)"),
    ("reconstruct inf gradient", ["reconstruct", "{d}/nan_grad.exr", "-o", "{d}/h.npy"], "holds 1 infinite value"),
    ("gradient calibration below the plate", [*GRAD, "--calibration", "{d}/cal_below.json"],
     "cal_below.json: detector 'right' has its centre at z=-5 mm, at or below the build plane"),
    ("gradient calibration through the plate", [*GRAD, "--calibration", "{d}/cal_through.json"],
     "cal_through.json: detector 'right' (centre z=5 mm, radius 25 mm) reaches down to z=-5.5"),
    ("invert calibration through the plate", [*INV, "--calibration", "{d}/cal_through.json"],
     "through the build plane z=0"),
    ("gradient calibration faces away", [*GRAD, "--calibration", "{d}/cal_away.json"], "faces away from the scan field"),
    ("gradient --dh cuts the plate", [*GRAD, "--dh", "5", "--dw", "127"], "--dh/--dw: detector 'right'"),
    ("new-scene truncated xml", ["new-scene", "{d}/s.xml", "--from", "{d}/truncated.xml"], "malformed XML"),
    ("mesh heights beyond float32", ["mesh", "{d}/huge.npy", *MESH], "beyond the float32 range of a PLY"),
    ("mesh --base beyond float32", ["mesh", "{d}/hm.npy", *MESH, "--base=-1e39"], "z coordinates reach 1e+39 mm"),
    # -- 8: contradictions refused
    ("render -D res with --resolution", [*R, "-D", "res=32", "--resolution", "16"],
     "--resolution 16 and -D res=32 both set the resolution"),
    ("render --layout with -D dh", [*R, "--resolution", "4", "--layout", "zeta50", "-D", "dh=100"],
     "--layout zeta50 sets dh and dw; -D dh=100 contradicts it"),
    ("render --layout with -D dw", [*R, "--resolution", "4", "--layout", "zeta50", "-D", "dw=100"], "-D dw=100 contradicts"),
    ("render --layout with -D layout", [*R, "--resolution", "4", "--layout", "zeta50", "-D", "layout=zeta25"],
     "-D layout=zeta25 contradicts"),
    ("render --transimpedance without volts", [*R, "--resolution", "4", "--transimpedance", "2e6"],
     "--transimpedance 2000000.0 scales volts only"),
    ("render --detector-samples with the quadrature", [*R, "--resolution", "4", "--detector-samples", "4",
                                                       "--quality", "draft"],
     "--detector-samples 4 would change nothing: --quality draft integrates the 1st event"),
    ("reconstruct --field contradicts the header", ["reconstruct", "{d}/grad.exr", "-o", "{d}/h.npy", "--field", "40"],
     "field 40x40 mm contradicts the header's field_mm 80x80 mm"),
    ("render, no electron reaches a detector", [*R, "--resolution", "4", "-D", "field=1e6"],
     "flat_plate: no electron reached any detector anywhere in the scan"),
    ("invert --fwhm beyond the field", [*INV, "--fwhm", "100"], "beam FWHM 100 mm (--fwhm): must be below"),
    ("invert --init relief reaching the detectors", [*INV, "--init", "{d}/tall.npy"],
     "--init heights: a relief of 500 mm (largest less smallest height) reaches the detectors"),
    ("invert output is its input", ["invert", "--flat", "{d}/flat.exr", "{d}/corr.exr", "-o", "{d}/corr.exr",
                                    "--overwrite"], "output {d}/corr.exr is also an input of this command"),
    ("gradient output is its input", ["gradient", "--flat", "{d}/flat.exr", "{d}/corr.exr", "-o", "{d}/flat.exr",
                                      "--overwrite"], "output {d}/flat.exr is also an input of this command"),
    ("reconstruct output is its input", ["reconstruct", "{d}/grad.exr", "-o", "{d}/grad.exr", "--overwrite"],
     "output {d}/grad.exr is also an input of this command"),
    ("new-scene onto its source", ["new-scene", "{d}/plate_copy.xml", "--from", "{d}/plate_copy.xml", "--overwrite"],
     "scene {d}/plate_copy.xml is also an input of this command"),
    ("render a detector with a radiance", ["render", "{d}/radiance.xml", "-o", "{d}/new.exr"],
     "detector 'right' has an emitter radiance of 5, which the renderer does not use"),
    ("render a detector beyond float32", ["render", "{d}/huge_detector.xml", "-o", "{d}/new.exr"],
     "detector 'right' has area nan mm^2 (a scale beyond float32?)"),
    ("mesh a bool array", ["mesh", "{d}/bool.npy", *MESH], "has dtype bool; heights must be real numbers"),
    ("new-scene empty name", ["new-scene", ""], "scene: the path is empty"),
    ("calibrate --event with --second-event", ["calibrate", "{d}/flat.exr", "--event", "1", "--second-event",
                                               "{d}/flat.exr", "-o", "{d}/c.json"], "--event 1 already takes one event"),
    ("calibrate --second-event of a 1st-event render", ["calibrate", "{d}/flat.exr", "--second-event", "{d}/flat.exr",
                                                         "-o", "{d}/c.json"],
     "flat.exr: rendered with events=1; later events need --events >= 2"),
    ("render a gun with a to_world transform", ["render", "{d}/gun_moved.xml", "-o", "{d}/new.exr"],
     "elo_beam: a to_world transform would be ignored"),
    ("render a cropped film", ["render", "{d}/film_crop.xml", "-o", "{d}/new.exr"],
     "elo_beam: the film crops 2x2 px at (0, 0) of 4x4; a crop is not supported"),
    ("render a detector id that names a channel", ["render", "{d}/id_collides.xml", "-o", "{d}/new.exr",
                                                   "--error-channels"],
     "id_collides.xml: detector id 'right.err': an id names the detector's image channels"),
    ("render a mesh without triangles", ["render", "{d}/no_faces.xml", "-o", "{d}/new.exr"],
     "no_faces.xml: mesh file 'no_faces.ply' has 3 vertices and 0 triangles"),
    ("render a mesh whose triangle names a missing vertex", ["render", "{d}/bad_index.xml", "-o", "{d}/new.exr"],
     "bad_index.ply: a triangle names vertex 7, but the file has 3"),
    ("render a mesh whose triangle names vertex 1e8 (a segmentation fault in Mitsuba's loader)",
     ["render", "{d}/far_index.xml", "-o", "{d}/new.exr"], "far_index.ply: a triangle names vertex 100000000"),
    ("render a mesh of no area", ["render", "{d}/flat_zero.xml", "-o", "{d}/new.exr"],
     "surface 'bump' has an area of 0 mm^2 (a scale of 0, or beyond float32?)"),
    ("render an instance of a shapegroup (its shapes out of the checks' reach; refused as a wrong BSDF before)",
     ["render", "{d}/instance.xml", "-o", "{d}/new.exr"], "surface 'baffle' is an instance of a shapegroup"),
    ("render a detector with a conductor BSDF", ["render", "{d}/conductor_plates.xml", "-o", "{d}/new.exr"],
     "detector 'right' has a SmoothConductor BSDF that reflects"),
    ("render a scene's own sampling under a preset", ["render", "{d}/own_sampling.xml", "-o", "{d}/new.exr"],
     "own_sampling.xml sets detector_sampling='stratified', detector_samples=16, which quality 'default' would "
     "override or not use"),
    ("render a scene's beam current without volts", ["render", "{d}/volts_unused.xml", "-o", "{d}/new.exr"],
     "elo: beam_current=0.01 scales volts only"),
    ("render a detector through the chamber wall", ["render", "athene_flat", "-o", "{d}/new.exr", "--resolution",
                                                     "4", "-D", "dw=360"],
     "detector 'right' is cut by a surface of the scene"),
    ("render the heat shield through the detectors", ["render", "shield_chamber", "-o", "{d}/new.exr", "--resolution",
                                                      "4", "--layout", "zeta75"], "detector 'right' is cut by"),
    ("render an include cycle", ["render", "{d}/cycle.xml", "-o", "{d}/new.exr"],
     "cycle_b.xml: includes 'cycle_a.xml', which includes it again (cycle.xml -> cycle_a.xml -> cycle_b.xml -> "
     "cycle_a.xml): an include cycle"),
    ("render a missing include", ["render", "{d}/missing_include.xml", "-o", "{d}/new.exr"],
     "included file 'nothere.xml' not found (an include is relative to the scene's folder"),
    ("render an empty default", ["render", "{d}/empty_default.xml", "-o", "{d}/new.exr"],
     "<default name='wd'> has no value (Mitsuba would read it as 0)"),
    ("render a default of nan in the scene file", ["render", "{d}/nan_default.xml", "-o", "{d}/new.exr"],
     "nan_default.xml: <default name='wd'> is 'nan', not a finite number"),
    ("render an empty float (Mitsuba reads it as 0)", ["render", "{d}/empty_float.xml", "-o", "{d}/new.exr"],
     "empty_float.xml: <float name='reflectance' value=''> is empty (Mitsuba would read it as 0)"),
    ("render a transform of nan", ["render", "{d}/nan_translate.xml", "-o", "{d}/new.exr"],
     "nan_translate.xml: <translate z='nan'> holds 'nan', not a finite number"),
    ("render a point emitter (not applied)", ["render", "{d}/point_emitter.xml", "-o", "{d}/new.exr"],
     "emitter '(no id)' (PointLight) is not on a shape, and the renderer does not use it"),
    ("render a constant emitter (not applied)", ["render", "{d}/constant_emitter.xml", "-o", "{d}/new.exr"],
     "(ConstantBackgroundEmitter) is not on a shape"),
    ("render an error in an included file", ["render", "{d}/include_error.xml", "-o", "{d}/new.exr"],
     "include_error.xml: in {d}/bad_part.xml line 2: Found 1 unreferenced property in shape plugin of type \"sphere\""),
    ("render a lobe given as text", ["render", "{d}/lobe_text.xml", "-o", "{d}/new.exr"],
     "elo_bse: lobe='false'; must be true or false"),
    ("render a scene without a sensor", ["render", "{d}/no_sensor.xml", "-o", "{d}/new.exr"],
     "the scene needs one sensor, <sensor type=\"elo_beam\"> (the gun); it has none"),
    ("render sample_count 0", [*R, "--resolution", "4", "--quality", "scene", "-D", "spp=0"],
     "the sampler's sample_count is 0 (-D spp=0)"),
    # -- 8: contradictions refused
    ("render --events with -D events", [*R, "--resolution", "4", "--events", "1", "-D", "events=3"],
     "--events 1 and -D events=3 both set events"),
    ("render --spp with -D spp", [*R, "--resolution", "4", "--quality", "scene", "--spp", "4", "-D", "spp=8"],
     "--spp 4 and -D spp=8 both set spp"),
    ("render -D twice", [*R, "--resolution", "4", "-D", "dh=100", "-D", "dh=200"],
     "-D dh=100 and -D dh=200: the parameter is given twice with different values"),
    ("optimize --design beyond the trials", ["optimize", "{d}/design.toml", "-o", "{d}/front.zarr", "--design", "100"],
     "--design 100: the run stores designs 0 .. 99"),
    ("reflectance-map --work-distance without pivot", ["reflectance-map", "--zeta", "50", "-o", "{d}/m.png",
                                                       "--work-distance", "300"], "add --beam pivot"),
    ("reflectance-map --layout and --zeta", ["reflectance-map", "--layout", "zeta50", "--zeta", "50", "-o",
                                             "{d}/m.png"], "--layout zeta50 and --zeta 50 both set the layout"),
    ("reflectance-map --layout and --dh", ["reflectance-map", "--layout", "zeta50", "--dh", "100", "-o", "{d}/m.png"],
     "--layout zeta50 sets dh and dw; --dh 100 contradicts it"),
    ("reflectance-map --layout unknown", ["reflectance-map", "--layout", "zeta33", "-o", "{d}/m.png"],
     "unknown detector layout 'zeta33'"),
    # -- 9: parsing never tracebacks
    ("invert --init garbage npy", [*INV, "--init", "{d}/garbage.npy"], "--init {d}/garbage.npy: not a readable .npy"),
    ("invert --init pickled npy", [*INV, "--init", "{d}/pickled.npy"], "cannot be loaded when allow_pickle=False"),
    ("invert --init empty npy", [*INV, "--init", "{d}/empty.npy"], "not a readable .npy array (an empty file)"),
    ("invert --init zero-size npy", [*INV, "--init", "{d}/zero_size.npy"], "expected one 2-D numeric image"),
    ("gradient header is a JSON list", ["gradient", "--flat", "{d}/flat.exr", "{d}/list_header.exr", "-o", "{d}/g.exr"],
     "header attribute 'elo_mitsuba' holds a JSON list, not an object"),
    ("reconstruct header is a JSON list", ["reconstruct", "{d}/list_header_grad.exr", "-o", "{d}/h.npy"],
     "holds a JSON list"),
    ("gradient calibration centre is text", [*GRAD, "--calibration", "{d}/cal_centre_text.json"],
     "detector 'right': center '127, 0, 272'"),
    ("gradient calibration radius is text", [*GRAD, "--calibration", "{d}/cal_radius_text.json"], "radius 'big'"),
    ("gradient calibration gain is text", [*GRAD, "--calibration", "{d}/cal_gain_text.json"], "gain 'x' is not a number"),
    ("gradient calibration detector is a list", [*GRAD, "--calibration", "{d}/cal_list.json"],
     "detector 'right' is a JSON list"),
    ("gradient EXR cut in its pixels", ["gradient", "--flat", "{d}/flat.exr", "{d}/cut_pixels.exr", "-o", "{d}/g.exr"],
     "not a readable EXR file (truncated or corrupt"),
    ("gradient EXR cut in its header", ["gradient", "--flat", "{d}/flat.exr", "{d}/cut_header.exr", "-o", "{d}/g.exr"],
     "not a readable EXR file"),
    ("invert --flat EXR of 4 bytes", ["invert", "--flat", "{d}/magic_only.exr", "{d}/corr.exr", "-o", "{d}/h.exr"],
     "magic_only.exr: not a readable EXR file"),
    ("gradient PNG named .exr", ["gradient", "--flat", "{d}/png.exr", "{d}/corr.exr", "-o", "{d}/g.exr"],
     "png.exr: not a readable EXR file (it does not start with the EXR magic number)"),
    ("mesh empty csv", ["mesh", "{d}/empty.csv", *MESH], "is empty (no numbers)"),
    ("mesh a file that is not .npy", ["mesh", "{d}/garbage.npy", *MESH], "garbage.npy' could not be read: not a NumPy .npy file"),
    ("mesh blank csv", ["mesh", "{d}/blank.csv", *MESH], "is empty (no numbers)"),
    # float32 vertices: a pixel of 1e-300 mm put every vertex at x = y = 0 and wrote the mesh
    ("mesh --pixel-size 1e-300", ["mesh", "{d}/hm.npy", "-o", "{d}/m.ply", "--pixel-size", "1e-300"],
     "pixel size 1e-300 mm must be 1e-06 to 1e+06 mm"),
    ("mesh --base nan", ["mesh", "{d}/hm.npy", *MESH, "--base", "nan"], "base nan mm must be a finite number below"),
    ("gradient --min-corrected nan", [*GRAD, "--min-corrected", "nan"], "--min-corrected nan: must be a finite number"),
    ("gradient --min-sum inf", [*GRAD, "--min-sum", "inf"], "--min-sum inf: must be a finite number"),
    ("validate --only bogus", ["validate", "--only", "bogus"], "invalid choice: 'bogus'"),
    ("gradient with a flat of another work distance", ["gradient", "--flat", "{d}/flat_wd300.exr", "{d}/corr.exr", "-o",
                                                      "{d}/g.exr"],
     "flat_wd300.exr: flat-plate work_distance_mm 300.0 differs from the object's 400.0; record all with one geometry"),
    ("gradient with a flat in volts", ["gradient", "--flat", "{d}/flat_volts.exr", "{d}/corr.exr", "-o", "{d}/g.exr"],
     "flat_volts.exr: flat-plate units 'V' differs from the object's 'N_d/N_0'; give all in one unit"),
    ("gradient with the object as its flat", ["gradient", "--flat", "{d}/corr.exr", "{d}/corr.exr", "-o", "{d}/g.exr"],
     "corr.exr is both an object image and a flat-plate image"),
    ("invert with the object as its flat", ["invert", "--flat", "{d}/flat.exr", "--flat", "{d}/corr.exr", "{d}/corr.exr",
                                           "-o", "{d}/h.exr"], "corr.exr is both an object image and a flat-plate image"),
    ("invert with a flat of another projection", ["invert", "--flat", "{d}/flat_ortho.exr", "{d}/corr.exr", "-o",
                                                 "{d}/h.exr"],
     "flat_ortho.exr: flat-plate projection 'orthographic' differs from the object's 'perspective'"),
    # the render side's sweep (2026-12-05, third session): a file its own reader refused, Inf
    # written after the work, numpy's warnings before the line
    ("render -D wd=1e-300", ["render", "flat_plate", "-D", "wd=1e-300", "-o", "{d}/new.exr"],
     "elo_beam: wd=1e-300 mm; must be 1e-06 to 1e+06 mm"),
    ("render pixels below 1e-6 mm", ["render", "flat_plate", "-D", "field=1e-6", "--resolution", "16", "-o",
                                     "{d}/new.exr"], "is a pixel of 6.25e-08 mm; pixels must be >= 1e-06 mm"),
    ("render --beam-current 1e300", ["render", "flat_plate", "--units", "voltage", "--beam-current", "1e300", "-o",
                                     "{d}/new.exr"], "= 1e+305 V per unit signal (Eq. 9); must be 1e-20 to 1e+20 V"),
    ("render --transimpedance 1e-300", ["render", "flat_plate", "--units", "voltage", "--transimpedance", "1e-300",
                                        "-o", "{d}/new.exr"], "= 3e-303 V per unit signal"),
    ("render detector plates that reflect", ["render", "{d}/sx_reflect/flat_plate.xml", "-o", "{d}/new.exr"],
     "detector 'right' has a SmoothDiffuse BSDF that reflects, which the renderer does not apply"),
    ("render a detector scaled beyond float32", ["render", "{d}/sx/flat_plate.xml", "-o", "{d}/new.exr"],
     "detectors.xml: <scale value='1e300'> holds '1e300', beyond float32 (Mitsuba's numbers reach 3.4e38)"),
]


def _snapshot(d):
    return {p.name: p.read_bytes() for p in d.rglob("*") if p.is_file()}


def _main(argv):
    try:
        return main(argv)
    except SystemExit as exc:  # argparse's usage errors
        return exc.code


@pytest.mark.parametrize("argv,fragment", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_cli_bad_input(d, capfd, argv, fragment):
    before = _snapshot(d)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = _main([a.format(d=d) for a in argv])
    out, err = capfd.readouterr()  # file descriptors: what a C library prints counts too
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith(("elo-mitsuba: error: ", "python -m validation: error: ")), err
    assert "Traceback" not in err and fragment.format(d=d) in lines[0], lines[0]
    assert "Traceback" not in out and "Warning" not in out, out
    assert not [str(w.message) for w in caught if not issubclass(w.category, ResourceWarning)]  # no numpy warning
    assert _snapshot(d) == before  # nothing written, nothing touched


def _scene():
    return em.load_scene("flat_plate", res=2)


def _after_a_preset_render():
    scene = _scene()
    scene.render(quality="draft", progress=False)
    return scene


#: (id, call, a fragment of the one-line EloInputError)
def _configured(**options):
    scene = em.load_scene("flat_plate", res=2)
    scene.configure(**options)
    return scene


def _invert(**kw):
    from elo_mitsuba.analysis.inversion import invert_heights

    return invert_heights(_flats(), _flats(), _geometry(), **kw)


def _noise(level):
    from elo_mitsuba.analysis.noise import check_noise

    return check_noise(level)


def _pq_grid(p_range):
    from elo_mitsuba.analysis.reflectance import pq_grid

    return pq_grid(p_range, (-1.0, 1.0), 3)


def _two_events():
    from elo_mitsuba.result import RenderResult

    e1, e2 = np.full((2, 2), 0.03), np.full((2, 2), 1e-6)
    return RenderResult({"right": e1 + e2, "right.e1": e1, "right.e2": e2}, {"events": 2})


API_CASES = [
    # bounds of the analysis's own parameters, as the command line has them
    ("check_noise 1e-300", lambda: _noise(1e-300), "noise=1e-300: must be a number from 1e-09 to 1"),
    ("invert_heights alpha 1e300", lambda: _invert(alpha=1e300), "alpha=1e+300: must be a number from 0 to 1e+06"),
    ("invert_heights fwhm 1e-300", lambda: _invert(fwhm_mm=1e-300), "beam FWHM 1e-300 mm (--fwhm): must be 0 (a single"),
    ("pq_grid beyond 1e3", lambda: _pq_grid((-1e300, 1e300)), "p_range=(-1e+300, 1e+300): must be lo < hi within +-1000"),
    ("negligible_events threshold text", lambda: _two_events().negligible_events("a"),
     "threshold='a': must be a share of the signal from 0 to 1"),
    ("negligible_events threshold nan", lambda: _two_events().negligible_events(float("nan")), "threshold=nan"),
    ("pq_grid reversed", lambda: _pq_grid((1.0, -1.0)), "p_range=(1.0, -1.0): must be lo < hi"),
    ("configure beam_current without volts", lambda: _scene().configure(beam_current=2e-3),
     "beam_current=0.002 scales volts only"),
    ("configure transimpedance without volts", lambda: _scene().configure(units="fraction", transimpedance=1e6),
     "add units='voltage'"),
    ("configure detector_samples with the quadrature",
     lambda: _scene().configure(detector_sampling="quadrature", detector_samples=4),
     "detector_samples=4 would change nothing: detector_sampling='quadrature'"),
    ("configure detector_samples after a preset", lambda: _after_a_preset_render().configure(detector_samples=4),
     "would change nothing"),
    ("EloOptions.replace beam_current", lambda: EloOptions().replace(beam_current=1e-3), "scales volts only"),
    ("check_combination sweep names", lambda: check_combination({"detector_samples": 4}, qualities=["default"],
                                                                events=1, prefix="integrator."),
     "integrator.detector_samples=4 would change nothing: quality 'default'"),
    ("load_scene layout and dh", lambda: scene_values("zeta50", {"dh": 100}),
     "detector_layout zeta50 sets dh and dw; dh=100 contradicts it"),
    ("load_scene detector_layout and dh", lambda: em.load_scene("flat_plate", detector_layout="zeta50", dh=100),
     "detector_layout zeta50 sets dh and dw; dh=100 contradicts it"),
    ("render a preset after detector_samples", lambda: _configured(detector_sampling="independent",
                                                                   detector_samples=4).render(quality="default"),
     "detector_samples=4 would change nothing: quality 'default'"),
    ("write_exr png", lambda: write_exr("/tmp/never-written.png", {"a": np.zeros((2, 2))}), "must end in .exr"),
    ("write_exr int", lambda: write_exr(5, {"a": np.zeros((2, 2))}), "EXR path 5 (int)"),
    ("write_exr None", lambda: write_exr(None, {"a": np.zeros((2, 2))}), "EXR path None"),
    ("write_exr nan in the header", lambda: write_exr("/tmp/never-written.exr", {"a": np.zeros((2, 2))},
                                                      {"thresholds": {"min_corrected": math.nan}}),
     "metadata holds NaN or Inf at thresholds.min_corrected"),
    ("read_calibration centre text", lambda: _read_calibration({"center": "abc"}), "center 'abc'"),
    ("read_calibration below", lambda: _read_calibration({"center": [127, 0, -1]}), "at or below the build plane"),
    ("read_calibration gain 0", lambda: _read_calibration({"gain": 0}), "finite gain other than 0"),
    ("read_calibration radius 1e-300", lambda: _read_calibration({"radius": 1e-300}),
     "detector 'right': detector radius 1e-300 mm: must be 1e-06 to 1e+06 mm"),
    ("read_calibration normal zero", lambda: _read_calibration({"normal": [0, 0, 0]}),
     "detector 'right': detector normal [0, 0, 0]: must not be zero"),
    ("heightmap_to_mesh beyond float32", lambda: _mesh(np.full((3, 3), 4e38)), "beyond the float32 range"),
    # the Python API's sweep (2026-12-05): truthy non-bools read as consent, numbers beyond float,
    # settings that silently changed or emptied a result
    ("write_exr overwrite='no'", lambda: _scene().render(quality="draft", progress=False).write_exr(
        "/tmp/never-written.exr", overwrite="no"), "overwrite='no': must be True or False"),
    ("write_exr NUL in the path", lambda: write_exr("/tmp/never\x00written.exr", {"a": np.zeros((2, 2))}),
     "a path cannot hold a NUL character"),
    ("render force='False'", lambda: _scene().render(force="False"), "force='False'; must be True or False"),
    ("render progress='no'", lambda: _scene().render(progress="no"), "progress='no'; must be True or False (or None)"),
    ("render quality a list", lambda: _scene().render(quality=["draft"]), "quality ['draft']; choose one of"),
    ("render spp text", lambda: _scene().render(spp="4"), "spp='4'; must be a whole number in [1, 4294967295]"),
    ("render events beyond float", lambda: _scene().render(events=10 ** 400), "elo: events=1000"),
    ("configure beyond float", lambda: _scene().configure(detector_samples=10 ** 400), "must be a finite number"),
    ("render a loaded scene with a variant", lambda: em.render(_scene(), variant="bogus"),
     "fixed once an EloScene is loaded"),
    ("ScanGeometry shape 16.5", lambda: _geometry((16.5, 16)), "shape (16.5, 16): give (rows, columns)"),
    ("calibrate without the back detector", lambda: _calibrate(drop="back"), "back missing (got right, left, front)"),
    ("calibrate grid 0", lambda: _calibrate(grid=0), "grid=0; must be a whole number >= 2"),
    ("surface_gradient min_sum nan", lambda: _gradient(min_sum=math.nan), "min_sum=nan; must be a number in [0, 2)"),
    ("model_gradient iterations 1.5", lambda: _model_gradient(iterations=1.5), "iterations=1.5; must be a whole number"),
    # the sweep's leftovers (2026-12-05, second session): wrong types read as other values, raw
    # tracebacks, a setting that silently changed the answer
    ("calibrate fit_offset='no'", lambda: _calibrate(fit_offset="no"), "fit_offset='no'; must be True or False"),
    ("calibrate without detectors", lambda: _calibrate_with(_geometry_kw(detectors={})), "has no detectors"),
    ("calibrate text images", lambda: _calibrate_with(_geometry(), {n: np.full((8, 8), "abc") for n in _flats()}),
     "flat-plate image 'right': an array of text; need real numbers"),
    ("calibrate a 4x4 image", lambda: _calibrate_with(_geometry((4, 4)), {n: v[:4, :4] for n, v in _flats().items()}),
     "need at least 8 pixels a side"),
    ("model_gradient nodes 0", lambda: _model_gradient(nodes=0), "nodes=0; must be two whole numbers"),
    ("model_gradient heights of another shape", lambda: _model_gradient(heights=np.zeros((4, 4))),
     "heights: shape (4, 4); need (8, 8)"),
    ("model_gradient NaN heights", lambda: _model_gradient(heights=np.full((8, 8), np.nan)), "heights: hold NaN or Inf"),
    ("model_gradient start text", lambda: _model_gradient(start="x"), "start='x': must be a GradientResult"),
    ("model_gradient flat_second_event lacks a detector", lambda: _model_gradient(
        flat_second_event={"right": np.zeros((8, 8))}), "flat_second_event: missing detector image(s) left"),
    ("surface_gradient complex images", lambda: _gradient_of({n: v + 1j for n, v in _flats().items()}),
     "object images: right: an array of complex numbers"),
    ("surface_gradient field as text", lambda: _gradient_field("80"), "field_mm='80': give one or two finite lengths"),
    ("surface_gradient d_h as text", lambda: _surface_gradient_dh("272"), "d_h='272': expected a length in mm"),
    ("invert_heights geometry None", lambda: _invert(geometry=None), "geometry=None: must be a ScanGeometry"),
    ("invert_heights force='no'", lambda: _invert(force="no"), "force='no'; must be True or False"),
    ("invert_heights scales 0", lambda: _invert(scales=0), "scales=0; must be a whole number >= 1"),
    ("invert_heights time budget 0", lambda: _invert(time_budget_s=0), "time_budget_s=0: must be a number of seconds"),
    ("invert_heights border of 1.5 px", lambda: _invert(fixed_border=1.5), "fixed_border=1.5; must be a whole"),
    ("invert_heights start text", lambda: _invert(start="flat"), "start heights: an array of text"),
    ("integrate mask of 2s", lambda: _integrate_with(mask=np.full((8, 8), 2.0)), "mask: holds values other than 0 and 1"),
    ("integrate min_component_size -1", lambda: _integrate_with(min_component_size=-1),
     "min_component_size=-1; must be a whole number >= 1"),
    ("integrate_robust tol nan", lambda: _integrate_robust(tol=math.nan), "tol=nan: must be a finite number"),
    ("integrate_fft mirror='no'", lambda: _integrate_fft(mirror="no"), "mirror='no'; must be True or False"),
    ("height_gradient 1x1", lambda: _height_gradient(np.zeros((1, 1))), "differences need 2 pixels a side"),
    ("ScanGeometry aim offset nan", lambda: _geometry_kw(aim_offset_mm=(math.nan, 0)), "aim_offset_mm (nan, 0)"),
    ("ScanGeometry d_h negative", lambda: _nominal(d_h=-272), "d_h=-272 mm: must be finite and > 0"),
    ("write_exr channels a list", lambda: write_exr("/tmp/never-written.exr", [np.zeros((2, 2))]),
     "give a mapping {channel name: 2-D image}"),
    ("write_exr empty channel name", lambda: write_exr("/tmp/never-written.exr", {"": np.zeros((2, 2))}),
     "channel name '': need a non-empty text"),
    ("write_exr 0x0", lambda: write_exr("/tmp/never-written.exr", {"a": np.zeros((0, 0))}), "2-D images of one shape"),
    ("write_exr complex", lambda: write_exr("/tmp/never-written.exr", {"a": np.zeros((2, 2)) + 1j}),
     "channel 'a': an array of complex numbers"),
    ("write_exr metadata object", lambda: write_exr("/tmp/never-written.exr", {"a": np.zeros((2, 2))}, {"x": object()}),
     "cannot store object in EXR metadata"),
    ("read_exr None", lambda: read_exr(None), "EXR path None: give a file name"),
    ("write_height mask of another shape", lambda: _write_height(np.zeros((4, 4)), np.zeros((3, 3), bool)),
     "mask shape (3, 3) differs from the height map's (4, 4)"),
    ("write_height text", lambda: _write_height(np.full((2, 2), "abc")), "height: an array of text"),
    ("configure an array of numbers", lambda: _scene().configure(detector_samples=np.array([4, 5])),
     "detector_samples=array([4, 5]); must be one number"),
    ("restore_detectors 5", lambda: _scene().restore_detectors(5), "no placed detector 5"),
    ("set_detector centre with a bool", lambda: _scene().set_detector("right", center=(True, 0, 250)),
     "centre (True, 0, 250); need 3 finite numbers"),
    ("set_detector radius True", lambda: _scene().set_detector("right", radius=True), "radius True; need a finite"),
    ("set_detector centre beyond float32", lambda: _scene().set_detector("right", center=(1e300, 0, 1e300)),
     "within +-1e+06 mm"),
    ("sweep seed beyond float", lambda: _sweep_spec(seed=10 ** 400), "must be a whole number in [0, 4294967295]"),
    # the optimiser spec's sweep (2026-12-05, third session): tracebacks (IndexError, OverflowError,
    # numpy's seed ValueError) and numpy warnings from numbers beyond any chamber
    ("render spp 10**300", lambda: _scene().render(spp=10 ** 300), "must be a whole number in [1, 4294967295]"),
    ("sweep spp 1e300", lambda: _sweep_spec(render={"spp": 1e300}),
     "render.spp = 1e+300; must be a whole number in [1, 4294967295]"),
    ("optimize dh 1e300", lambda: _optimize_spec(parameters={"dh": [60.0, 1e300]}),
     "parameters.dh = 1e+300; must be a finite number <= 1e+06"),
    ("optimize aim_z -1e300", lambda: _optimize_spec(parameters={"aim_z": -1e300}), "must be a finite number >= -1e+06"),
    ("optimize wd 1e300", lambda: _optimize_spec(metric={"wd": 1e300}), "metric.wd = 1e+300; must be a finite number >= 1e-06 <= 1e+06"),
    ("optimize s_max 1e300", lambda: _optimize_spec(metric={"s_max": 1e300}), "metric.s_max = 1e+300; must be a finite number >= 0 <= 5.7"),
    ("optimize amplifier 1e300", lambda: _optimize_spec(metric={"amplifier": 1e300}), "metric.amplifier = 1e+300; must be a finite"),
    ("optimize beam current 1e300", lambda: _optimize_spec(metric={"beam_current": 1e300}),
     "metric.beam_current = 1e+300 A x metric.dwell = 1e-06 s is inf electrons per pixel; must be <= 1e+30"),
    ("optimize seed 2^40", lambda: _optimize_spec(optimizer={"seed": 2 ** 40}), "optimizer.seed = 1099511627776; must be a whole number >= 0 <= 4294967295"),
]


def _optimize_spec(**tables):
    from elo_mitsuba.design.spec import load_spec

    return load_spec(tables)


def _calibrate_with(geometry, flats=None):
    from elo_mitsuba.analysis.calibration import calibrate

    return calibrate(_flats() if flats is None else flats, geometry)


def _gradient_of(images):
    from elo_mitsuba.analysis import surface_gradient

    return surface_gradient(images, _flats(), 80.0, 272.0, 127.0)


def _gradient_field(field):
    from elo_mitsuba.analysis import surface_gradient

    return surface_gradient(_flats(), _flats(), field, 272.0, 127.0)


def _surface_gradient_dh(d_h):
    from elo_mitsuba.analysis import surface_gradient

    return surface_gradient(_flats(), _flats(), 80.0, d_h, 127.0)


def _invert(geometry="nominal", **kw):
    from elo_mitsuba.analysis.inversion import invert_heights

    return invert_heights(_flats(), _flats(), _geometry() if geometry == "nominal" else geometry, **kw)


def _integrate_with(**kw):
    from elo_mitsuba.analysis.integrate import integrate_gradient

    return integrate_gradient(np.zeros((8, 8)), np.zeros((8, 8)), 8.0, **kw)


def _integrate_robust(**kw):
    from elo_mitsuba.analysis.integrate import integrate_robust

    return integrate_robust(np.zeros((8, 8)), np.zeros((8, 8)), 8.0, **kw)


def _integrate_fft(**kw):
    from elo_mitsuba.analysis.integrate import integrate_fft

    return integrate_fft(np.zeros((8, 8)), np.zeros((8, 8)), 8.0, **kw)


def _height_gradient(height):
    from elo_mitsuba.analysis.integrate import height_gradient

    return height_gradient(height, 8.0)


def _geometry_kw(**kw):
    from elo_mitsuba.analysis.scan_geometry import ScanGeometry

    return ScanGeometry(field_mm=80.0, shape=(8, 8), **{"detectors": _geometry().detectors, **kw})


def _nominal(d_h=272.0, d_w=127.0):
    from elo_mitsuba.analysis.scan_geometry import ScanGeometry

    return ScanGeometry.nominal((8, 8), 80.0, d_h, d_w)


def _write_height(height, mask=None):
    from elo_mitsuba.heightmap import write_height

    return write_height("/tmp/never-written-height.npy", height, mask)


def _sweep_spec(**top):
    from elo_mitsuba.sweeps.spec import load_spec

    return load_spec({"scene": "flat_plate", "vary": {"dh": [200, 272]}, **top})


def _geometry(shape=(8, 8)):
    from elo_mitsuba.analysis.scan_geometry import ScanGeometry

    return ScanGeometry.nominal(shape, 80.0, 272.0, 127.0)


def _flats():
    from elo_mitsuba.analysis import flat_plate_images

    return flat_plate_images((8, 8), 80.0, 272.0, 127.0, model="lambert")


def _calibrate(drop=None, **kw):
    from elo_mitsuba.analysis.calibration import calibrate

    return calibrate({n: v for n, v in _flats().items() if n != drop}, _geometry(), **kw)


def _gradient(**kw):
    from elo_mitsuba.analysis import surface_gradient

    return surface_gradient(_flats(), _flats(), 80.0, 272.0, 127.0, **kw)


def _model_gradient(**kw):
    from elo_mitsuba.analysis.model_gradient import model_gradient

    return model_gradient(_flats(), _flats(), _geometry(), **kw)


def _read_calibration(right, tmp=[]):  # noqa: B006 - one folder for the module's calls
    import tempfile
    from pathlib import Path

    from elo_mitsuba.analysis.calibration import read_calibration

    disc = {"center": [127.0, 0.0, 272.0], "normal": [-0.42, 0.0, -0.91], "radius": 25.0}
    path = Path(tempfile.mkdtemp()) / "c.json"
    path.write_text(json.dumps({"detectors": {"right": {**disc, **right}}}))
    try:
        return read_calibration(path)
    finally:
        shutil.rmtree(path.parent)


def _mesh(height):
    from elo_mitsuba.mesh import heightmap_to_mesh

    return heightmap_to_mesh(height, 0.1)


@pytest.mark.parametrize("call,fragment", [c[1:] for c in API_CASES], ids=[c[0] for c in API_CASES])
def test_api_bad_input(call, fragment):
    message = one_line_error(call)
    assert fragment in message, message


def test_a_refused_render_changes_nothing():
    """A refused render leaves the scene's events and quality as they were."""
    scene = _scene()
    with pytest.raises(em.EloInputError, match="quality 'bogus'"):
        scene.render(events=2, quality="bogus")
    assert scene.options.events == 1
    # refused by the time estimate, after the events and the quality were set: both as they were
    # (16^2 px at the most spp a sampler counts: days of work)
    scene = em.load_scene("flat_plate", res=16)
    with pytest.raises(em.EloInputError, match="refused"):
        scene.render(events=2, quality="draft", spp=2 ** 32 - 1)
    assert scene.options.events == 1 and scene.quality == "scene"
    assert scene.render(progress=False).metadata["events"] == 1


def test_refused_configure_changes_nothing():
    scene = _scene()
    before = scene.options
    with pytest.raises(em.EloInputError):
        scene.configure(beam_current=2e-3)
    assert scene.options == before
    assert scene.configure(units="voltage", beam_current=2e-3).beam_current == 2e-3  # together: applied


@pytest.mark.parametrize("argv,fragment", [
    (["gradient", "--flat", "{d}/flat.exr", "{d}/cut_pixels.exr", "-o", "{d}/g.exr"], "truncated or corrupt"),
    (["validate", "--only", "bogus"], "invalid choice: 'bogus'"),
])
def test_real_processes(d, argv, fragment):
    """The OpenEXR library's own report (on file descriptors 1 and 2) and argparse's usage stay
    unprinted: one line on stderr, nothing on stdout."""
    before = _snapshot(d)
    r = subprocess.run([sys.executable, "-m", "elo_mitsuba", *[a.format(d=d) for a in argv]], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and fragment in r.stderr, r.stderr
    assert r.stdout == "" and "Traceback" not in r.stderr and _snapshot(d) == before


def test_a_good_exr_still_reads_and_says_nothing(d, capfd):
    channels, meta = read_exr(d / "corr.exr")
    assert set(channels) >= {"right", "left", "back", "front"} and isinstance(meta, dict)
    assert capfd.readouterr() == ("", "")


def test_the_table_has_every_class():
    assert len(CLI_CASES) + len(API_CASES) >= 45
    assert len({c[0] for c in CLI_CASES}) == len(CLI_CASES) and len({c[0] for c in API_CASES}) == len(API_CASES)


def test_nan_in_a_gradient_is_unknown_not_spread(d):
    """Another tool's NaN gradient pixels (a gradient without a mask channel) are masked and 0 (the
    'gradient' command's convention), so an integration (reconstruct, invert --init) never sees
    them: issue 23 measured a 1.4e5 mm height range from one NaN. (NaN where a mask channel says
    trusted is refused: tests/test_bad_input_analysis.py.)"""
    from elo_mitsuba.analysis.io import read_gradient

    grad, meta = read_exr(d / "grad.exr")
    grad = {k: v.copy() for k, v in grad.items() if k != "mask"}
    grad["dzdx"][2, 3] = np.nan
    raw_exr(d / "only_nan.exr", grad, json.dumps(meta))
    g = read_gradient(d / "only_nan.exr")
    assert g["dzdx"][2, 3] == 0 and g["mask"][2, 3] and np.all(np.isfinite(g["dzdx"]))
    assert g["mask"].sum() == 1
    assert main(["reconstruct", str(d / "only_nan.exr"), "-o", str(d / "only_nan_h.npy")]) == 0
    assert main(["reconstruct", str(d / "grad.exr"), "-o", str(d / "plain_h.npy")]) == 0
    h, plain = np.load(d / "only_nan_h.npy"), np.load(d / "plain_h.npy")
    # no height (NaN, heightmap.write_height) at most where masked; the rest finite, not spread
    assert np.isnan(h).sum() <= g["mask"].sum() and not np.isinf(h).any()
    assert np.nanmax(h) - np.nanmin(h) < 2 * (np.nanmax(plain) - np.nanmin(plain)) + 1e-9


def test_a_dark_detector_is_said_in_a_note():
    """A render in which no electron reaches a detector says so (the API writes it, the CLI refuses
    to write four black images): the beam of a 1000 m field misses the 100 mm plate."""
    dark = em.load_scene("flat_plate", res=4, field=1e6).render(quality="draft", progress=False)
    assert dark.dark_detectors == ["right", "left", "back", "front"]
    assert sum("received no electron anywhere in the scan" in n for n in dark.metadata["notes"]) == 4
    lit = em.load_scene("flat_plate", res=4).render(quality="draft", progress=False)
    assert lit.dark_detectors == [] and not any("received no electron" in n for n in lit.metadata["notes"])


def test_a_detector_in_the_beams_path_is_said_in_a_note():
    """A detector between the gun and the field stops the beam there (no surface under those
    pixels) and said nothing. A 25 mm disc 30 mm above the middle of the 80 mm field, seen from
    the gun at the work distance wd, covers pi (25 wd / (wd - 30))^2 / 80^2 of the field (36 % at
    wd = 400 mm)."""
    scene = em.load_scene("flat_plate", res=8)
    plain = scene.render(quality="draft", progress=False).metadata
    assert not any("beam's path" in n for n in plain["notes"])
    scene.set_detector("right", center=(0, 0, 30))
    notes = [n for n in scene.render(quality="draft", progress=False).metadata["notes"] if "beam's path" in n]
    assert len(notes) == 1 and notes[0].startswith("detector 'right' lies in the beam's path over about ")
    share = float(notes[0].split("about ")[1].split(" %")[0])
    wd = plain["work_distance_mm"]
    expected = 100 * math.pi * (25 * wd / (wd - 30)) ** 2 / 80 ** 2
    assert abs(share - expected) < 2.0, (share, expected)  # the probe's 65 x 65 grid


def test_a_wall_turned_away_from_the_field_is_said_in_a_note(tmp_path):
    """A chamber wall whose front faces out of the chamber (its look-at target on the outer side)
    absorbs every electron that reaches it, silently: the right detector's 2nd event fell by 16 %
    (32², `default`). The render names its plane (x = 350 mm, normal +x) in a note; a steel dome
    whose normals point out is named once, as a whole (its e2 was exactly 0)."""
    import shutil

    from elo_mitsuba.scene_files import scenes_dir

    shutil.copytree(scenes_dir(), tmp_path / "s", ignore=shutil.ignore_patterns("meshes", "*.py", "*.md"))
    chamber = tmp_path / "s" / "parts" / "chamber.xml"
    text = chamber.read_text()
    assert text.count('target="349, -60, 275"') == 1
    chamber.write_text(text.replace('target="349, -60, 275"', 'target="351, -60, 275"'))
    notes = [n for n in em.load_scene(tmp_path / "s" / "athene_flat.xml", res=4).render(
        quality="draft", progress=False).metadata["notes"] if "arrive at its back" in n]
    assert len(notes) == 1 and notes[0].startswith("a surface, its plane of normal (1, 0, 0) about (350, "), notes
    assert " mm: 100 % of the electrons leaving the scan field that reach it arrive at its back" in notes[0]
    # a curved surface is named once, as a whole: a steel dome round the plate, its normals outward
    dome = ('<shape type="sphere" id="dome"><float name="radius" value="800"/><bsdf type="elo_bse"><string '
            'name="material" value="316L"/></bsdf></shape>')
    plate = tmp_path / "s" / "flat_plate.xml"
    plate.write_text(plate.read_text().replace('<include filename="parts/detectors.xml"/>',
                                               '<include filename="parts/detectors.xml"/>' + dome))
    notes = [n for n in em.load_scene(plate, res=4, events=2).render(quality="draft", progress=False).metadata["notes"]
             if "arrive at its back" in n]
    assert len(notes) == 1 and notes[0].startswith("surface 'dome', about ("), notes
    assert "100 % of the electrons leaving the scan field that reach it arrive at its back (" in notes[0]
    of_all = float(re.search(r"\(([0-9.]+) % of all that leave\)", notes[0]).group(1))
    assert 95 < of_all < 99, notes[0]  # all but those that reach the detectors (97.5 %)


def test_surfaces_overlapping_in_one_plane_are_said_in_a_note(tmp_path):
    """A floor frame moved onto the plate (x in [-25, 225] mm): the ray tracer returns the floor or
    the plate at the same depth, and the pixels there mix 316L and Ti-6Al-4V without a sign (the
    1st event changed by 8 %). The render names both surfaces, their materials and where; no
    shipped scene has such a pair, nor does a floor frame that only touches the plate's edge."""
    import shutil

    from elo_mitsuba.plugins._relief import beam_probe, surfaces_overlapping
    from elo_mitsuba.scene_files import scenes_dir, shipped_scenes

    shutil.copytree(scenes_dir(), tmp_path / "s", ignore=shutil.ignore_patterns("*.py", "*.md"))
    chamber = tmp_path / "s" / "parts" / "chamber.xml"
    text = chamber.read_text()
    frame = '<lookat origin="225, 0, 0" target="225, 0, 1" up="0, 1, 0"/>'
    assert text.count(frame) == 1
    for scene, origin in (("athene_flat", 100), ("melt_chamber", 100)):
        chamber.write_text(text.replace(frame, frame.replace("225, 0, 0", f"{origin}, 0, 0").replace("225, 0, 1", f"{origin}, 0, 1")))
        notes = [n for n in em.load_scene(tmp_path / "s" / f"{scene}.xml", res=4).render(
            quality="draft", progress=False).metadata["notes"] if "lie in one plane" in n]
        assert len(notes) == 1, (scene, notes)
        assert notes[0].startswith("a surface without an id (316L) and ") and "(Ti-6Al-4V)" in notes[0], notes
        share = float(re.search(r"overlap over about ([0-9.]+) % of the scan field", notes[0]).group(1))
        assert 30 < share < 85, notes[0]  # of the field's 81 % under the frame, where the floor is met
    # the shipped scenes; and a 200 mm field, whose probe rows and columns at +-100 mm lie on the
    # edges the plate shares with the floor frame: an edge shared is not an overlap
    for name, field in [(name, 80) for name in shipped_scenes()] + [("athene_flat", 200)]:
        loaded = em.load_scene(name, res=4, field=field).scene
        beam = loaded.sensors()[0]
        si = beam_probe(loaded, beam)
        if field == 200:
            assert np.count_nonzero(np.isclose(np.abs(np.ravel(si.p[0])), 100.0, atol=1e-4)) >= 100
        assert surfaces_overlapping(list(loaded.shapes()), beam, lambda: si) == [], name


def test_images_of_another_lobe_than_the_models_get_a_note(d, capsys):
    """The header records each surface's g_BSE lobe; gradient, invert and calibrate say when it is
    not the paper's, which their models assume (a 25 deg lobe biased the corrugated sheet's median
    slope to 1.072 for a true 1.000 without a word)."""
    assert main(["render", str(d / "lobe_25.xml"), "-o", str(d / "lobe25.exr"), "--quality", "draft", "--quiet"]) == 0
    _, meta = read_exr(d / "lobe25.exr")
    assert meta["scattering"] == {"plate": {"lobe": True, "lobe_width_deg": 25.0}}
    shutil.copy(d / "lobe25.exr", d / "lobe25_flat.exr")  # one file cannot be both (refused)
    capsys.readouterr()
    for args in (["gradient", str(d / "lobe25.exr"), "--flat", str(d / "lobe25_flat.exr"), "-o", str(d / "g25.exr")],
                 ["calibrate", str(d / "lobe25.exr"), "-o", str(d / "c25.json"), "--max-misfit", "1"]):
        main(args)
        assert "another g_BSE than the analysis models" in capsys.readouterr().err, args[0]
    assert main(["gradient", str(d / "corr.exr"), "--flat", str(d / "flat.exr"), "-o", str(d / "g13.exr")]) == 0
    assert "another g_BSE" not in capsys.readouterr().err


def test_set_detector_moves_discs_only(d):
    """A rectangle detector has a to_world transform too, and set_detector(radius=20) turned a
    50 mm square into a 40 mm one (a sweep over detectors.radius did so without a word)."""
    text = (d / "radiance.xml").read_text().replace('<rgb name="radiance" value="5"/>', "")
    square = text.replace('<shape type="disk" id="right">', '<shape type="rectangle" id="right">', 1)
    (d / "square_detector.xml").write_text(square)
    scene = em.load_scene(str(d / "square_detector.xml"))
    message = one_line_error(lambda: scene.set_detector("right", radius=20))
    assert "detector 'right' is not a disk; move it by editing the scene" in message
    scene.set_detector("back", radius=20)  # the discs still move


def test_a_scenes_own_sampling_renders_with_quality_scene(d):
    """The refusal under a preset names the way that works: the scene file's sampling as set."""
    assert main(["render", str(d / "own_sampling.xml"), "-o", str(d / "own.exr"), "--quality", "scene",
                 "--quiet", "--overwrite"]) == 0
    _, meta = read_exr(d / "own.exr")
    assert meta["integrator_options"]["detector_sampling"] == "stratified"
    assert meta["integrator_options"]["detector_samples"] == 16


def test_a_mesh_with_vertex_normals_is_said_to_be_smoothed(d, tmp_path):
    """A user's PLY without face_normals=true: g_BSE sees its vertex normals interpolated, and the
    corrugated sheet rendered like a flat plate (left image range 1.23-1.72e-3 against 0.34-1.66e-3
    with facets) without a word. The shipped scenes' meshes (facets) and rectangles get no note."""
    scene = (scenes_dir() / "corrugated_sheet.xml").read_text()
    assert 'name="face_normals" value="true"' in scene
    smooth = scenes_dir() / "corrugated_sheet.xml"
    text = em.scene_files.portable_scene_text(smooth).replace('<boolean name="face_normals" value="true"/>', "")
    (tmp_path / "smooth.xml").write_text(text)
    notes = em.load_scene(str(tmp_path / "smooth.xml"), res=4).render(quality="draft", progress=False).metadata["notes"]
    assert any("has vertex normals: g_BSE sees them interpolated" in n for n in notes), notes
    for name in ("corrugated_sheet", "athene_flat"):
        notes = em.load_scene(name, res=4).render(quality="draft", progress=False).metadata["notes"]
        assert not any("vertex normals" in n for n in notes), (name, notes)


def test_a_tiny_field_renders_with_the_filter_and_reads_back(tmp_path):
    """A 10 nm field at 8 px: the bounce filter's 1 mm window is 8e5 pixels, which asked for
    tiles of 2^19 px (a 1 TiB scratch plane, a traceback); capped at the image it renders, and
    the header (pixel 1.25e-6 mm) reads back."""
    from elo_mitsuba.options import filter_window_levels

    assert filter_window_levels(1.0, 1e-5 / 8) == 19 and filter_window_levels(1.0, 1e-5 / 8, 8) == 3
    assert filter_window_levels(1.0, 80.0 / 1500, 1500) == filter_window_levels(1.0, 80.0 / 1500) == 4
    scene = em.load_scene("athene_flat", res=8, field=1e-5)
    result = scene.render(quality="default", progress=False)
    assert scene.integrator.options.bounce_filter == 1.0  # the filter did run
    result.write_exr(tmp_path / "tiny.exr")
    images, header = read_exr(tmp_path / "tiny.exr")
    assert header["pixel_size_mm"] == pytest.approx(1.25e-6)
    assert all(np.isfinite(v).all() and (v > 0).all() for v in images.values())


def test_a_huge_detector_normal_is_a_direction_without_warnings():
    """set_detector takes a normal of any length: (-1e300, -1e300, -1e300) is the direction
    (-1, -1, -1), and the zero test took its norm first (numpy's overflow warnings before the
    render, the sweep fuzz of 2026-12-05)."""
    scene = em.load_scene("flat_plate", res=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene.set_detector("right", normal=(-1e300, -1e300, -1e300))
    np.testing.assert_allclose(scene.detector_geometry()["right"]["normal"], -np.ones(3) / np.sqrt(3), atol=1e-4)  # float32


def test_more_scales_than_the_image_holds_are_the_scales_it_holds():
    """``--scales 2^63`` looped over 2^63 factors of 2^k and ran out of memory (a MemoryError
    traceback): the factors stop where the shorter side would keep fewer than MIN_SCALE_PX pixels."""
    from elo_mitsuba.analysis.height_solver import scale_factors

    assert scale_factors((512, 512), 2 ** 63) == scale_factors((512, 512), 5) == [16, 8, 4, 2]
    assert scale_factors((32, 32), 2 ** 63) == [] and scale_factors((1500, 1500), 2 ** 63) == [4, 2]
