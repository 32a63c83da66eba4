"""``elo-mitsuba new-scene``: a copy of a shipped scene to edit, working from any folder."""

from __future__ import annotations

import argparse

DESCRIPTION = """\
Write NAME.xml, a copy of a shipped scene (default athene_flat) whose includes (detectors,
layouts, plates) and meshes are referenced by absolute path into the installed package, so that
it loads from any folder, with every -D parameter of the original. A scene copied by hand out of
scenes_xml/ does not: its includes are relative to scenes_xml/.
"""

EPILOG = """\
examples:
  elo-mitsuba new-scene my_scene.xml                      # from athene_flat
  elo-mitsuba new-scene plate.xml --from flat_plate
  elo-mitsuba render my_scene.xml -o my.exr -D dh=250 --resolution 256
"""


def add_parser(subparsers):
    from ..scene_files import shipped_scenes

    p = subparsers.add_parser("new-scene", help="write a self-contained copy of a shipped scene to edit",
                              description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("output", metavar="NAME.xml", help="scene file to write")
    p.add_argument("--from", dest="source", default="athene_flat", metavar="SCENE",
                   help=f"shipped scene name ({', '.join(shipped_scenes())}) or an XML file (default athene_flat)")
    p.add_argument("--overwrite", action="store_true", help="replace NAME.xml if it exists")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from ..scene_files import write_scene_copy

    out = write_scene_copy(args.output, args.source, overwrite=args.overwrite)
    print(f"wrote {out} (from {args.source}); render it with: elo-mitsuba render {out} -o OUT.exr")
    return 0
