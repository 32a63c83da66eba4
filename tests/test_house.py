"""The layering of the house: what may import what, and docs that point inside the repository."""

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHECKOUT_ONLY = ("validation", "benchmarks", "tests")


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def _sources(*folders):
    return sorted(p for f in folders for p in (ROOT / f).rglob("*.py"))


def test_the_package_imports_nothing_of_the_checkout():
    for path in _sources("elo_mitsuba", "plugins"):
        bad = {n for n in _imports(path) if n.split(".")[0] in CHECKOUT_ONLY + ("forward_scenes", "golden_cases")}
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


@pytest.mark.parametrize("folder", ["validation", "benchmarks"])
def test_validation_and_benchmarks_do_not_reach_into_tests(folder):
    for path in _sources(folder):
        text = path.read_text()
        bad = {n for n in _imports(path) if n.split(".")[0] == "tests" or n.startswith("test_")
               or n in ("forward_scenes", "golden_cases")}
        assert not bad and "sys.path" not in text, f"{path.relative_to(ROOT)} reaches into tests/"


def test_plugins_read_no_private_state_of_each_other_from_outside():
    for path in _sources("elo_mitsuba", "validation", "benchmarks"):
        text = path.read_text()
        assert not re.search(r"integ\w*\._[a-z]", text), f"{path.relative_to(ROOT)} reads private integrator state"


