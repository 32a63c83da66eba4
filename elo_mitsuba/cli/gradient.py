"""``elo-mitsuba gradient``: four detector images -> surface gradient (model fit or Eq. 26) + mask."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..errors import EloInputError
from ..schema import scattering_note
from ._args import add_scan_arguments, model_inputs, noise_level, read_checked_scan, scan_files

DESCRIPTION = """\
Compute the surface gradient dZ/dx, dZ/dy of the build surface from four detector images
(right +x, left -x, back +y, front -y):

  1. STSA correction (Renner et al. 2023, Sec. 2.1.4):  R^C = R / R_flat, ... (flat = plane plate)
  2. --method model (default): per pixel, the facet normal whose modelled corrected images (1st
     event, full g_BSE of Eq. 13, the real disc detectors, that pixel's beam direction) match the
     four measured ones best (least squares; 4 values, slope p, q and a common scale). Exact for
     the 1st event of a facet; Eq. 26 is biased by the specular lobe (tens of % on slopes of
     0.6, measured in validation/REPORT.md). Adds channels residual (RMS misfit, corrected units),
     dzdx_sigma, dzdy_sigma (one-sigma uncertainty from the noise level and the Jacobian) and
     scale; pixels the model cannot explain (shadowing, strong later events, mixed facets) are
     masked (mask_reason bit 32).
     --method eq26: the paper's closed form, M_x = (R^C - L^C)/(R^C + L^C) (Eq. 15) and
     -dZ/dx = M_x d_h / (d_w + x M_x + y M_y), -dZ/dy = M_y d_h / (d_w + x M_x + y M_y) (Eq. 26),
     exact for point detectors and Lambert's law.

Geometry (field, d_h, d_w) comes from the EXR headers written by 'elo-mitsuba render'
(d_h = detector centre z, d_w = centre distance from the z-axis; the four must agree); --dh,
--dw override it (--field must agree with it); --field, --dh, --dw are required for recorded
machine images given as four single-channel files (EXR/TIFF/NPY, same orientation: row 0 = +y
edge, columns towards +x).

Output EXR channels: dzdx, dzdy (mm/mm), Mx, My, sum_rl, sum_bf (Eq. 23, material contrast),
mask (1 = untrusted pixel: a detector masked or dark, a sum or the Eq. 26 denominator near zero,
the model's misfit, bad input; gradient 0 there) and mask_reason (bit field, see the header).
The header carries the geometry so that 'elo-mitsuba reconstruct' needs no flags.
Run time at 1500 x 1500 on 2 idle CPU cores, end to end: eq26 3 s, model 12 s (14-30 s under load).
"""

EPILOG = """\
examples:
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad.exr --preview grad.png
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad26.exr --method eq26      # the paper's Eq. 26
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad.exr --calibration CALIB.json
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad_e1.exr --event 1      # 1st event only
  elo-mitsuba gradient --flat flat1.exr --flat flat2.exr melt.exr -o grad.exr  # the flats' mean
  elo-mitsuba gradient --right R.tif --left L.tif --back B.tif --front F.tif \\
      --flat-right R0.tif --flat-left L0.tif --flat-back B0.tif --flat-front F0.tif \\
      --field 80 --dh 272 --dw 127 -o grad.exr
"""


def height_passes(text: str) -> int | None:
    """``--height-passes``: 1, 2, 3, or auto (None)."""
    if text.strip().lower() == "auto":
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n not in (1, 2, 3):
        raise argparse.ArgumentTypeError(f"{text!r}: choose 1, 2, 3 or auto")
    return n


def add_parser(subparsers):
    p = subparsers.add_parser(
        "gradient", help="four detector images -> surface gradient (model fit or Eq. 26) and mask",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_scan_arguments(p)
    p.add_argument("-o", "--output", required=True, metavar="GRAD.exr", help="gradient EXR to write")
    mod = p.add_argument_group("method")
    mod.add_argument("--method", choices=("model", "eq26"), default="model",
                     help="model: per-pixel fit of the 1st-event model (default); eq26: the paper's Eq. 26")
    mod.add_argument("--iterations", type=int, default=None, metavar="N",
                     help="Levenberg-Marquardt iterations of the model fit (default 10)")
    mod.add_argument("--noise", type=noise_level, default=None, metavar="SIGMA",
                     help="noise (std) of the corrected images for the uncertainty, 1e-9 to 1 (e.g. 0.01); default: estimated")
    mod.add_argument("--second-event", metavar="SIM_FLAT.exr",
                     help="a render of the flat plate in the chamber with --events >= 2: its share of later "
                          "events is taken out of the flat and the object images (the model is 1st-event only)")
    mod.add_argument("--height-passes", type=height_passes, default=None, metavar="N",
                     help="fits, each with the beam's landing points on the heights integrated from the one "
                          "before: 1, 2, 3, or auto (default: 2 where the first pass's relief exceeds 50 um RMS, "
                          "analysis.model_gradient.AUTO_RELIEF_MM, and the scan resolves it; with the landing "
                          "points at z = 0 heights come "
                          "out about 1.3 %% of the relief off, on the surface 0.5 %%)")
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
    from ..analysis import chain
    from ..analysis.io import write_gradient
    from ..analysis.plots import preview_gradient
    from ..files import check_output

    chain.check_gradient_settings(args.method, args.iterations, args.height_passes)
    if args.method == "eq26":
        for flag in ("calibration", "iterations", "noise", "radius", "wd", "projection", "material", "second_event"):
            if getattr(args, flag) is not None:
                raise EloInputError(f"--{flag.replace('_', '-')} applies to --method model only")
        if args.height_passes is not None:
            raise EloInputError("--height-passes applies to --method model only")
    elif args.min_denominator is not None:
        raise EloInputError("--min-denominator applies to --method eq26 only (the model has no denominator)")
    if args.event is not None and args.event < 1:  # it was reported as missing channels right.e0 ...
        raise EloInputError(f"--event {args.event}: must be >= 1 (the 1st event is 1)")
    for flag in ("min_corrected", "min_sum", "min_denominator"):
        value = getattr(args, flag)
        if value is not None and not np.isfinite(value):
            raise EloInputError(f"--{flag.replace('_', '-')} {value}: must be a finite number")
    read = scan_files(args)
    out = check_output(args.output, (".exr",), overwrite=args.overwrite, inputs=read)
    if args.preview:
        check_output(args.preview, (".png",), overwrite=args.overwrite, what="preview", inputs=read)
    scan = read_checked_scan(args, model_discs=args.method == "model")
    if scattering_note(scan.header, scan.source):  # images of another g_BSE than the models' (a lobe study)
        print(f"note: {scattering_note(scan.header, scan.source)}", file=sys.stderr)
    geo = scan.geo
    model = chain.model_geometry(scan, **model_inputs(args)) if args.method == "model" else None
    res, thresholds = chain.gradient(scan, method=args.method, geometry=model, iterations=args.iterations,
                                     noise=args.noise, second_event=args.second_event,
                                     height_passes=args.height_passes, min_corrected=args.min_corrected,
                                     min_sum=args.min_sum, min_denominator=args.min_denominator)
    sources = {"object": scan.object_files, "flat": scan.flat_provenance()}
    write_gradient(out, res, geo["field_mm"], geo["d_h"], geo["d_w"], thresholds=thresholds,
                   stsa_corrected=not args.no_flat, event=args.event, sources=sources, header=scan.header,
                   overwrite=args.overwrite, method=args.method, model_geometry=model, calibration=args.calibration)
    extra = ""
    if model is not None:
        passes = res.height_passes
        extra = (f", {passes} height pass{'es' if passes > 1 else ''}, noise {res.noise:.2g}, median uncertainty of dZ/dx "
                 f"{np.median(res.dzdx_sigma[~res.mask]) if (~res.mask).any() else float('nan'):.2g}")
    shape = scan.shape
    print(f"wrote {out}: {shape[1]}x{shape[0]} px, field {geo['field_mm'][0]:g}x{geo['field_mm'][1]:g} mm, "
          f"d_h={geo['d_h']:g} mm, d_w={geo['d_w']:g} mm, method {args.method}, {100 * res.mask.mean():.2f} % masked"
          + extra + scan.flat_note())
    noise_line = scan.noise_shares()[1]
    if noise_line:
        print(noise_line)
    _report_mask(res)
    if args.preview:
        title = "Surface gradient (model fit)" if args.method == "model" else "Surface gradient (Eq. 26)"
        preview_gradient(res.dzdx, res.dzdy, geo["field_mm"], Path(args.preview), mask=res.mask, title=title,
                         overwrite=args.overwrite)
        print(f"wrote {args.preview}")
    return 0
