"""``elo-mitsuba gradient``: four detector images -> surface gradient by Eq. 26 (+ mask)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..constants import DETECTOR_NAMES
from ..errors import EloInputError

DESCRIPTION = """\
Compute the surface gradient dZ/dx, dZ/dy of the build surface from four detector images
(right +x, left -x, back +y, front -y), after Renner et al. 2023:

  1. STSA correction (Sec. 2.1.4):  R^C = R / R_flat, ... (flat = images of a plane plate)
  2. normalised differences (Eq. 15): M_x = (R^C - L^C)/(R^C + L^C),  M_y = (B^C - F^C)/(B^C + F^C)
  3. gradient (Eq. 26):  -dZ/dx = n_Sx = M_x d_h / (d_w + x M_x + y M_y),
                         -dZ/dy = n_Sy = M_y d_h / (d_w + x M_x + y M_y)
     with (x, y) the pixel position in mm and d_h, d_w the detector height and distance from the
     z-axis. Eq. 26 removes the d_w/d_h scaling and the position dependence of raw M_x (Eq. 24).

Geometry (field, d_h, d_w) comes from the EXR headers written by 'elo-mitsuba render'
(d_h = detector centre z, d_w = centre distance from the z-axis; the four must agree); --field,
--dh, --dw override it and are required for recorded machine images given as four single-channel
files (EXR/TIFF/NPY, same orientation: row 0 = +y edge, columns towards +x).

Output EXR channels: dzdx, dzdy (mm/mm), Mx, My, sum_rl, sum_bf (Eq. 23, material contrast),
mask (1 = untrusted pixel: a detector masked or dark, a sum or the Eq. 26 denominator near zero,
bad input; gradient 0 there) and mask_reason (bit field, see the header). The header carries the
geometry so that 'elo-mitsuba reconstruct' needs no flags.
"""

EPILOG = """\
examples:
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad.exr --preview grad.png
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad_e1.exr --event 1      # 1st event only
  elo-mitsuba gradient --right R.tif --left L.tif --back B.tif --front F.tif \\
      --flat-right R0.tif --flat-left L0.tif --flat-back B0.tif --flat-front F0.tif \\
      --field 80 --dh 272 --dw 127 -o grad.exr
