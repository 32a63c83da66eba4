"""Argument types shared by the sub-commands: each rejects bad text with a one-line reason.

The one home of the command line's numeric argument types; range checks that depend on other
arguments belong to the library.
"""

from __future__ import annotations

import argparse
import math

from ..constants import MAX_SEED
from ..schema import FWHM_RANGE, LENGTH_RANGE, is_fwhm, is_length


#: Namespace attribute in which :class:`_StoreOnce` notes the options given while one parser parses;
#: removed before :meth:`OneLineParser.parse_known_args` returns.
_GIVEN = "_elo_options_given"


def _shown(value) -> str:
    """An option's parsed value as the user wrote it, near enough (``80,80`` for a field, ``0.5``)."""
    if isinstance(value, (tuple, list)):
        return ",".join(_shown(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


class _StoreOnce(argparse._StoreAction):
    """argparse's ``store`` for an option that takes one value: given twice with different values
    it is refused in one line (argparse kept the last one silently: ``--resolution 16 --resolution
    32`` rendered 32^2). The same value twice is harmless and taken, as for a repeated ``-D``.
    Options meant to repeat use ``action="append"`` (``--flat``, ``-D``) and are not affected."""

    def __call__(self, parser, namespace, values, option_string=None):
        if option_string is not None:  # positionals are consumed once by argparse itself
            given = vars(namespace).setdefault(_GIVEN, {})
            if self.dest in given and given[self.dest][1] != values:
                first, old = given[self.dest]
                parser.error(f"{first} {_shown(old)} and {option_string} {_shown(values)}: the option is given "
                             "twice with different values; give it once")
            given.setdefault(self.dest, (option_string, values))
        super().__call__(parser, namespace, values, option_string)


class OneLineParser(argparse.ArgumentParser):
    """Usage errors as one line (what is wrong, and where to look), exit status 2, no usage dump;
    an option of one value given twice with different values is such an error (:class:`_StoreOnce`,
    registered here as the default action, so every sub-command's parser and argument group has it)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.register("action", None, _StoreOnce)
        self.register("action", "store", _StoreOnce)

    def parse_known_args(self, args=None, namespace=None):
        parsed, extra = super().parse_known_args(args, namespace)
        if hasattr(parsed, _GIVEN):  # bookkeeping only: not an option of the command
            delattr(parsed, _GIVEN)
        return parsed, extra

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def number(text: str) -> float:
    """Any finite or infinite float (range checks belong to the library)."""
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def positive_float(text: str) -> float:
    """A finite number > 0 (a length in mm, a noise level, seconds)."""
    v = number(text)
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: must be finite and > 0")
    return v


def length_mm(text: str) -> float:
    """A length in mm that a header may hold (:func:`~elo_mitsuba.schema.is_length`): the geometry
    options override a header's, and a field of 1e300 mm reached the calibration's fit."""
    v = number(text)
    if not is_length(v):
        raise argparse.ArgumentTypeError(f"{text!r}: must be a length of {LENGTH_RANGE}")
    return v


def field_arg(text: str) -> tuple[float, float]:
    """``--field FX[,FY]``: the scan field in mm (one value: a square field), each a :func:`length_mm`."""
    try:
        vals = [float(v) for v in text.replace("x", ",").split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give FX or FX,FY in mm, e.g. 80 or 80,60") from None
    if len(vals) not in (1, 2) or not all(is_length(v) for v in vals):
        raise argparse.ArgumentTypeError(f"{text!r}: give one or two lengths of {LENGTH_RANGE}, e.g. 80 or 80,60")
    return (vals[0], vals[-1])


def noise_level(text: str) -> float:
    """``--noise``: a noise level of the corrected images (:func:`~elo_mitsuba.analysis.noise.check_noise`)."""
    from ..analysis.noise import NOISE_RANGE, is_noise_level

    v = number(text)
    if not is_noise_level(v):
        raise argparse.ArgumentTypeError(f"{text!r}: must be {NOISE_RANGE}, e.g. 0.01)")
    return v


def fwhm_arg(text: str) -> float:
    """``--fwhm``: a beam profile's FWHM in mm (:func:`~elo_mitsuba.schema.is_fwhm`), as renders and headers take it."""
    v = number(text)
    if not is_fwhm(v):
        raise argparse.ArgumentTypeError(f"{text!r}: must be {FWHM_RANGE}")
    return v


def material_arg(text: str) -> str:
    """``--material``: not blank (an empty one fell back to the header's without a word); the
    library names an unknown preset or a bad composition."""
    if not text.strip():
        from ..physics.materials import PRESETS

        raise argparse.ArgumentTypeError(f"{text!r} is empty; give a preset ({', '.join(PRESETS)}) or a composition "
                                         "such as 'Ti:0.9,Al:0.06,V:0.04'")
    return text


def positive_int(text: str) -> int:
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be >= 1")
    return value


def non_negative_int(text: str) -> int:
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} must be >= 0")
    return value


def define(text: str) -> tuple[str, str]:
    """``NAME=VALUE`` of a scene parameter."""
    if "=" not in text or not text.split("=", 1)[0].strip():
        raise argparse.ArgumentTypeError(f"{text!r} is not NAME=VALUE (e.g. -D dh=250)")
    name, value = text.split("=", 1)
    if not value.strip():  # Mitsuba would read an empty length as a vector of the wrong size
        raise argparse.ArgumentTypeError(f"{text!r} gives {name.strip()} no value (e.g. -D {name.strip()}=250)")
    return name.strip(), value.strip()


def seed(text: str) -> int:
    """A sampler seed: 0 .. 2^32 - 1."""
    value = non_negative_int(text)
    if value > MAX_SEED:
        raise argparse.ArgumentTypeError(f"{value} is above {MAX_SEED} (seeds are 32-bit)")
    return value


def add_yes(parser) -> None:
    """``--yes``: run work estimated to take longer than budget.REFUSE_SECONDS (refused otherwise)."""
    from ..budget import REFUSE_SECONDS

    parser.add_argument("--yes", action="store_true",
                        help=f"run even when the estimate says it takes longer than {REFUSE_SECONDS / 3600:g} h "
                             "(refused otherwise as likely a mistyped number); memory beyond what is available "
                             "is refused regardless")


def add_scan_arguments(p):
    """The inputs of one scan (object and flat-plate images, geometry): shared by gradient and invert
    (:func:`scan_inputs` turns them into the keywords of :func:`~elo_mitsuba.analysis.chain.read_scan`)."""
    from ..constants import DETECTOR_NAMES

    p.add_argument("object", nargs="?", metavar="OBJECT.exr",
                   help="object images: EXR with channels right, left, back, front")
    src = p.add_argument_group("single-channel inputs (recorded machine images)")
    for n in DETECTOR_NAMES:
        src.add_argument(f"--{n}", metavar="FILE", help=f"{n} detector image (EXR/TIFF/NPY)")
    flat = p.add_argument_group("STSA correction (flat plate)")
    flat.add_argument("--flat", metavar="FLAT.exr", action="append",
                      help="flat-plate EXR with channels right, left, back, front; repeat it for several "
                           "recordings: their mean is used (the flat's noise falls as 1/sqrt(N))")
    for n in DETECTOR_NAMES:
        flat.add_argument(f"--flat-{n}", metavar="FILE", action="append",
                          help=f"flat-plate image of the {n} detector (repeatable, as --flat)")
    flat.add_argument("--no-flat", action="store_true",
                      help="the inputs are already STSA-corrected (skip the division)")
    geo = p.add_argument_group("geometry (for images without headers; --dh/--dw override a header's, "
                               "--field must agree with it)")
    geo.add_argument("--field", type=field_arg, metavar="FX[,FY]", help="scan field in mm, e.g. 80")
    geo.add_argument("--dh", type=length_mm, metavar="MM", help="detector height d_h in mm")
    geo.add_argument("--dw", type=length_mm, metavar="MM", help="detector distance d_w from the z-axis in mm")
    geo.add_argument("--radius", type=length_mm, metavar="MM",
                     help="detector disc radius (model method, without a header; default 25)")
    geo.add_argument("--wd", "--work-distance", dest="wd", type=length_mm, metavar="MM",
                     help="work distance: beam pivot height (model method, without a header; default 400)")
    geo.add_argument("--projection", choices=("perspective", "orthographic"),
                     help="beam from the pivot or parallel to -z (model method, without a header)")
    geo.add_argument("--material", type=material_arg, metavar="NAME",
                     help="surface material for the model (default: the header's, else Ti-6Al-4V)")
    geo.add_argument("--calibration", metavar="CALIB.json",
                     help="detector centres and normals from 'elo-mitsuba calibrate' (model method)")


def scan_inputs(args) -> dict:
    """The keywords of :func:`~elo_mitsuba.analysis.chain.read_scan` from :func:`add_scan_arguments`'s flags."""
    from ..constants import DETECTOR_NAMES

    return dict(object_exr=args.object, files={n: getattr(args, n) for n in DETECTOR_NAMES}, flat=args.flat or [],
                flat_files={n: getattr(args, f"flat_{n}") or [] for n in DETECTOR_NAMES}, no_flat=args.no_flat,
                event=args.event, field_mm=args.field, d_h=args.dh, d_w=args.dw, material=args.material)


def read_checked_scan(args, *, model_discs: bool):
    """:func:`~elo_mitsuba.analysis.chain.read_scan` of :func:`add_scan_arguments`'s flags, with the
    checks of what the flags say against each other and the headers ('gradient', 'invert'): a flat
    file repeated, a calibration file (read first: its one line before the images), one file for two
    detectors, ``--field`` against the headers, a ``--second-event`` render of another set-up."""
    from ..analysis import chain
    from ..analysis.io import check_distinct_scan_files, check_field, check_repeated_recordings, check_second_event
    from ..constants import DETECTOR_NAMES

    check_repeated_recordings(args.flat, {n: getattr(args, f"flat_{n}") for n in DETECTOR_NAMES})
    if args.calibration:
        from ..analysis.calibration import read_calibration

        read_calibration(args.calibration)
    inputs = scan_inputs(args)
    scan = chain.read_scan(**inputs, model_discs=model_discs)
    check_distinct_scan_files(inputs["files"], inputs["flat_files"])
    check_field(args.field, scan.header, scan.shape, scan.source)
    if getattr(args, "second_event", None):
        check_second_event(args.second_event, scan.header, scan.source, scan.shape, field_mm=args.field, d_h=args.dh,
                           d_w=args.dw)
    return scan


def scan_files(args) -> list:
    """Every file :func:`add_scan_arguments`'s flags name (for the check that no output replaces one)."""
    from ..constants import DETECTOR_NAMES

    files = [args.object, *(args.flat or []), args.calibration]
    for n in DETECTOR_NAMES:
        files += [getattr(args, n), *(getattr(args, f"flat_{n}") or [])]
    return [f for f in files if f]


def model_inputs(args) -> dict:
    """The keywords of :func:`~elo_mitsuba.analysis.chain.model_geometry` from :func:`add_scan_arguments`'s flags."""
    return dict(d_h=args.dh, d_w=args.dw, radius=args.radius, work_distance_mm=args.wd, projection=args.projection,
                material=args.material, calibration=args.calibration)
