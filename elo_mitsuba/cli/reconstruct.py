"""``elo-mitsuba reconstruct``: gradient EXR -> height map by normal integration."""

from __future__ import annotations

import argparse

import numpy as np

from ..errors import EloInputError
from ._args import field_arg

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
          surfaces; 2.5-4x its time (15-25 s at 1500x1500 on 2 cores)
  auto    'masked' if any pixel is masked, else 'dct' (default; never 'robust')

Output by suffix (elo_mitsuba.heightmap): .exr (channels height and mask, 1 = no height; geometry
in the header), .tif (float32, the header as JSON in its ImageDescription, the pixel size in its
resolution tags), .gsf (Gwyddion Simple Field, metres) or .npy (float64, no header). Pixels
without a height hold NaN in TIFF/GSF/NPY, 0 with mask 1 in the EXR (use .exr, .tif or .gsf to
keep the figures below).

How far the result can be trusted is printed and stored in the header ("quality"):
  integrability residual  relative RMS misfit between the height map's gradient and the input
                          (0 = the gradient of a surface, ~0.7 = noise); warning above {res:g}
  masked fraction         share of pixels without height; warning above {mask:g}
  bowl / relief           peak-to-valley of the best-fitting quadric (tilt + bowl) and of the
                          rest; a small gradient bias integrates to a bowl, so a bowl larger than
                          the relief is warned about: the height range is then not relief
"""

EPILOG = """\
examples:
  elo-mitsuba reconstruct grad.exr -o height.exr --preview height.png
  elo-mitsuba reconstruct grad.exr -o height.npy --method dct
  elo-mitsuba reconstruct grad.exr -o height.exr --method robust     # a layer with part edges
"""


def add_parser(subparsers):
    from ..analysis.integrate import MAX_INTEGRABILITY_RESIDUAL, MAX_MASKED_FRACTION, METHODS

    p = subparsers.add_parser(
        "reconstruct", help="gradient EXR -> height map (normal integration)",
        description=DESCRIPTION.format(res=MAX_INTEGRABILITY_RESIDUAL, mask=MAX_MASKED_FRACTION), epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("gradient", metavar="GRAD.exr", help="output of 'elo-mitsuba gradient'")
    p.add_argument("-o", "--output", required=True, metavar="HEIGHT.(exr|tif|gsf|npy)", help="height map to write")
    p.add_argument("--method", choices=("auto",) + METHODS, default="auto", help="integration solver (default auto)")
    p.add_argument("--field", type=field_arg, metavar="FX[,FY]", help="scan field in mm if the header lacks it")
    p.add_argument("--ignore-mask", action="store_true", help="treat every pixel as trusted")
    p.add_argument("--min-component", type=int, default=16, metavar="N",
                   help="masked and robust solvers: trusted regions with fewer pixels are dropped (default 16)")
    p.add_argument("--preview", metavar="PNG", help="also write a PNG of the height map")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    import sys
    from pathlib import Path

    from ..files import check_output

    # the arguments first: a rejected one costs no import of the analysis (scipy, matplotlib)
    from ..heightmap import HEIGHT_SUFFIXES, write_height

    out = check_output(args.output, HEIGHT_SUFFIXES, overwrite=args.overwrite)
    if args.preview:
        check_output(args.preview, (".png",), overwrite=args.overwrite, what="preview")
    if args.min_component < 1:
        raise EloInputError(f"--min-component {args.min_component}: must be >= 1")
    if not Path(args.gradient).is_file():
        raise EloInputError(f"{args.gradient}: no such file")

    from ..analysis.chain import heights
    from ..analysis.io import read_gradient
    from ..analysis.plots import preview_height
    from ..schema import PROJECTION, WORK_DISTANCE

    grad = read_gradient(args.gradient, field_mm=args.field, use_mask=not args.ignore_mask)
    field, meta = grad["field_mm"], grad["metadata"]
    rec = heights(grad["dzdx"], grad["dzdy"], field, mask=grad["mask"], method=args.method,
                  projection=meta.get(PROJECTION), work_distance_mm=meta.get(WORK_DISTANCE),
                  min_component_size=args.min_component)
    height, mask_out, method, quality = rec["height"], rec["mask"], rec["method"], rec["quality"]
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
    write_height(out, height, mask_out, out_meta, overwrite=args.overwrite)
    valid = ~mask_out
    span = float(np.ptp(height[valid])) if valid.any() else 0.0
    print(f"wrote {out}: method {method}, {height.shape[1]}x{height.shape[0]} px, height range {span:.4g} mm, "
          f"{100 * mask_out.mean():.2f} % without height")
    print(f"quality: integrability residual {quality['integrability_residual']:.3f}, "
          f"{100 * quality['masked_fraction']:.2f} % masked, bowl {quality['bowl_mm']:.3g} mm, "
          f"relief {quality['relief_mm']:.3g} mm")
    for line in quality["warnings"]:
        print(f"elo-mitsuba: warning: {line}", file=sys.stderr)
    if args.preview:
        preview_height(height, field, args.preview, mask=mask_out if mask_out.any() else None,
                       title=f"Height map by normal integration ('{method}' solver)", overwrite=args.overwrite)
        print(f"wrote {args.preview}")
    return 0
