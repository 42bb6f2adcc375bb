"""``ftcal params``: the effective configuration, each value with where it came from.

``ftcal params [--params PATH] [--set-only] [KEY ...]`` prints one line per value (its dotted key, the value,
and ``params.yaml`` or ``default``; `pipeline.core.defaults`), only those under the KEYs if given, only
those the lab's file sets with ``--set-only``. ``ftcal params --write FILE`` writes the effective mapping
(YAML) instead, atomically: the DVC stage ``params`` writes ``params.resolved.yaml`` so, and every other
stage tracks the keys it reads there. The file is validated first, as every stage does: an unknown key or
a bad value is refused with its dotted path.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option

COMMAND = "params"
WIDTH = 60  # characters of a value shown on its line (longer ones are cut, ending in ...)


def effective(path: Path | None) -> tuple[dict[str, Any], dict[str, str], Path]:
    """(effective mapping, dotted leaf -> source, the lab's file) of params file `path` (default: the repo
    root's params.yaml), validated as the stages load it (ConfigError naming the key)."""
    from pipeline.core.config import PARAMS_FILE, load_params, repo_root
    from pipeline.core.defaults import read_yaml_file, resolve

    path = path if path is not None else repo_root() / PARAMS_FILE
    params = load_params(path)  # validates, as every stage does (the file named in the message)
    data = {k: v for k, v in params.raw.items() if k != "__file__"}  # what the stages read
    return data, resolve(read_yaml_file(path))[1], path


def lines(data: dict[str, Any], sources: dict[str, str], keys: list[str], set_only: bool) -> list[str]:
    """One aligned line per leaf: ``key  value  source``."""
    import yaml

    rows = []
    for key, source in sources.items():
        if keys and not any(key == k or key.startswith(f"{k}.") for k in keys):
            continue
        if set_only and source == "default":
            continue
        node: Any = data
        for part in key.split("."):
            node = node[part] if part in node else node[int(part)]
        text = (
            yaml.safe_dump(node, default_flow_style=True, sort_keys=False, width=10**6)
            .strip()
            .removesuffix("...")
            .strip()
        )
        rows.append((key, text if len(text) <= WIDTH else text[: WIDTH - 3] + "...", source))
    width = max((len(k) for k, _, _ in rows), default=0)
    shown = max((len(v) for _, v, _ in rows), default=0)
    return [f"{k:<{width}}  {v:<{shown}}  {s}" for k, v, s in rows]


def write(data: dict[str, Any], lab: Path, out: Path) -> None:
    """The effective mapping into `out` (YAML, atomically), for DVC; the lab's file must set the keys
    dvc.yaml's templates read from it (`pipeline.core.defaults.require_templated`)."""
    import yaml

    from pipeline.core.config import display_path
    from pipeline.core.defaults import read_yaml_file, require_templated
    from pipeline.core.io import write_text

    require_templated(read_yaml_file(lab), display_path(lab))
    head = (
        f"# Written by `ftcal params --write` from {display_path(lab)} over pipeline/defaults.yaml: the\n"
        "# effective configuration, which dvc.yaml's stages track. Edit params.yaml, not this file.\n"
    )
    write_text(out, head + yaml.safe_dump(data, sort_keys=False, width=100))


def _cmd(args: argparse.Namespace) -> int:
    data, sources, lab = effective(args.params)
    if args.write is not None:
        write(data, lab, args.write)
        mine = sum(s != "default" for s in sources.values())
        print(f"params: {args.write} ({len(sources)} values, {mine} set in {lab.name})")
        return 0
    shown = lines(data, sources, args.keys, args.set_only)
    if args.keys and not shown:
        from pipeline.core.errors import ConfigError

        raise ConfigError(f"no value under {', '.join(args.keys)} (see `ftcal params`)")
    print("\n".join(shown))
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal params [KEY ...] [--set-only] [--write FILE]`."""
    p = subparsers.add_parser(
        COMMAND,
        help="print the effective configuration (defaults and params.yaml) and where each value came from",
        description=(__doc__ or "").split("\n\n")[0],
    )
    p.add_argument("keys", nargs="*", metavar="KEY", help="dotted keys or sections to show (default: all)")
    p.add_argument("--set-only", action="store_true", help="only the values params.yaml sets")
    p.add_argument("--write", type=Path, metavar="FILE", help="write the effective YAML to FILE instead")
    add_params_option(p)
    p.set_defaults(func=_cmd)
