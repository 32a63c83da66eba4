"""``elo-mitsuba reflectance-map``: g_BSE over the (p, q) plane for one detector (Sec. 4.3)."""

from __future__ import annotations

import argparse

import numpy as np

from ..constants import DETECTOR_NAMES, TABLE1_LAYOUTS, WORK_DISTANCE_MM
from ..errors import EloInputError
from ._args import length_mm, material_arg, positive_float

DESCRIPTION = f"""\
Draw the reflectance maps of Sec. 4.3 (Figs. 12-13): the scattering function g_BSE of Eq. 13
(per steradian) as a function of the surface normal n_S = [p, q, 1] = [-dZ/dx, -dZ/dy, 1] for a
point detector in the direction d = [d_x, d_y, 1] (p,q-form, Eq. 17: d_x = (d_w - x)/d_h for the
right detector seen from (x, y)). Left panel: full g_BSE; right panel: its diffuse part only.
Hatched: normals for which the detector is geometrically masked, p d_x + q d_y + 1 <= 0
(for the right detector at the origin: p <= -d_h/d_w). The white cross marks d.

The layout is --dh/--dw in mm or --layout zetaNN (or --zeta NN), an inclination of Table 1
({', '.join(f'{z} deg: d_h={dh:g}, d_w={dw:g}' for z, (dh, dw) in TABLE1_LAYOUTS.items())}).
"""

EPILOG = """\
examples:
  elo-mitsuba reflectance-map --dh 272 --dw 127 -o fig12.png            # zeta = 25 deg
  elo-mitsuba reflectance-map --layout zeta50 -o fig13.png --data fig13.npz
  elo-mitsuba reflectance-map --zeta 25 --detector back --at 30,-20 --beam pivot -o map.png
"""


def _xy_arg(text):
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give X,Y in mm, e.g. 30,-20") from None
    if len(vals) != 2 or not all(np.isfinite(vals)):
        raise argparse.ArgumentTypeError(f"{text!r}: give X,Y in mm, e.g. 30,-20")
    return tuple(vals)


def _both(layout, given, flag, value):
    if given is not None:
        raise EloInputError(f"--layout {layout} sets dh and dw; {flag} {given:g} contradicts it: give the layout or "
                            "--dh/--dw, not both")
    return value


def add_parser(subparsers):
    p = subparsers.add_parser(
        "reflectance-map", help="g_BSE over the (p, q) plane of normals, masked region hatched",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("-o", "--output", required=True, metavar="MAP.png", help="PNG to write")
    p.add_argument("--dh", type=length_mm, metavar="MM", help="detector height d_h in mm")
    p.add_argument("--dw", type=length_mm, metavar="MM", help="detector distance d_w from the z-axis in mm")
    p.add_argument("--layout", metavar="zetaNN", help="a Table 1 detector layout instead of --dh/--dw: "
                   + ", ".join(f"zeta{z}" for z in TABLE1_LAYOUTS) + " (as render --layout)")
    p.add_argument("--zeta", type=float, choices=[float(z) for z in TABLE1_LAYOUTS], metavar="DEG",
                   help="the same by its inclination in degrees: " + ", ".join(map(str, TABLE1_LAYOUTS)))
    p.add_argument("--detector", choices=DETECTOR_NAMES, default="right", help="which detector (default right)")
    p.add_argument("--at", type=_xy_arg, default=(0.0, 0.0), metavar="X,Y",
                   help="surface position in mm the detector is seen from (default 0,0)")
    p.add_argument("--material", type=material_arg, default=None, help="preset or composition, e.g. Ti-6Al-4V or 'Ti:0.9,Al:0.1'")
    p.add_argument("--beam", choices=("vertical", "pivot"), default="vertical",
                   help="vertical beam (paper) or deflected from the gun pivot at --wd")
    p.add_argument("--wd", "--work-distance", dest="work_distance", type=length_mm, default=None, metavar="MM",
                   help=f"pivot height for --beam pivot (default {WORK_DISTANCE_MM:g} mm)")
    p.add_argument("--range", type=positive_float, default=3.0, metavar="R", help="plot -R <= p, q <= R (default 3)")
    p.add_argument("--samples", type=int, default=301, metavar="N", help="samples along p and q (default 301)")
    p.add_argument("--data", metavar="MAP.npz", help="also save p, q, g_full, g_diffuse, masked as .npz")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from ..analysis import beam_directions, detector_pq, layout_geometry, reflectance_map, zeta_deg
    from ..analysis.plots import plot_reflectance_maps
    from ..analysis.reflectance import MAX_PQ
    from ..files import atomic_write, check_output
    from ..physics import get_material

    out = check_output(args.output, (".png",), overwrite=args.overwrite)
    if args.data:
        check_output(args.data, (".npz",), overwrite=args.overwrite, what="--data")
    if args.layout is not None:
        from ..scene_files import layout_parameters

        if args.zeta is not None:
            raise EloInputError(f"--layout {args.layout} and --zeta {args.zeta:g} both set the layout; give one")
        layout = layout_parameters(args.layout)
        args.dh, args.dw = (_both(args.layout, args.dh, "--dh", layout["dh"]),
                            _both(args.layout, args.dw, "--dw", layout["dw"]))
    if args.range > MAX_PQ:
        raise EloInputError(f"--range {args.range:g}: must be at most {MAX_PQ:g} (|p|, |q| of a facet 89.94 degrees "
                            "from level; the default 3 is 71.6 degrees)")
    if args.zeta is not None and (args.dh is not None or args.dw is not None):
        raise EloInputError("give either --zeta or --dh/--dw, not both")
    if args.work_distance is not None and args.beam != "pivot":
        raise EloInputError(f"--wd {args.work_distance:g} sets the pivot of --beam pivot; with --beam "
                            f"{args.beam} (parallel to -z) it would change nothing: add --beam pivot or leave it out")
    work_distance = WORK_DISTANCE_MM if args.work_distance is None else args.work_distance
    d_h, d_w = layout_geometry(args.zeta, args.dh, args.dw)
    if not 2 <= args.samples <= 4001:
        raise EloInputError(f"--samples {args.samples}: allowed 2..4001")
    material = get_material(args.material)
    x, y = args.at
    d_pq = detector_pq(d_h, d_w, args.detector, x, y)
    beam = beam_directions(x, y, args.beam, work_distance)
    common = dict(beam_dir=beam, material=material, p_range=(-args.range, args.range),
                  q_range=(-args.range, args.range), n=args.samples)
    p, q, g_full, masked = reflectance_map(d_pq, lobe=True, **common)
    _, _, g_diff, _ = reflectance_map(d_pq, lobe=False, **common)
    title = (f"{args.detector} detector, d_h={d_h:g} mm, d_w={d_w:g} mm (zeta={zeta_deg(d_h, d_w):.1f} deg), "
             f"at ({x:g}, {y:g}) mm, {material.name}")
    plot_reflectance_maps(p, q, g_full, g_diff, masked, d_pq, out, title=title, overwrite=args.overwrite)
    print(f"wrote {out}: d = [{d_pq[0]:.4g}, {d_pq[1]:.4g}, 1], {100 * masked.mean():.1f} % of the window masked")
    if args.data:
        atomic_write(args.data, lambda tmp: np.savez(tmp, p=p, q=q, g_full=g_full, g_diffuse=g_diff,
                                                     masked=masked, d_pq=np.array(d_pq), d_h=d_h, d_w=d_w))
        print(f"wrote {args.data}")
    return 0
