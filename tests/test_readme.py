"""What README.md (and docs/) tells a user to run or to look at exists in the product.

Every ``ftcal`` command of a code block parses with the command's own parser, its groups are groups of
params.yaml and its paths exist (in git, or as a DVC stage's output or dependency); every ``dvc repro``
names a stage of dvc.yaml; every benchmark exists with the options shown; inline params keys are keys of
params.yaml, inline paths exist, stage names are stages. The short commands run: ``ftcal <command> --help``
of every command shown, ``dvc dag``, ``dvc status``, ``dvc metrics show``.
"""

from __future__ import annotations

import fnmatch
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.cli import COMMANDS, build_parser, split_commands
from tests.factories.docs import DOCS, ROOT, code_blocks, commands, inline_spans, params, stages, tracked

GROUP_ARGS = {"train": 0, "worker": 0, "evaluate": 0}  # command -> index of its group argument


def _paths(stage: dict, kinds: tuple[str, ...]) -> list[str]:
    out = []
    for kind in kinds:
        for entry in stage.get(kind, []) or []:
            out += list(entry) if isinstance(entry, dict) else [entry]
    return [str(p).rstrip("/") for p in out]


def path_exists(path: str) -> bool:
    """A file or folder of the checkout, or a DVC stage's output or dependency (or inside one)."""
    path = path.rstrip("/")
    for key, value in {"<group>": "*", "<day>": "*", "<log>": "*", "<headline>": "*", "<date>": "*"}.items():
        path = path.replace(key, value)
    if any(fnmatch.fnmatch(f, path) or fnmatch.fnmatch(f, path + "/*") for f in tracked()):
        return True
    dvc = [p for s in stages().values() for p in _paths(s, ("outs", "deps", "metrics", "plots"))]
    return any(  # a stage's path, inside one, or a folder of such paths
        fnmatch.fnmatch(d, path) or path.startswith(d + "/") or d.startswith(path + "/") for d in dvc
    ) or any(fnmatch.fnmatch(d, path.split("/*")[0]) for d in dvc)


def params_key_exists(key: str) -> bool:
    value: object = params()
    for part in key.split("."):
        if not isinstance(value, dict):
            return False
        names = [k for k in value if fnmatch.fnmatch(str(k), part)]
        if not names:
            return False
        value = value[names[0]]
    return True


def check_ftcal(words: list[str]) -> list[str]:
    """Problems of one `ftcal ...` command line (words after `ftcal`)."""
    words = [w.strip("[]") for w in words]
    command = next((w for w in words if not w.startswith("-")), None)
    if command is None:
        return []
    if command not in COMMANDS and command != "robot":
        return [f"no command {command!r}"]
    if len(words) == 1 or words[1:] and all(w.isupper() or w.startswith("-") for w in words[1:]):
        return []  # a usage line: `ftcal worker GROUP IN`
    try:
        args = build_parser(command).parse_args(words)
    except SystemExit:
        return [f"does not parse: ftcal {' '.join(words)}"]
    problems = []
    positional = [w for w in words[1:] if not w.startswith("-")]
    if command in GROUP_ARGS and positional and not positional[0].isupper():
        group = positional[GROUP_ARGS[command]]
        if group not in params()["train"]["groups"]:
            problems.append(f"train.groups has no group {group!r}")
    for value in vars(args).values():
        text = str(value)
        looks_like_path = "/" in text and not text.isupper() and not text.startswith(("-", "/", "http"))
        if looks_like_path and not path_exists(text) and not path_exists(str(Path(text).parent)):
            problems.append(f"no path {text}")
    return problems


def check_command(line: str) -> list[str]:
    words = shlex.split(line)
    head = words[0]
    if head == "ftcal":  # commands joined by + run one after the other
        return [problem for part in split_commands(words[1:]) for problem in check_ftcal(part)]
    if head == "dvc" and words[1:2] == ["repro"]:
        names = [w for w in words[2:] if not w.startswith("-")]
        families = {s.split("@")[0] for s in stages()}
        return [f"dvc.yaml has no stage {n!r}" for n in names if n not in stages() and n not in families]
    if head == "python" and words[1:2] and words[1].endswith(".py"):
        script = ROOT / words[1]
        if not script.is_file():
            return [f"no script {words[1]}"]
        source = script.read_text()
        return [f"{words[1]} has no option {w}" for w in words[2:] if w.startswith("--") and w not in source]
    if head == "export":
        name = words[1].split("=")[0]
        found = any(name in p.read_text() for p in (ROOT / "pipeline").rglob("*.py"))
        return [] if found or name == "MLFLOW_TRACKING_URI" else [f"nothing reads ${name}"]
    return []


@pytest.mark.parametrize(("doc", "line"), commands(), ids=lambda v: v if len(v) < 60 else v[:57] + "...")
def test_command_names_what_exists(doc: str, line: str) -> None:
    assert not check_command(line), f"{doc}: {line}: {check_command(line)}"


def spans() -> list[tuple[str, str]]:
    return [(doc.name, s) for doc in DOCS for s in inline_spans(doc.read_text())]


def check_span(span: str) -> list[str]:
    if re.fullmatch(r"[a-z_]+\.py", span):
        return [] if list((ROOT / "pipeline").rglob(span)) else [f"no module file {span}"]
    span = span.split("::")[0]  # a test's node id: its file
    sections = set(params())
    key = span.split(":")[0].strip()
    if re.fullmatch(r"[a-z_]+(\.[a-z_0-9*]+)+", key) and key.split(".")[0] in sections:
        return [] if params_key_exists(key) else [f"params.yaml has no key {key}"]
    prefixes = ("pipeline/", "tests/", "benchmarks/", "docs/", "data/", "reports/", "models/", "exported/")
    if span.startswith(prefixes) and " " not in span:
        return [] if path_exists(span) else [f"no path {span}"]
    if re.fullmatch(r"[a-z_]+@(<\w+>|\w+)?", span):
        family = span.split("@")[0]
        return [] if any(s.startswith(family + "@") for s in stages()) else [f"no stage family {family}@"]
    return []


