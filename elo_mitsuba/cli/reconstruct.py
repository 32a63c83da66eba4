"""``elo-mitsuba reconstruct``: gradient EXR -> height map by normal integration."""

from __future__ import annotations

import argparse

import numpy as np

from ..errors import EloInputError
from ._args import field_arg

#: Trusted regions with fewer pixels get no height (masked and robust solvers): their own zero
#: mean says nothing of where they lie.
MIN_COMPONENT = 16

DESCRIPTION = """\
Integrate a surface gradient (the EXR written by 'elo-mitsuba gradient': channels dzdx, dzdy and
mask, geometry in the header) into a height map Z(x, y) in mm, known up to a constant (zero mean).

Solvers (Queau, Durou & Aujol 2018 survey the field):
  dct     least squares over all pixel pairs, Neumann boundary, exact via the DCT (fast; masked
          pixels count as flat)
  fft     Frankot-Chellappa on the mirrored field (fast; masked pixels count as flat)
  masked  the least-squares functional of 'dct' restricted to trusted pixels, sparse direct solve;
          each connected trusted region gets its own zero-mean constant (their relative heights
          are unknown); needs memory for large images
  robust  discontinuity-preserving (Queau, Durou & Aujol 2018, "Variational methods for normal
          integration": the Cauchy estimator, iteratively reweighted 'masked' solves): a pair
          of pixels whose gradient disagrees with the rest is given up instead of being spread
          over the relief around it. Use it for surfaces with cliffs (parts beside powder,
          craters): one wall of a step saying less than the others no longer tilts the flats
          beside it. It cannot add height that no wall's gradient holds: a cliff blurred or
          shadowed on every side stays short, and a part cut off by masked pixels all round
          gets its own zero mean, as with 'masked'. Its integrability residual runs above least
          squares' (the misfit is gathered on the pairs it gives up). Equals 'masked' on smooth
          surfaces; 2.5-4x its time (15-25 s at 1500x1500 on 2 cores, up to 85 s where it
          runs to its 30 reweighted solves)
  auto    'masked' if any pixel is masked, else 'dct' (default; never 'robust')

Output by suffix (elo_mitsuba.heightmap): .exr (channels height and mask, 1 = no height; geometry
in the header), .tif (float32, the header as JSON in its ImageDescription, the pixel size in its
resolution tags), .gsf (Gwyddion Simple Field, metres) or .npy (float64, no header). Pixels
without a height hold NaN in TIFF/GSF/NPY, 0 with mask 1 in the EXR (use .exr, .tif or .gsf to
keep the figures below). Pixels that are not square (--field FX,FY with FX/W != FY/H) can only be
written as .npy: the other formats record one pixel size.

Refused before integrating: a mask channel with values other than 0 and 1, and, for a perspective
scan, slopes that face away from the beam (1 + S.g/wd <= 0 at scan point S, work distance wd: the
surface there would fall away from the axis by more than wd/r at r off axis; no beam lands on it).

How far the result can be trusted is printed and stored in the header ("quality"):
  integrability residual  relative RMS misfit between the height map's gradient and the input
                          (0 = the gradient of a surface, ~0.7 = noise); warning above {res:g}
  masked fraction         share of pixels without height; warning above {mask:g}
  regions                 connected regions of measured pixels; each has its own zero mean (no
                          slope connects them): warning when more than {detached:g} of the measured
                          pixels lie outside the largest
  bowl / relief           peak-to-valley of the best-fitting quadric (tilt + bowl) and of the
                          rest; a small gradient bias integrates to a bowl, so a bowl larger than
                          the relief is warned about: the height range is then not relief
  every other pixel       RMS difference between heights integrated from every other pixel (two
                          diagonal sub-lattices, the same solver) and these, a test of whether the
                          scan resolves the relief: the map's own error from sampling measured
                          0.2-0.3x this figure where the relief is smooth between pixel centres
                          (melt plate, rough layer) and 0.8-1.4x where it bends between them
                          (ridges, cliffs); warning above {half:g} x the relief's RMS. The
                          corrugated sheet (1.4 mm period, 45-degree flanks) is such a case: at
                          256 x 256 0.42 mm, its heights off by 0.48 mm RMS (truth: 0.20 mm RMS)
  relief / work distance  perspective scans: a height range above {wd:g} x the work distance is
                          warned about (the conversion of slopes to the scan grid assumes less)
"""

