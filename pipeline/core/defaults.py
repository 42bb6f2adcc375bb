"""The effective configuration: the defaults (``pipeline/defaults.yaml``) under a lab's params.yaml.

A lab's params.yaml holds what it sets (the robot, where its logs are, the sensor groups, ...); every other
key takes its value from ``pipeline/defaults.yaml``, where each default lives once with its unit and
reason. A mapping of the lab's file is merged key by key into the default's (``train.defaults.lr`` alone
changes the learning rate), except the collections whose keys the lab names (`COLLECTIONS`: the sensor
groups, the serial numbers, ...), which the lab's replace whole. A key the defaults do not know is kept,
so the sections' validation refuses it with its dotted path (`pipeline.core.config`).

`resolve` gives the effective mapping and where each value came from; ``ftcal params`` prints them, and
``ftcal params --write params.resolved.yaml`` writes the mapping the DVC stages track (dvc.yaml: each
stage's params are keys of that file, so a stage re-runs when a value it reads changes, wherever it was
set).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from pipeline.core.errors import ConfigError

DEFAULTS_FILE = Path(__file__).resolve().parents[1] / "defaults.yaml"
RESOLVED_FILE = "params.resolved.yaml"  # what `ftcal params --write` writes and dvc.yaml's stages track
DEFAULT, LAB = "default", "params.yaml"  # where a value came from
# Mappings whose keys a lab names (a sensor, a group, a joint, a dataDumper part): the lab's replaces the
# default's whole, so a lab's two groups are its groups, not the default's three plus its two.
COLLECTIONS = frozenset(
    {
        "robot.foot_pairs",
        "robot.serials",
        "simulate.imu.axes",
        "ingest.imu_axes",
        "ingest.fixed_joints",
        "ingest.mat.sensor_names",
        "ingest.dumper.ft_ports",
        "ingest.dumper.joints",
        "train.defaults.search",
        "train.groups",
        "export.models",
        "deploy.torque_limbs",
        "deploy.interaction.sites",
    }
)
# Keys dvc.yaml's templates read from params.yaml itself (``${ingest.source}``, ``foreach:
# ${train.groups}``, ``${deploy.real_logs}``): DVC reads them before any stage runs, so a lab's file sets
# them (`require_templated`).
TEMPLATED = ("ingest.source", "train.groups", "deploy.real_logs")


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys (PyYAML silently keeps the last one)."""


def _construct_unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    keys: set[Any] = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in keys:
            raise yaml.constructor.ConstructorError(
                "while constructing a mapping",
                node.start_mark,
                f"found duplicate key {key!r}",
                key_node.start_mark,
            )
        keys.add(key)
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_unique_mapping)


def read_yaml_file(path: Path) -> Any:
    """The YAML document of `path` (duplicate keys refused); ConfigError saying what is wrong (not which
    file: the caller names it)."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read: {exc}") from None
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"invalid YAML at {where}{problem}") from None


def read_defaults() -> dict[str, Any]:
    """The defaults file as a mapping (ConfigError if the installation lacks it)."""
    try:
        data = read_yaml_file(DEFAULTS_FILE)
    except ConfigError as exc:
        raise ConfigError(f"{DEFAULTS_FILE}: {exc} (the installation's defaults)") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{DEFAULTS_FILE}: not a mapping of defaults")
    return data


def resolve(lab: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, str]]:
    """(effective mapping, dotted key of every leaf -> `DEFAULT` or `LAB`): `lab` over the defaults.

    Raises:
        ConfigError: the lab gives a scalar or a list where the defaults hold a mapping (naming the key).
    """
    sources: dict[str, str] = {}
    return _merge(read_defaults(), lab, "", sources), sources


def _merge(default: Any, lab: Any, key: str, sources: dict[str, str]) -> Any:
    """`lab` (given at dotted `key`) over `default`: mappings merged key by key, anything else replaced."""
    if not isinstance(default, Mapping) or key in COLLECTIONS:
        _mark(lab, key, LAB, sources)
        return lab
    if not isinstance(lab, Mapping):
        raise ConfigError(f"{key or 'the top level'} must be a mapping, got {lab!r}")
    out = {}
    for k in dict.fromkeys([*default, *lab]):
        sub = f"{key}.{k}" if key else str(k)
        if k not in lab:
            out[k] = copy.deepcopy(default[k])
            _mark(default[k], sub, DEFAULT, sources)
        elif k not in default:  # unknown: kept, for the sections' validation to refuse with its key
            out[k] = lab[k]
            _mark(lab[k], sub, LAB, sources)
        else:
            out[k] = _merge(default[k], lab[k], sub, sources)
    return out


def _mark(value: Any, key: str, source: str, sources: dict[str, str]) -> None:
    """Every leaf under `key` of `value` came from `source`."""
    if isinstance(value, Mapping) and key not in COLLECTIONS and value:
        for k, v in value.items():
            _mark(v, f"{key}.{k}", source, sources)
    else:
        sources[key] = source


def require_templated(lab: Mapping[str, Any], where: str) -> None:
    """ConfigError unless the lab's file `where` sets every `TEMPLATED` key (dvc.yaml reads them there)."""
    for dotted in TEMPLATED:
        node: Any = lab
        for part in dotted.split("."):
            if not isinstance(node, Mapping) or part not in node:
                raise ConfigError(
                    f"{where}: {dotted} must be set in this file: dvc.yaml reads it from params.yaml itself "
                    f"(the default: {_default(dotted)!r})"
                )
            node = node[part]


def _default(dotted: str) -> Any:
    node: Any = read_defaults()
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, Mapping) else None
    return node
