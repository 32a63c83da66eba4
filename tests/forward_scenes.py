"""Scene dictionaries for the forward-model tests, built independently of scenes_xml/."""


def detector(mi, center, radius=25.0):
    """A disk detector at ``center`` facing the origin, absorbing (black) for Mitsuba's `path`."""
    c = [float(v) for v in center]
    return {
        "type": "disk",
        "to_world": mi.ScalarTransform4f().look_at(origin=c, target=[0, 0, 0], up=[0, 0, 1])
        @ mi.ScalarTransform4f().scale(radius),
        "emitter": {"type": "area"},
        "bsdf": {"type": "diffuse", "reflectance": 0.0},
    }


def four_detectors(mi, dh=272.0, dw=127.0, radius=25.0):
    return {
        "right": detector(mi, (dw, 0, dh), radius),
        "left": detector(mi, (-dw, 0, dh), radius),
        "back": detector(mi, (0, dw, dh), radius),
        "front": detector(mi, (0, -dw, dh), radius),
    }


def flat_scene(mi, res=3, field=80.0, wd=400.0, spp=64, events=1, integrator=None, wall=False,
               material="Ti-6Al-4V", dh=272.0, dw=127.0, projection="perspective", height=None):
    """Flat Ti-6Al-4V plate (300 x 300 mm at z=0) + four detectors, optionally one steel wall."""
    scene = {
        "type": "scene",
        "integrator": integrator or {"type": "elo", "events": events},
        "sensor": {
            "type": "elo_beam", "wd": wd, "field": field, "projection": projection,
            "film": {"type": "hdrfilm", "width": res, "height": height or res,
                     "rfilter": {"type": "box"}, "pixel_format": "luminance"},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "plate": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(150.0),
                  "bsdf": {"type": "elo_bse", "material": material}},
    }
    for name, d in four_detectors(mi, dh, dw).items():
        scene[name] = d
    if wall:
        # a 316L wall at x = -200 facing +x, 400 mm high: gives the 2nd event something to hit
        scene["wall"] = {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([-200.0, 0.0, 200.0])
            @ mi.ScalarTransform4f().rotate([0, 1, 0], 90.0) @ mi.ScalarTransform4f().scale(200.0),
            "bsdf": {"type": "elo_bse", "material": "316L"},
        }
    return scene