EPILOG = """\
examples:
  elo-mitsuba reconstruct grad.exr -o height.exr --preview height.png
  elo-mitsuba reconstruct grad.exr -o height.npy --method dct
  elo-mitsuba reconstruct grad.exr -o height.exr --method robust     # a layer with part edges
"""


def add_parser(subparsers):
    from ..analysis.integrate import (
        MAX_DETACHED_FRACTION,
        MAX_HALF_SAMPLING,
        MAX_INTEGRABILITY_RESIDUAL,
        MAX_MASKED_FRACTION,
        MAX_RELIEF_OVER_WORK_DISTANCE,
        METHODS,
    )

    p = subparsers.add_parser(
        "reconstruct", help="gradient EXR -> height map (normal integration)",
        description=DESCRIPTION.format(res=MAX_INTEGRABILITY_RESIDUAL, mask=MAX_MASKED_FRACTION, half=MAX_HALF_SAMPLING,
                                       detached=MAX_DETACHED_FRACTION,
                                       wd=MAX_RELIEF_OVER_WORK_DISTANCE), epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("gradient", metavar="GRAD.exr", help="output of 'elo-mitsuba gradient'")
    p.add_argument("-o", "--output", required=True, metavar="HEIGHT.(exr|tif|gsf|npy)", help="height map to write")
    p.add_argument("--method", choices=("auto",) + METHODS, default="auto", help="integration solver (default auto)")
    p.add_argument("--field", type=field_arg, metavar="FX[,FY]", help="scan field in mm if the header lacks it")
    p.add_argument("--ignore-mask", action="store_true",
                   help="treat every pixel as trusted: masked pixels enter with the slopes the EXR holds there "
                        "(0 in a gradient written by 'elo-mitsuba gradient', so they pull the heights flat)")
    p.add_argument("--min-component", type=int, default=None, metavar="N",
                   help=f"masked and robust solvers (and auto): trusted regions with fewer pixels are dropped "
                        f"(default {MIN_COMPONENT})")
    p.add_argument("--preview", metavar="PNG", help="also write a PNG of the height map")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    import sys

    from ..arguments import input_file
    from ..files import check_output

    # the arguments first: a rejected one costs no import of the analysis (scipy, matplotlib)
    from ..heightmap import HEIGHT_SUFFIXES, write_height

    out = check_output(args.output, HEIGHT_SUFFIXES, overwrite=args.overwrite, inputs=[args.gradient])
    if args.preview:
        check_output(args.preview, (".png",), overwrite=args.overwrite, what="preview", inputs=[args.gradient])
    if args.min_component is not None and args.min_component < 1:
        raise EloInputError(f"--min-component {args.min_component}: must be >= 1")
    if args.min_component is not None and args.method in ("dct", "fft"):  # it would be taken and not applied
        raise EloInputError(f"--min-component applies to --method masked, robust or auto; --method {args.method} "
                            "integrates every pixel (masked ones as flat)")
    min_component = MIN_COMPONENT if args.min_component is None else args.min_component
    input_file(args.gradient)

    from ..analysis.chain import heights
    from ..analysis.integrate import check_scan_grid_slopes, check_trusted_regions, perspective_relief_warning
    from ..analysis.io import read_gradient
    from ..analysis.plots import preview_height
    from ..schema import PROJECTION, WORK_DISTANCE

    grad = read_gradient(args.gradient, field_mm=args.field, use_mask=not args.ignore_mask)
    field, meta = grad["field_mm"], grad["metadata"]
    dzdx, dzdy, mask = grad["dzdx"], grad["dzdy"], grad["mask"]
    # checked before any work: pixels the output can hold, slopes a perspective beam can land on
    square = _check_pixels(args, out, field, dzdx.shape)
    # dct and fft give every pixel a height; the others none where all is masked or regions are small
    check_trusted_regions(dzdx, dzdy, mask, None if args.method in ("dct", "fft") else min_component,
                          source=str(args.gradient))
    perspective = meta.get(PROJECTION) == "perspective"
    if perspective:
        wd = meta.get(WORK_DISTANCE)
        if isinstance(wd, bool) or not isinstance(wd, (int, float)) or not (np.isfinite(wd) and wd > 0):
            raise EloInputError(f"{args.gradient}: header projection 'perspective' with work_distance_mm {wd!r}; "
                                "a perspective scan needs the pivot height, a finite number > 0 (mm)")
        check_scan_grid_slopes(dzdx, dzdy, field, meta.get(WORK_DISTANCE), mask, source=str(args.gradient))
        if mask is not None:  # untrusted: their values enter nothing (0, as 'gradient' writes them)
            dzdx, dzdy = np.where(mask, np.float32(0), dzdx), np.where(mask, np.float32(0), dzdy)
    from ..progress import PROGRESS_AFTER_S

    def progress(step):  # robust's reweighted solves: about 2 s each at 1500²; short runs stay quiet
        if step["seconds"] >= PROGRESS_AFTER_S:
            print(f"  robust: reweighted solve {step['iteration']}/{step['iterations']} at most, Cauchy energy "
                  f"{step['energy']:.6g}, {step['seconds']:.1f} s", file=sys.stderr, flush=True)

    rec = heights(dzdx, dzdy, field, mask=mask, method=args.method,
                  projection=meta.get(PROJECTION), work_distance_mm=meta.get(WORK_DISTANCE),
                  min_component_size=min_component, progress=progress)
    height, mask_out, method, quality = rec["height"], rec["mask"], rec["method"], rec["quality"]
    if perspective:
        line = perspective_relief_warning(height, mask_out, meta.get(WORK_DISTANCE))
        if line:
            quality["warnings"].append(line)
            quality["flags"].append("relief large against the work distance")
    out_meta = {
        "quantity": "height map (relative, zero mean)",
        "units": "mm",
        "field_mm": list(field),
        "resolution": [height.shape[1], height.shape[0]],
        "method": method,
        "mask": "1 = no height measured, 0 = measured",
        "source": str(args.gradient),
        "quality": quality,
        "grid": rec["grid"],
    }
    for key in ("d_h_mm", "d_w_mm", "material", "projection", "work_distance_mm"):
        if key in meta:
            out_meta[key] = meta[key]
    # a .npy records no pixel size, so it may hold non-square pixels (the solvers take dx and dy)
    write_height(out, height, mask_out, out_meta if square else {k: v for k, v in out_meta.items() if k != "field_mm"},
                 overwrite=args.overwrite)
    valid = ~mask_out
    span = float(np.ptp(height[valid])) if valid.any() else 0.0
    print(f"wrote {out}: method {method}, {height.shape[1]}x{height.shape[0]} px, height range {span:.4g} mm, "
          f"{100 * mask_out.mean():.2f} % without height")
    print(f"quality: integrability residual {quality['integrability_residual']:.3f}, "
          f"{100 * quality['masked_fraction']:.2f} % masked"
          + (f" in {quality['regions']} regions ({100 * quality['detached_fraction']:.1f} % outside the largest)"
             if quality["regions"] > 1 else "")
          + f", bowl {quality['bowl_mm']:.3g} mm, "
          f"relief {quality['relief_mm']:.3g} mm (RMS {quality['relief_rms_mm']:.3g} mm)"
          + ("" if quality["half_sampling_mm"] is None else
             f", every other pixel differs by {quality['half_sampling_mm']:.3g} mm RMS"))
    for line in quality["warnings"]:
        print(f"elo-mitsuba: warning: {line}", file=sys.stderr)
    if args.preview:
        preview_height(height, field, args.preview, mask=mask_out if mask_out.any() else None,
                       title=f"Height map by normal integration ('{method}' solver)", overwrite=args.overwrite,
                       warning="; ".join(quality["flags"]) or None)
        print(f"wrote {args.preview}")
    return 0


def _check_pixels(args, out, field, shape) -> bool:
    """Whether the pixels are square; non-square ones only for a .npy output, which records no
    pixel size (EXR, TIFF and GSF height maps record one square pitch)."""
    import math

    fx, fy = field
    dx, dy = fx / shape[1], fy / shape[0]
    if math.isclose(dx, dy, rel_tol=1e-6):
        return True
    if out.suffix.lower() != ".npy":
        given = (f"--field {args.field[0]:g},{args.field[1]:g}" if args.field
                 else f"{args.gradient}: header field_mm {fx:g} x {fy:g} mm")
        raise EloInputError(f"{given} over {shape[1]}x{shape[0]} px gives pixels of {dx:g} x {dy:g} mm; "
                            f"a {out.suffix} height map records one square pixel size: write a .npy (no pixel "
                            f"size), or give a field with square pixels (e.g. --field {fx:g},{fx * shape[0] / shape[1]:g})")
    return False
