"""The layout rules of pipeline/: module and function sizes, no import circle and no import from a lower
package to a higher one, dvc.yaml deps that cover every module a stage imports, and a command line that
imports no heavy library to list its commands; of tests/: no test file imports another (shared helpers
live in tests/factories/, fixtures in conftest.py)."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "pipeline"
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80


def _modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _type_only(tree: ast.AST) -> set[int]:
    """The ids of the import nodes under ``if TYPE_CHECKING:`` (annotations only, never run)."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            out |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    return out


def _imports(path: Path, annotations: bool = True) -> set[str]:
    """The pipeline modules `path` imports anywhere (top level or inside functions; without `annotations`,
    not those imported for annotations only)."""
    out: set[str] = set()
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = set() if annotations else _type_only(tree)
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        out |= {n for n in names if n in MODULES}
    return out


GRAPH = {name: _imports(path) - {name} for name, path in MODULES.items()}
RUN_GRAPH = {name: _imports(path, annotations=False) - {name} for name, path in MODULES.items()}


def _closure(start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        module = todo.pop()
        if module not in seen:
            seen.add(module)
            todo += GRAPH[module]
    return seen


def test_modules_and_functions_are_small() -> None:
    too_long = []
    for name, path in MODULES.items():
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > MAX_MODULE_LINES:
            too_long.append(f"{name}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    too_long.append(f"{name}.{node.name}: {length} lines")
    assert not too_long, too_long


def test_no_import_circle() -> None:
    """Depth-first search for a back edge in the import graph of what runs (an import for annotations
    only, under ``if TYPE_CHECKING:``, is no circle; package __init__ modules are empty)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(module: str) -> list[str] | None:
        state[module] = 1
        stack.append(module)
        for dep in sorted(RUN_GRAPH[module]):
            if state.get(dep) == 1:
                return stack[stack.index(dep) :] + [dep]
            if dep not in state and (cycle := visit(dep)):
                return cycle
        state[module] = 2
        stack.pop()
        return None

    for module in MODULES:
        if module not in state:
            cycle = visit(module)
            assert cycle is None, " -> ".join(cycle)


# The packages of pipeline/, lowest first: a module imports only its own package's and lower ones (one
# layer may hold several packages that do not import each other). The per-log library (`pipeline.logs`)
# sits under everything that reads a log; the stages and the commands on top.
LAYERS = (
    ("core",),
    ("logs",),
    ("physics",),
    ("labels", "sim", "calib"),
    ("export",),
    ("evaluation",),
    ("deploy",),
    ("stages", "tools"),
    ("cli",),
)


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def test_no_arrow_from_a_lower_package_to_a_higher_one() -> None:
    # pipeline/__init__.py (the version, the kernels chosen before anything runs) sits on core
    level = {pkg: k for k, layer in enumerate(LAYERS) for pkg in layer} | {"__init__": 0.5}
    packages = {_package(m) for m in MODULES}
    assert packages <= set(level), sorted(packages - set(level))  # every package has its layer
    up = sorted(
        f"{name} imports {dep}"
        for name in MODULES
        for dep in GRAPH[name]
        if _package(dep) != _package(name) and level[_package(dep)] >= level[_package(name)]
    )
    assert not up, up


def test_commands_modules_are_imported_by_the_command_line_only() -> None:
    """pipeline/tools holds commands (argument parsing, printing); the library they run lives in the
    subpackages, which never import a command's module (the export's runtime is `pipeline.export`)."""
    tools = {name for name in MODULES if name.startswith("pipeline.tools.")}
    users = sorted(
        f"{name} imports {sorted(GRAPH[name] & tools)}"
        for name in MODULES
        if GRAPH[name] & tools and name != "pipeline.cli" and not name.startswith("pipeline.tools.")
    )
    assert not users, users


def test_dvc_deps_cover_every_module_a_stage_imports() -> None:
    """A code change can never leave a stage stale: each stage depends on every file its module reaches."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    checked = 0
    for name, stage in stages.items():
        body = stage.get("do", stage)
        command = body["cmd"].split()[1]
        from pipeline.cli import COMMANDS

        module = COMMANDS[command][0]
        deps = [d for d in body["deps"] if d.startswith("pipeline")]
        missing = []
        for reached in sorted(_closure(module)):
            rel = MODULES[reached].relative_to(ROOT).as_posix()
            if reached.count(".") > 0 and not any(
                rel == d or rel.startswith(d.rstrip("/") + "/") for d in deps
            ):
                missing.append(rel)
        missing = [m for m in missing if m not in ("pipeline/__init__.py",)]
        assert not missing, f"dvc.yaml stage {name} does not depend on {missing}"
        checked += 1
    assert checked >= 7


def test_command_line_help_imports_no_heavy_library() -> None:
    """`ftcal --help` and `ftcal <command> --help` build their parser without torch, numpy, mlflow...
    (a stage imports them when it runs): the command line answers at once."""
    from pipeline.cli import COMMANDS

    code = (
        "import sys\n"
        "from pipeline.cli import COMMANDS, build_parser\n"
        "heavy = {'torch', 'numpy', 'mlflow', 'pinocchio', 'pyarrow', 'scipy', 'pandas', 'onnxruntime'}\n"
        "for command in ['', *COMMANDS]:\n"
        "    build_parser(command).format_help()\n"
        "    print(command or '-', sorted(heavy & set(sys.modules)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    lines = out.stdout.split("\n")[:-1]
    assert len(lines) == len(COMMANDS) + 1 and all(line.endswith(" []") for line in lines), out.stdout


def _test_module(name: str) -> str | None:
    """The test module that the dotted `name` (leading dots: relative to its package) is or lies in."""
    dots = len(name) - len(name.lstrip("."))
    parts = name[dots:].split(".")
    if dots and parts[0].startswith("test_"):
        return name[:dots] + parts[0]
    if not dots and parts[0] == "tests" and len(parts) > 1 and parts[1].startswith("test_"):
        return f"tests.{parts[1]}"
    return None


def _test_module_imports(source: str) -> list[tuple[int, str]]:
    """(line, test module) of every import of a test module in `source`, top level or inside functions:
    ``import tests.test_x``, ``from tests.test_x import y``, ``from tests import test_x``, ``from .test_x
    import y``, ``from . import test_x``."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = "." * node.level + (node.module or "")
            names = [base, *(base + ("" if base.endswith(".") else ".") + a.name for a in node.names)]
        else:
            continue
        out += [(node.lineno, m) for m in sorted({m for m in map(_test_module, names) if m})]
    return out


def test_no_test_file_imports_another() -> None:
    """A helper that test files share has one home in tests/factories/ (a shared fixture: tests/conftest.py),
    so that no file under tests/ imports a test module (which would also import its tests and fixtures)."""
    forms = (
        "import tests.test_a\nfrom tests.test_b import x\nfrom .test_c import y\n"
        "def f():\n    from tests import test_d\n    from . import test_e\n"
    )
    expected = ["tests.test_a", "tests.test_b", ".test_c", "tests.test_d", ".test_e"]
    assert sorted(n for _, n in _test_module_imports(forms)) == sorted(expected)
    assert not _test_module_imports("import tests.conftest\nfrom tests.factories.logs import write_log\n")
    found = [
        f"{path.relative_to(ROOT).as_posix()}:{line} imports {name}"
        for path in sorted((ROOT / "tests").rglob("*.py"))
        for line, name in _test_module_imports(path.read_text(encoding="utf-8"))
    ]
    assert not found, found


def test_ruff_check_and_format_are_clean() -> None:
    """The lint and format rules of pyproject.toml hold (so CI, which runs the tests, enforces them)."""
    for args in (["check", "--no-cache"], ["format", "--check", "--no-cache"]):
        out = subprocess.run(
            [sys.executable, "-m", "ruff", *args, "pipeline", "tests", "benchmarks"],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        assert out.returncode == 0, out.stdout + out.stderr


_NAMED_PATH = re.compile(r"(?<![\w/.])((?:pipeline|tests|benchmarks|docs)/[\w/.-]*\w\.(?:py|md|c|h|yaml))")
_NAMED_MODULE = re.compile(r"(?<![\w/.])(pipeline(?:\.\w+)+)")


def _sources() -> list[Path]:
    """Every file whose comments and docstrings name the product's files and modules."""
    files = [*ROOT.glob("pipeline/**/*.py"), *ROOT.glob("benchmarks/*.py"), *ROOT.glob("benchmarks/*.c")]
    return [
        *files,
        *ROOT.glob("tests/**/*.py"),  # tests/factories/ too
        *ROOT.glob("docs/*.md"),
        *(ROOT / f for f in ("dvc.yaml", "params.yaml", "README.md")),
    ]


def _defines(module: Path, name: str) -> bool:
    text = module.read_text(encoding="utf-8")
    return bool(
        re.search(rf"^\s*(def|class|async def) {name}\b|^{name}\b\s*[:=]|import .*\b{name}\b", text, re.M)
    )


def test_every_file_and_module_a_comment_names_exists() -> None:
    """Paths (``pipeline/export/wbd.py``, ``docs/labels.md``) and dotted names (``pipeline.export.wbd``,
    ``pipeline.calib.split.split_logs``) in code, params, dvc.yaml and docs: each one exists, and nothing
    sends a reader outside the clone (a design document a clone does not have)."""
    missing = []
    for source in _sources():
        text = source.read_text(encoding="utf-8")
        missing += [f"{source.name}: {p}" for p in _NAMED_PATH.findall(text) if not (ROOT / p).exists()]
        outside = "ARCHITECTURE" + ".md"  # the design document beside a developer's checkout, not in a clone
        missing += [f"{source.name}: {outside}" for _ in range(text.count(outside))]
        for dotted in _NAMED_MODULE.findall(text):
            parts = dotted.split(".")
            k = len(parts)
            while k > 1 and not (
                ROOT.joinpath(*parts[:k]).with_suffix(".py").is_file()
                or ROOT.joinpath(*parts[:k], "__init__.py").is_file()
            ):
                k -= 1
            module = ROOT.joinpath(*parts[:k]).with_suffix(".py")
            module = module if module.is_file() else ROOT.joinpath(*parts[:k], "__init__.py")
            if k == 1 or (k < len(parts) and not _defines(module, parts[k])):
                missing.append(f"{source.name}: {dotted}")
    assert not missing, sorted(set(missing))
