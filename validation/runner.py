"""Run the studies, time them, collect the rows and write the report."""

from __future__ import annotations

import importlib
import json
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from . import STUDIES
from .config import settings as _settings
from .report import StudyResult, rows_as_dicts, write_report

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The committed report: written only with --update-report (a full default run).
COMMITTED_OUTPUT = REPO_ROOT / "validation"
#: Default output folders, in the current folder (never the checkout unless run from there).
DEFAULT_OUTPUT = Path("validation-report")
QUICK_OUTPUT = Path("validation-quick")
PARTIAL_OUTPUT = Path("validation-partial")


class Renderer:
    """Loads scenes once (per scene + parameters) and renders them, counting samples and time."""

    def __init__(self, log):
        self._scenes = {}
        self.log = log
        self.samples = 0.0
        self.seconds = 0.0

    def scene(self, scene, **params):
        import elo_mitsuba as em

        key = (str(scene), tuple(sorted((k, str(v)) for k, v in params.items())))
        if key not in self._scenes:
            self._scenes[key] = em.load_scene(scene, **params)
        return self._scenes[key]

    def release(self) -> None:
        """Drop the loaded scenes: every scene alive joins the virtual calls that each render's kernel
        traces, so another study's scenes would make this one's kernels larger and compile anew."""
        import gc

        self._scenes.clear()
        gc.collect()

    def render(self, scene, *, spp, events=1, seed=0, detector_samples=None, options=None, **params):
        """Render a shipped scene (name or XML path) with scene parameters ``params``.

        ``detector_samples`` (points sampled on each detector per event) and ``options`` (other
        attributes of the ``elo`` integrator, e.g. ``detector_sampling``) are integrator properties
        that the shipped scenes do not expose as parameters; they are set on the loaded integrator
        for this render only. An option the integrator does not have raises AttributeError.
        """
        s = self.scene(scene, **params)
        integ = s.integrator
        opts = dict(options or {})
        if detector_samples is not None:
            opts["detector_samples"] = int(detector_samples)
        saved = integ.options
        t0 = time.perf_counter()
        try:
            s.configure(**opts)
            result = s.render(spp=int(spp), events=int(events), seed=int(seed), progress=False)
        finally:
            integ.configure(saved)
        dt = time.perf_counter() - t0
        res = result.metadata["resolution"]
        n = float(res[0] * res[1] * int(spp))
        self.samples += n
        self.seconds += dt
        return result


@dataclass
class Context:
    quick: bool
    out_dir: Path
    fig_dir: Path
    tmp_dir: Path
    settings: dict
    log: object
    renderer: Renderer
    figures: bool = True
    shared: dict = field(default_factory=dict)  # results shared between studies

    def say(self, msg):
        if self.log:
            self.log(msg)


@dataclass
class Validation:
    rows: list
    studies: list
    report_path: Path
    header: dict


def environment_info(quick: bool, mode_cmd: str) -> dict:
    """Date, commit and machine for the report header (read-only git only)."""
    from elo_mitsuba.provenance import machine, software, source_state, utc_now

    m, sw, src = machine(), software(), source_state(REPO_ROOT)
    load = ", ".join(f"{v:.1f}" for v in m["load"]) if m["load"] else "?"
    mem = f"{m['mem_gib']:.0f} GiB" if m["mem_gib"] else ""
    return {
        "Date (UTC)": utc_now().removesuffix(" UTC"),
        "Commit": f"`{src['commit']}` (working tree: {src['state']})",
        "Machine": f"{m['system']}, {m['cpu']}, {m['cores']} cores, {mem} "
                   f"(load average at start {load}; shared with other jobs)",
        "Software": f"elo-mitsuba {sw['elo_mitsuba']}, Mitsuba {sw['mitsuba']} ({sw['variant']}), "
                    f"Dr.Jit {sw['drjit']}, LLVM {sw['llvm']}, Python {sw['python']}, numpy {sw['numpy']}",
        "Mode": ("quick (`--quick`: tiny resolutions, for CI; numbers are noisy)" if quick
                 else "default settings"),
        "Command": f"`{mode_cmd}`",
    }


def check_outputs(out_dir: Path, json_path=None, overwrite: bool = False) -> None:
    """Refuse, before any study runs, an output folder that is a file (or under one), an existing
    report without ``overwrite``, and a bad ``--json`` path (one line, EloInputError)."""
    from elo_mitsuba.errors import EloInputError
    from elo_mitsuba.files import check_output, check_writable_folder

    for folder in (out_dir, *out_dir.parents):
        if folder.exists() and not folder.is_dir():
            raise EloInputError(f"--output-dir {out_dir}: {folder} is a file, not a folder")
    # the folder, or the nearest one that exists (the rest is created), must take new files
    check_writable_folder(next(f for f in (out_dir, *out_dir.parents) if f.exists()), f"--output-dir {out_dir}")
    if (out_dir / "REPORT.md").exists() and not overwrite:
        raise EloInputError(f"--output-dir {out_dir} holds a REPORT.md already; pass --overwrite to replace it "
                            "(or choose another --output-dir)")
    if json_path is not None:
        check_output(json_path, (".json",), overwrite=overwrite, what="--json")