@pytest.mark.parametrize(("doc", "span"), spans(), ids=lambda v: v if len(v) < 60 else v[:57] + "...")
def test_inline_names_exist(doc: str, span: str) -> None:
    assert not check_span(span), f"{doc}: `{span}`: {check_span(span)}"


def test_stage_table_names_the_stages() -> None:
    text = (ROOT / "README.md").read_text()
    table = text.split("## Stages", 1)[1].split("\n\n", 2)[1]
    names = [row.split("|")[1].strip() for row in table.splitlines()[2:]]
    families = {s.split("@")[0] for s in stages()}
    assert names and all(n.split("@")[0] in families for n in names), (names, sorted(families))
    assert families <= {n.split("@")[0] for n in names}, sorted(families - {n.split("@")[0] for n in names})


def _run(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=ROOT, capture_output=True, text=True, check=False, timeout=300)


@pytest.mark.slow
def test_short_commands_run() -> None:
    shown = sorted(
        {
            shlex.split(line)[1]
            for _, line in commands()
            if line.startswith("ftcal ") and len(line.split()) > 1
        }
        - {"--help"}
    )
    assert shown
    for command in shown:
        proc = _run([sys.executable, "-m", "pipeline.cli", command, "--help"])
        assert proc.returncode == 0 and "usage: ftcal" in proc.stdout, (command, proc.stderr[-500:])
    for args in (["dag"], ["status"], ["metrics", "show"]):
        proc = _run([sys.executable, "-m", "dvc", *args])
        assert proc.returncode == 0, (args, proc.stderr[-1000:])


def _prose(text: str) -> str:
    """The text outside fenced code blocks and inline code spans."""
    return re.sub(r"`[^`\n]*`", "", re.sub(r"```.*?```", "", text, flags=re.S))


def anchors(text: str) -> set[str]:
    """The anchors a forge gives the headings of a Markdown text: lower case, code and link markup dropped,
    punctuation but ``-`` and ``_`` dropped, spaces -> ``-``, a repeated one suffixed ``-1``, ``-2``..."""
    seen: dict[str, int] = {}
    for heading in re.findall(r"^#{1,6} (.+)$", re.sub(r"```.*?```", "", text, flags=re.S), flags=re.M):
        plain = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).replace("`", "").strip().lower()
        slug = re.sub(r"[^\w\- ]", "", plain).replace(" ", "-")
        seen[slug] = seen.get(slug, -1) + 1
        if seen[slug]:
            seen[f"{slug}-{seen[slug]}"] = 0
    return set(seen)


def links() -> list[tuple[str, str]]:
    out = []
    for doc in DOCS:
        for target in re.findall(r"\]\(([^)\s]+)\)", _prose(doc.read_text())):
            if not re.match(r"[a-z]+:", target):  # http:, https:, mailto: are not files of the checkout
                out.append((doc.relative_to(ROOT).as_posix(), target))
    return out


def check_link(doc: str, target: str) -> list[str]:
    path, _, fragment = target.partition("#")
    file = (ROOT / doc).parent / path if path else ROOT / doc
    if not file.resolve().is_relative_to(ROOT) or not file.exists():
        return [f"no file {path}"]
    if fragment and fragment not in anchors(file.read_text()):
        return [f"{path or doc} has no heading #{fragment}"]
    return []


@pytest.mark.parametrize(("doc", "target"), links(), ids=lambda v: v if len(v) < 60 else v[:57] + "...")
def test_links_resolve(doc: str, target: str) -> None:
    """Every link between the pages names a file of the checkout, and a heading of it after a ``#``."""
    assert not check_link(doc, target), f"{doc}: ({target}): {check_link(doc, target)}"


def test_every_docs_page_is_linked_from_the_readme_and_opens_with_a_title_and_a_summary() -> None:
    linked = {target.partition("#")[0] for doc, target in links() if doc == "README.md"}
    for page in DOCS[1:]:
        name = page.relative_to(ROOT).as_posix()
        assert name in linked, f"README.md does not link {name}"
        title, summary = page.read_text().split("\n\n", 2)[:2]
        assert re.fullmatch(r"# \S.*", title), f"{name}: no title on its first line"
        assert not summary.startswith(("#", "|", "```", "- ")), f"{name}: no summary under the title"


def test_ci_runs_what_the_readme_says() -> None:
    """`.ci/run` installs with the README's install commands (pip's output options aside) and runs the
    README's test command, exactly."""
    readme = (ROOT / "README.md").read_text()
    lines = (ROOT / ".ci/run").read_text().splitlines()
    ci = [shlex.split(line) for line in lines if line.split()[:1] in (["pip"], ["pytest"])]
    quiet = ("--quiet", "-q", "--disable-pip-version-check")
    ci_pip = [[w for w in words if w not in quiet] for words in ci if words[0] == "pip"]
    block = re.search(r"## Install\n\n```\n(.*?)\n```", readme, flags=re.S)
    assert block, "README.md: no install block under ## Install"
    assert ci_pip == [shlex.split(part) for part in block.group(1).split(" && ")], (ci_pip, block.group(1))
    tests = [line for line in code_blocks(readme) if line.startswith("pytest")]
    assert tests == [" ".join(words) for words in ci if words[0] == "pytest"], tests
