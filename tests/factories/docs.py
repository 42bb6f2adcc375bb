"""README.md, docs/ and dvc.yaml read as data: the shell commands the docs show, the stages of dvc.yaml
(foreach expanded, params substituted), params.yaml and the files git tracks."""

from __future__ import annotations

import re
import subprocess
from functools import cache
from pathlib import Path

import yaml

from tests.factories.params import repo_params

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# the first words of the shell commands the docs show
SHELL = ("ftcal", "dvc", "python", "mlflow", "export", "pip", "pytest", "for")


@cache
def params() -> dict:
    """params.yaml as data."""
    return repo_params()


@cache
def tracked() -> list[str]:
    """Every file git tracks, relative to the checkout."""
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True)
    return out.stdout.split()


@cache
def stages() -> dict[str, dict]:
    """Every stage of dvc.yaml, foreach expanded: name (``train@legs``) -> its cmd, deps and outs."""
    raw = (ROOT / "dvc.yaml").read_text()

    def lookup(match: re.Match) -> str:
        value = params()
        for part in match.group(1).split("."):
            value = value[part]
        return str(value)

    out = {}
    for name, stage in yaml.safe_load(raw)["stages"].items():
        if "foreach" not in stage:
            out[name] = stage
            continue
        items = stage["foreach"]
        if isinstance(items, str):
            items = eval_params(items)
        pairs = items.items() if isinstance(items, dict) else [(item, item) for item in items]
        for key, item in pairs:  # a mapping: ${key} its key, ${item} its value; a list: both the element
            text = yaml.safe_dump(stage["do"]).replace("${key}", str(key)).replace("${item}", str(item))
            out[f"{name}@{key}"] = yaml.safe_load(text)
    for stage in out.values():
        text = re.sub(r"\$\{([\w.]+)\}", lookup, yaml.safe_dump(stage))
        stage.clear()
        stage.update(yaml.safe_load(text))
    return out


def eval_params(ref: str) -> dict:
    """The params.yaml value a ``${a.b}`` reference of dvc.yaml names."""
    value = params()
    for part in ref.strip("${}").split("."):
        value = value[part]
    return value


def code_blocks(text: str) -> list[str]:
    """Shell command lines of the fenced blocks: continuation lines joined, comments dropped."""
    lines = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S):
        joined = block.replace("\\\n", " ")
        for line in joined.splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if line.split(" ")[:1] and line.split(" ")[0] in SHELL:
                lines.append(line)
    return lines


def inline_spans(text: str) -> list[str]:
    """The inline code spans of the prose (fenced blocks left out)."""
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    return re.findall(r"`([^`\n]+)`", prose)


def commands() -> list[tuple[str, str]]:
    """(doc file name, command) of every shell command the docs show, in code blocks or inline, each part
    of a chained line on its own."""
    out = []
    for doc in DOCS:
        text = doc.read_text()
        for line in code_blocks(text):
            for part in re.split(r"\s*(?:&&|;|&|\bdo\b|\bdone\b)\s*", line):
                if part.split(" ")[:1] and part.split(" ")[0] in SHELL:
                    out.append((doc.name, part))
        out += [(doc.name, s) for s in inline_spans(text) if s.split(" ")[0] in ("ftcal", "dvc", "python")]
    return out