def run_validation(quick=False, output_dir=None, only=None, log=print, json_path=None, figures=True,
                   overwrite=False):
    t_start = time.perf_counter()
    # only --update-report (output_dir=COMMITTED_OUTPUT) writes validation/REPORT.md, the committed report
    if output_dir is not None:
        out_dir = Path(output_dir)
    else:
        out_dir = QUICK_OUTPUT if quick else (PARTIAL_OUTPUT if only else DEFAULT_OUTPUT)
    names = list(STUDIES) if not only else [n for n in STUDIES if n in set(only)]
    unknown = set(only or ()) - set(STUDIES)
    if unknown:
        raise ValueError(f"unknown studies {sorted(unknown)}; choose from {', '.join(STUDIES)}")
    check_outputs(out_dir, json_path, overwrite=overwrite or out_dir.resolve() == COMMITTED_OUTPUT.resolve())
    fig_dir = out_dir / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)

    import elo_mitsuba

    elo_mitsuba.ensure_variant()
    cmd = "python -m validation" + (" --quick" if quick else "")
    if only:
        cmd += " --only " + " ".join(names)
    header = {"command": cmd, "info": environment_info(quick, cmd)}
    tmp = Path(tempfile.mkdtemp(prefix="elo-validation-"))
    renderer = Renderer(log)
    ctx = Context(quick=quick, out_dir=out_dir, fig_dir=fig_dir, tmp_dir=tmp,
                  settings=_settings(quick), log=log, renderer=renderer, figures=figures)
    studies = []
    try:
        for name in names:
            module = importlib.import_module(f"{__package__}.study_{name}")
            ctx.say(f"[validation] {name}: {module.TITLE} ...")
            s0, r0, t0 = renderer.samples, renderer.seconds, time.perf_counter()
            result: StudyResult = module.run(ctx)
            renderer.release()
            result.seconds = time.perf_counter() - t0
            result.samples = renderer.samples - s0
            result.render_seconds = renderer.seconds - r0
            for row in result.rows:
                if row.verdict != "agrees" and not row.why.strip():
                    row.why = ("criterion not met at these settings"
                               + (" (quick mode: resolution and Monte Carlo noise limit it; see the default run)"
                                  if quick else ""))
            studies.append(result)
            ctx.say(f"[validation] {name}: {len(result.rows)} rows in {result.seconds:.1f} s "
                    f"({', '.join(r.verdict for r in result.rows)})")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    # remove figures of earlier runs that this run did not produce (full runs only)
    if not only:
        produced = {Path(f.path).name for s in studies for f in s.figures}
        for old in fig_dir.glob("*.png"):
            if old.name not in produced:
                old.unlink()
    rows = [r for s in studies for r in s.rows]
    header["total_seconds"] = time.perf_counter() - t_start
    header["info"]["Run time"] = (f"{header['total_seconds']:.0f} s wall in total, "
                                  f"{renderer.seconds:.0f} s of it rendering "
                                  f"({renderer.samples / 1e6:.0f} M samples)")
    report_path = write_report(out_dir / "REPORT.md", studies, header, rows)
    if json_path is not None:
        Path(json_path).write_text(json.dumps({
            "header": header, "rows": rows_as_dicts(rows),
            "studies": [{"name": s.name, "seconds": s.seconds, "figures": [str(f.path) for f in s.figures]}
                        for s in studies]}, indent=1, default=str))
    ctx.say(f"[validation] wrote {report_path} ({len(rows)} rows, {header['total_seconds']:.0f} s)")
    return Validation(rows, studies, report_path, header)


def main(argv=None) -> int:
    from elo_mitsuba.cli._args import OneLineParser  # a usage error is one line, not the usage

    parser = OneLineParser(
        prog="python -m validation",
        description="Reproduce the checkable claims of Renner et al. 2023 with elo-mitsuba: figures "
                    "(PNG) and REPORT.md with the paper's number beside ours for every claim.")
    add_arguments(parser)
    args = parser.parse_args(argv)
    return run_from_args(args)


def add_arguments(parser):
    parser.add_argument("--quick", action="store_true",
                        help="tiny resolutions (about 40 s on 2 cores; for CI). Default: the full settings "
                             "(about 4-7 min on 2 cores)")
    parser.add_argument("-o", "--output-dir", dest="output_dir", metavar="DIR", default=None,
                        help="where REPORT.md and figures/ go (default, in the current folder: validation-report/, "
                             "validation-quick/ with --quick, validation-partial/ with --only)")
    parser.add_argument("--update-report", action="store_true",
                        help="write the committed validation/REPORT.md and figures of the checkout (full default run)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing REPORT.md / --json file")
    parser.add_argument("--only", nargs="+", metavar="STUDY", choices=STUDIES, default=None,
                        help=f"run only these studies ({', '.join(STUDIES)})")
    parser.add_argument("--json", metavar="FILE", default=None, help="also write the rows as JSON")
    parser.add_argument("--no-figures", action="store_true", help="numbers only, no PNG figures")
    parser.add_argument("--list", action="store_true", help="list the studies and exit")
    return parser


def run_from_args(args) -> int:
    if args.list:
        for name in STUDIES:
            module = importlib.import_module(f"{__package__}.study_{name}")
            print(f"{name:12s} {module.TITLE}")
        return 0
    output_dir = args.output_dir
    if args.update_report:
        if args.output_dir or args.quick or args.only or args.no_figures:
            from elo_mitsuba.errors import EloInputError

            raise EloInputError("--update-report rewrites validation/REPORT.md from the full default run: "
                                "no --output-dir, --quick, --only or --no-figures")
        output_dir = COMMITTED_OUTPUT
    result = run_validation(quick=args.quick, output_dir=output_dir, only=args.only,
                            json_path=args.json, figures=not args.no_figures, overwrite=args.overwrite)
    bad = [r.id for r in result.rows if r.verdict == "disagrees"]
    print(f"{len(result.rows)} claims: " + ", ".join(
        f"{sum(r.verdict == v for r in result.rows)} {v}" for v in ("agrees", "agrees approx.", "partly", "disagrees"))
        + (f" (disagreeing rows: {', '.join(bad)}; each says why)" if bad else ""))
    print(f"report: {result.report_path}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