"""


def field_arg(text: str) -> tuple[float, float]:
    """argparse type for ``--field FX[,FY]`` in mm."""
    try:
        vals = [float(v) for v in text.replace("x", ",").split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give FX or FX,FY in mm, e.g. 80 or 80,60") from None
    if len(vals) not in (1, 2) or not all(np.isfinite(v) and v > 0 for v in vals):
        raise argparse.ArgumentTypeError(f"{text!r}: give one or two lengths > 0 in mm, e.g. 80 or 80,60")
    return (vals[0], vals[-1])


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (np.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: must be finite and > 0")
    return v


def add_parser(subparsers):
    p = subparsers.add_parser(
        "gradient", help="four detector images -> surface gradient (Eq. 26) and mask",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("object", nargs="?", metavar="OBJECT.exr",
                   help="object images: EXR with channels right, left, back, front")
    p.add_argument("-o", "--output", required=True, metavar="GRAD.exr", help="gradient EXR to write")
    src = p.add_argument_group("single-channel inputs (recorded machine images)")
    for n in DETECTOR_NAMES:
        src.add_argument(f"--{n}", metavar="FILE", help=f"{n} detector image (EXR/TIFF/NPY)")
    flat = p.add_argument_group("STSA correction (flat plate)")
    flat.add_argument("--flat", metavar="FLAT.exr", help="flat-plate EXR with channels right, left, back, front")
    for n in DETECTOR_NAMES:
        flat.add_argument(f"--flat-{n}", metavar="FILE", help=f"flat-plate image of the {n} detector")
    flat.add_argument("--no-flat", action="store_true",
                      help="the inputs are already STSA-corrected (skip the division)")
    geo = p.add_argument_group("geometry (overrides the EXR headers)")
    geo.add_argument("--field", type=field_arg, metavar="FX[,FY]", help="scan field in mm, e.g. 80")
    geo.add_argument("--dh", type=positive_float, metavar="MM", help="detector height d_h in mm")
    geo.add_argument("--dw", type=positive_float, metavar="MM", help="detector distance d_w from the z-axis in mm")
    p.add_argument("--event", type=int, metavar="K",
                   help="use the per-event channels right.eK ... instead of the totals")
    thr = p.add_argument_group("mask thresholds")
    thr.add_argument("--min-corrected", type=float, default=None, metavar="V",
                     help="a corrected image R^C <= V marks the pixel (detector masked); default 0.02")
    thr.add_argument("--min-sum", type=float, default=None, metavar="V",
                     help="R^C+L^C or B^C+F^C below V marks the pixel; default 0.05 (flat plate: 2)")
    thr.add_argument("--min-denominator", type=float, default=None, metavar="F",
                     help="Eq. 26 denominator <= F*d_w marks the pixel; default 0.05")
    p.add_argument("--preview", metavar="PNG", help="also write a PNG of dZ/dx, dZ/dy with the mask")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(run=run)
    return p


def _same(a, b, rtol=1e-6):
    return np.allclose(np.asarray(a, float), np.asarray(b, float), rtol=rtol, atol=0)


def _report_mask(res) -> None:
    """Why pixels are masked (share per reason of MASK_BITS), and a warning when most are."""
    import sys

    from ..analysis.gradient import MASK_BITS

    if not res.mask.any():
        return
    shares = [f"{name} {100 * np.mean((res.reasons & bit) > 0):.2f} %" for name, bit in MASK_BITS.items()
              if np.any(res.reasons & bit)]
    print(f"masked pixels by reason (a pixel may have several): {', '.join(shares)}")
    if res.mask.mean() > 0.5:
        print(f"elo-mitsuba: warning: {100 * res.mask.mean():.1f} % of the pixels are masked; see the reasons above "
              "and the mask thresholds in 'elo-mitsuba gradient --help'", file=sys.stderr)


def run(args) -> int:
    from ..analysis import geometry_from_metadata, surface_gradient
    from ..analysis.gradient import MIN_CORRECTED, MIN_DENOMINATOR
    from ..analysis.io import check_signs, load_detector_set, write_gradient
    from ..analysis.plots import preview_gradient
    from ..analysis.stsa import MIN_SUM
    from ..files import check_output

    out = check_output(args.output, (".exr",), overwrite=args.overwrite)
    if args.preview:
        check_output(args.preview, (".png",), overwrite=args.overwrite, what="preview")
    images, meta = load_detector_set(args.object, {n: getattr(args, n) for n in DETECTOR_NAMES}, "object images",
                                     args.event)
    if images is None:
        raise EloInputError("no object images: give OBJECT.exr or --right/--left/--back/--front")
    flats, flat_meta = load_detector_set(args.flat, {n: getattr(args, f"flat_{n}") for n in DETECTOR_NAMES},
                                 "flat-plate images", args.event)
    if flats is None and not args.no_flat:
        raise EloInputError("no flat-plate images: give --flat FLAT.exr (or --flat-right ...), "
                            "or --no-flat if the images are already STSA-corrected")
    if flats is not None and args.no_flat:
        raise EloInputError("--no-flat contradicts the flat-plate images given")
    check_signs(images, flats, {n: args.object or getattr(args, n) for n in DETECTOR_NAMES})

    # Geometry: explicit flags win; otherwise the object header, else the flat header.
    header = meta if meta else flat_meta
    source = args.object or args.flat or "command line"
    if not header and (args.field is None or args.dh is None or args.dw is None):
        what = (f"{source} has no elo-mitsuba geometry header (not written by 'elo-mitsuba render')"
                if (args.object or args.flat) else "single-channel inputs carry no geometry")
        raise EloInputError(f"{what}: pass --field, --dh and --dw (mm)")
    shape = next(iter(images.values())).shape
    geo = geometry_from_metadata(header, str(source), d_h=args.dh, d_w=args.dw, field_mm=args.field, shape=shape)
    if meta and flat_meta:
        # The flat must describe the same scan, or the division mixes two geometries.
        fgeo = geometry_from_metadata(flat_meta, str(args.flat), d_h=args.dh, d_w=args.dw, field_mm=args.field,
                                      shape=shape)
        for key in ("field_mm", "d_h", "d_w", "resolution"):
            if (geo[key] is None) != (fgeo[key] is None) or (geo[key] is not None and not _same(geo[key], fgeo[key])):
                raise EloInputError(
                    f"{args.flat}: flat-plate {key} {fgeo[key]} differs from the object's {geo[key]}; "
                    "record both with one geometry"
                )
    if geo["resolution"] is not None and tuple(geo["resolution"]) != (shape[1], shape[0]):
        raise EloInputError(
            f"{source}: header resolution {list(geo['resolution'])} (W, H) does not match the image "
            f"shape {shape[1]}x{shape[0]}"
        )
    kw = dict(min_corrected=MIN_CORRECTED if args.min_corrected is None else args.min_corrected,
              min_sum=MIN_SUM if args.min_sum is None else args.min_sum,
              min_denominator=MIN_DENOMINATOR if args.min_denominator is None else args.min_denominator)
    res = surface_gradient(images, flats, geo["field_mm"], geo["d_h"], geo["d_w"], **kw)

    sources = {"object": args.object or {n: getattr(args, n) for n in DETECTOR_NAMES},
               "flat": args.flat or {n: getattr(args, f"flat_{n}") for n in DETECTOR_NAMES}}
    write_gradient(out, res, geo["field_mm"], geo["d_h"], geo["d_w"], thresholds=kw, stsa_corrected=not args.no_flat,
                   event=args.event, sources=sources, header=header, overwrite=args.overwrite)
    print(f"wrote {out}: {shape[1]}x{shape[0]} px, field {geo['field_mm'][0]:g}x{geo['field_mm'][1]:g} mm, "
          f"d_h={geo['d_h']:g} mm, d_w={geo['d_w']:g} mm, {100 * res.mask.mean():.2f} % masked")
    _report_mask(res)
    if args.preview:
        preview_gradient(res.dzdx, res.dzdy, geo["field_mm"], Path(args.preview), mask=res.mask,
                         overwrite=args.overwrite)
        print(f"wrote {args.preview}")
    return 0