def test_every_cited_document_is_in_the_repository():
    """Docstrings, comments and docs cite files by path: each must exist here (generated outputs
    under out/ excepted)."""
    cited = re.compile(r"(?<![\w/.-])((?:[\w-]+/)*[\w.-]+\.md)\b")
    texts = [p for p in _sources("elo_mitsuba", "plugins", "validation", "benchmarks", "tests") if p != Path(__file__)]
    texts += [ROOT / "README.md", ROOT / "scenes_xml" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    missing = []
    for path in texts:
        for name in cited.findall(path.read_text()):
            if name.startswith("out/") or name in ("REPORT.md", "RESULTS.md", "RESULTS-quick.md", "README.md"):
                continue
            if not (ROOT / name).is_file() and not (path.parent / name).is_file():
                missing.append(f"{path.relative_to(ROOT)}: {name}")
    assert not missing, "cited files not in the repository: " + "; ".join(missing)


def _docstring_lines(path: Path) -> set[int]:
    """Line numbers of the module's, classes' and functions' docstrings."""
    lines = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                lines.update(range(first.lineno, first.end_lineno + 1))
    return lines


def test_render_py_stays_one_concept():
    """render.py is EloScene (load once, render many): its helpers live in their own modules.

    Counted without docstrings (their numpydoc Parameters and Examples are documentation, not
    concepts): 360 lines of code when the docstrings grew (issue 24)."""
    path = ROOT / "elo_mitsuba" / "render.py"
    lines = len(path.read_text().splitlines()) - len(_docstring_lines(path))
    assert lines <= 380, f"elo_mitsuba/render.py has {lines} lines outside docstrings (at most 380)"


def _writes_to_world(path: Path) -> list[int]:
    """Lines of ``path`` that assign to a subscript whose key names ``to_world``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else [])
        for target in targets:
            if isinstance(target, ast.Subscript) and "to_world" in ast.unparse(target.slice):
                out.append(node.lineno)
    return out


def test_only_render_py_moves_a_detector():
    """A detector's ``to_world`` is written by EloScene alone (set_detector, restore_detectors),
    so that its checks and the bit-for-bit guarantee of a moved detector hold everywhere."""
    owner = ROOT / "elo_mitsuba" / "render.py"
    assert _writes_to_world(owner), "the rule no longer sees render.py's writes"
    bad = [f"{p.relative_to(ROOT)}:{n}" for p in _sources("elo_mitsuba", "plugins", "validation", "benchmarks")
           if p != owner for n in _writes_to_world(p)]
    assert not bad, "to_world written outside elo_mitsuba/render.py: " + ", ".join(bad)


# -- the inverse wing's rules (issue 24) --
def _private_imports(path: Path) -> set[str]:
    """``from X import _name`` of another module's private function (``__future__`` and dunders aside)."""
    bad = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            bad |= {f"{node.module}.{a.name}" for a in node.names if a.name.startswith("_") and not a.name.startswith("__")}
    return bad


def test_no_cli_module_imports_another_except_args():
    """The commands are thin over the API: shared argument types live in cli/_args.py, the pipeline
    in the library (analysis/chain.py), never in another command's module."""
    for path in _sources("elo_mitsuba/cli"):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                names = [node.module] if node.module else [a.name for a in node.names]
                bad = [n for n in names if n.split(".")[0] not in ("_args", "checkout")]
                assert not bad, f"{path.relative_to(ROOT)} imports cli module(s) {bad}"
            if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("elo_mitsuba.cli."):
                assert node.module == "elo_mitsuba.cli._args", f"{path.relative_to(ROOT)} imports {node.module}"


def test_no_module_imports_another_modules_private_names():
    found = {}
    for path in _sources("elo_mitsuba", "plugins"):
        bad = {n.lstrip(".") for n in _private_imports(path)}
        if bad:
            found[str(path.relative_to(ROOT))] = sorted(bad)
    assert not found, f"private names imported across modules: {found}"


def test_event_channel_names_are_built_in_schema_only():
    """``<id>.e<k>`` has one builder (elo_mitsuba.schema.event_channel)."""
    pattern = re.compile(r"""f["'][^"']*\.e\{""")
    for path in _sources("elo_mitsuba", "plugins", "validation", "benchmarks"):
        if path == ROOT / "elo_mitsuba" / "schema.py":
            continue
        assert not pattern.search(path.read_text()), f"{path.relative_to(ROOT)} builds '<id>.e<k>' itself"


def test_one_reader_of_the_geometry_header():
    """Only schema.read_geometry reads the header's geometry keys; the old second reader is gone."""
    keys = re.compile(r"""(?:\.get\(|\[)["'](detectors|work_distance_mm|beam_aim_offset_mm)["']""")
    for path in _sources("elo_mitsuba/analysis", "elo_mitsuba/cli"):
        if path.name == "calibration.py":
            continue  # CALIB.json's own detectors, not an image header
        text = path.read_text()
        assert "def geometry_from_metadata" not in text, f"{path.relative_to(ROOT)}: a second header reader"
        assert not keys.search(text), f"{path.relative_to(ROOT)} reads geometry keys of a header itself"
    defs = [p for p in _sources("elo_mitsuba") if "def from_metadata(" in p.read_text()]
    assert [p.name for p in defs] == ["scan_geometry.py"]
    assert "read_geometry(" in (ROOT / "elo_mitsuba" / "analysis" / "scan_geometry.py").read_text()


def test_fwhm_to_sigma_is_written_once():
    pattern = re.compile(r"sqrt\(2(\.0)? \* np\.log\(2")
    hits = [p for p in _sources("elo_mitsuba", "plugins", "validation", "benchmarks") if pattern.search(p.read_text())]
    assert [p.name for p in hits] == ["schema.py"], hits


def test_every_link_of_the_readme_and_the_guide_resolves():
    """Markdown links and images of README.md and docs/*.md point at files of the repository
    (relative to the page; the guide links to results and examples outside docs/)."""
    link = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")
    missing = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for target in link.findall(page.read_text()):
            if re.match(r"[a-z]+:", target):
                continue
            if not (page.parent / target).exists():
                missing.append(f"{page.relative_to(ROOT)}: {target}")
    assert not missing, "links to nothing: " + "; ".join(missing)


#: Public names documented elsewhere (none left).
EXAMPLES_ELSEWHERE: set = set()
#: Methods of the public classes a user calls.
PUBLIC_METHODS = {
    "EloScene": ("render", "configure", "set_detector", "set_material", "set_quality", "restore_detectors",
                 "detector_geometry"),
    "RenderResult": ("write_exr", "error_summary", "event_shares", "negligible_events", "detectors"),
}


def _public_api():
    """(qualified name, object) of every callable the package and ``elo_mitsuba.analysis`` export,
    and of the public classes' methods."""
    import elo_mitsuba as em
    import elo_mitsuba.analysis as ea

    out = []
    for package in (em, ea):
        for name in package.__all__:
            if name in EXAMPLES_ELSEWHERE:
                continue
            obj = getattr(package, name)
            if callable(obj):
                out.append((f"{package.__name__}.{name}", obj))
    for cls, methods in PUBLIC_METHODS.items():
        for method in methods:
            attr = getattr(getattr(em, cls), method)
            out.append((f"elo_mitsuba.{cls}.{method}", attr.fget if isinstance(attr, property) else attr))
    return out


def test_every_public_name_has_a_numpydoc_example_that_a_test_runs():
    """Issue 24: each exported function, class and public method has an ``Examples`` section,
    and its module is one tests/test_doctests.py runs (so the example is run, not only shown)."""
    import inspect

    from test_doctests import MODULES

    missing, unrun = [], []
    for name, obj in _public_api():
        if not re.search(r"^Examples\n--------$", inspect.getdoc(obj) or "", re.M):
            missing.append(name)
        elif obj.__module__ not in MODULES:
            unrun.append(f"{name} ({obj.__module__})")
    assert not missing, "no Examples section: " + ", ".join(missing)
    assert not unrun, "Examples that tests/test_doctests.py does not run: " + ", ".join(unrun)
