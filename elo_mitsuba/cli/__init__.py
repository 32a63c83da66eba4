"""The ``elo-mitsuba`` command line: a thin layer over the Python API.

Each sub-command lives in its own module of this package, which provides
``add_parser(subparsers)`` (returning the parser, with ``set_defaults(run=...)``) and does its
work through the library. User errors (:class:`~elo_mitsuba.errors.EloError`) are printed as one
line ``elo-mitsuba: error: ...`` with exit status 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from ..errors import EloError
from . import checkout
from ._args import OneLineParser

#: Sub-command modules, in the order ``--help`` lists them.
COMMANDS = (
    "render",
    "mesh",
    "gradient",
    "calibrate",
    "reconstruct",
    "invert",
    "reflectance_map",
    "sweep",
    "sweep_plot",
    "optimize",
    "new_scene",
)

DESCRIPTION = """\
Simulate electron-optical (ELO) imaging in electron-beam powder bed fusion (PBF-EB) with Mitsuba 3,
after Renner et al. 2023 (J. Manuf. Mater. Process. 7, 87), and turn four detector images into
surface gradients and height maps. Lengths are millimetres; images are seen from above with +y up
(columns run towards +x, row 0 is the +y edge of the scan field).
"""

EPILOG = """\
examples:
  elo-mitsuba render flat_plate -o flat.exr                 # a shipped scene, by name
  elo-mitsuba render scenes_xml/athene_flat.xml -o a.exr --events 2 --spp 64 -D dh=250
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad.exr
  elo-mitsuba calibrate flat.exr --dh 272 --dw 127 -o CALIB.json
  elo-mitsuba reconstruct grad.exr -o height.npy
  elo-mitsuba invert --flat flat.exr melt.exr -o height.exr
  elo-mitsuba sweep examples/sweep_minimal.toml -o sweep.zarr --workers 2
  elo-mitsuba optimize examples/optimize_athene.toml -o front.zarr --plot front.png

Run 'elo-mitsuba COMMAND --help' for each command's options.
"""


_Parser = OneLineParser  # usage errors as one line (what is wrong, and where to look), exit status 2


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The whole parser, or with ``only`` (a module of :data:`COMMANDS`) just that sub-command's:
    the others' parsers import what their help needs (scipy for 'reconstruct'), which a
    'render' need not pay for."""
    parser = _Parser(
        prog="elo-mitsuba",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from .._version import __version__

    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(title="commands", metavar="COMMAND")
    for name in COMMANDS:
        if only is None or name == only:
            importlib.import_module(f"{__name__}.{name}").add_parser(sub)
    if only is None:
        checkout.add_parsers(sub)
    parser.commands = sub.choices  # a sub-command's own parser names its own --help in an error
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in checkout.COMMANDS:  # validation/benchmarks parse their own options
        try:
            return checkout.run(argv[0], argv[1:])
        except EloError as exc:
            print(f"elo-mitsuba: error: {exc}", file=sys.stderr)
            return 2
    wanted = argv[0].replace("-", "_") if argv else None
    parser = build_parser(only=wanted if wanted in COMMANDS else None)
    args, extra = parser.parse_known_args(argv)
    if extra:  # argparse reports a sub-command's stray arguments from the top parser
        parser.commands.get(argv[0], parser).error(f"unrecognized arguments: {' '.join(extra)}")
    if not hasattr(args, "run"):
        parser.print_help()
        return 2
    command = parser.commands.get(argv[0], parser)
    for action in command._actions:
        value = getattr(args, action.dest, None)
        # an empty string (an unset shell variable) would be taken as 'not given': the option silently unapplied
        if action.option_strings and (value == "" or (isinstance(value, list) and "" in value)):
            command.error(f"{action.option_strings[-1]} '': empty; give a value")
    try:
        result = args.run(args)
    except EloError as exc:
        print(f"elo-mitsuba: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("elo-mitsuba: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader left (`... | head -1`): stop quietly, as a command SIGPIPE ends
        _quiet_stdout()
        return 141
    return int(result or 0)


def _quiet_stdout() -> None:
    """Point stdout at /dev/null, so that Python's flush at exit does not fail on the closed pipe."""
    import os

    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
