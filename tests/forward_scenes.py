"""Scene dictionaries for the forward-model tests, built independently of scenes_xml/."""

import numpy as np


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


def disc_integral(point, beam_dir, normal, centre, disc_normal, radius, material, n_r=64, n_phi=256,
                  lobe=True):
    """Eq. 5 by quadrature over a disc: int g_BSE dOmega = int g_BSE cos(theta_d) / r^2 dA.

    Gauss-Legendre in the radius, uniform (spectrally accurate) in the azimuth.
    """
    from elo_mitsuba.analysis.geometry import disc_nodes
    from elo_mitsuba.physics import g_bse

    disc_normal = np.asarray(disc_normal, float) / np.linalg.norm(disc_normal)
    q, WA = disc_nodes(centre, disc_normal, radius, n_r, n_phi)
    d = q - np.asarray(point, float)
    dist2 = np.sum(d * d, axis=-1)
    dirs = d / np.sqrt(dist2)[..., None]
    cos_d = np.clip(-np.sum(dirs * disc_normal, axis=-1), 0.0, None)
    g = g_bse(np.broadcast_to(normal, dirs.shape), np.broadcast_to(beam_dir, dirs.shape), dirs,
              material, lobe=lobe)
    return float(np.sum(g * cos_d / dist2 * WA))
