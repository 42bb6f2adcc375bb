"""The model families of ftcal, where training, scoring, export, the deployment tests and the pages find a
family by the name of one of its models.

A family is one module of `pipeline.calib.families` holding a ``FAMILY`` (a `Family`: its key, rank, kind,
name, colours, and the hooks that fit, predict, cross-validate, save, read and export it); a family defined
elsewhere (a lab's own, a test's) joins with `register`. Nothing else names a family: training
(`pipeline.calib.fitting`), selection, scoring, the export, the deployment tests and the pages iterate
`families()`.

A model's name is its family's key, followed for a numbered family by its number: ``raw``, ``offset`` (the
factory map with a constant correction: what a re-zeroing does), ``affine``,
``poly2`` (a polynomial of order 2), ``play`` (the affine map with play-operator features of the raw
wrench: memory), ``arx`` (the affine map with low-pass departures of the raw wrench: memory), ``nn7`` (a
network of 7 inputs per sensor), ``win`` (a network over a causal window of the raw wrench correcting the play
model: memory). The built-in families, simplest first (the order in which cross-validation walks
them, `pipeline.calib.params.select_by_folds`):

| family | kind | memory | fitted by | exported as |
|---|---|---|---|---|
| raw | identity | no | nothing (the factory map) | the raw wrench |
| offset | linear | no | closed form (the mean residual) | a linear part (the constant) |
| affine | linear | no | closed form (`pipeline.calib.linear`) | a linear part |
| poly<n> | linear | no | closed form, ridge | a linear part (monomials) |
| play | linear | yes | closed form | a linear part with play state |
| arx | linear | yes | closed form | a linear part with filter state |
| nn<k> | network | no | Optuna + Adam (`pipeline.calib.search`) | an MLP |
| win | window | yes | Adam, on the play model (`pipeline.calib.window`) | a play part, an MLP, window state |

A family with memory calibrates a sample from its present inputs and a state carried from sample to sample
(the play operators' or the filters' outputs, `pipeline.core.lowpass`): trained on whole logs in time order,
its state starts afresh at each log's (or segment's) first sample and carries across gaps, as the exported
graph does with its ``state`` input and output (`pipeline.export.graph`). The play model ranks before the
arx model: a play operator reads the path of the wrench alone, whatever the rate, while a filter is tied to
the training logs' sample period; the arx model is deployed only where it wins clearly.

Light on purpose (no torch, no onnx): params and pages import it.
"""

from __future__ import annotations

import importlib
import pkgutil

from pipeline.calib.families.base import IDENTITY, KINDS, LINEAR, NETWORK, WINDOW, Family

__all__ = ["IDENTITY", "KINDS", "LINEAR", "NETWORK", "WINDOW", "Family"]
PACKAGE = "pipeline.calib.families"  # every module of it with a FAMILY is a family
RAW, OFFSET, AFFINE, POLY, PLAY, ARX, NN, WIN = "raw", "offset", "affine", "poly", "play", "arx", "nn", "win"
OTHER_COLOUR = "#7f7f7f"  # a name of no family (the oracle and the labels have their own colours)
_REGISTERED: dict[str, Family] = {}
_FOUND: dict[str, Family] = {}


def _found() -> dict[str, Family]:
    """The families of `PACKAGE`'s modules, imported once."""
    if not _FOUND:
        package = importlib.import_module(PACKAGE)
        for info in pkgutil.iter_modules(package.__path__):
            family = getattr(importlib.import_module(f"{PACKAGE}.{info.name}"), "FAMILY", None)
            if isinstance(family, Family):
                _FOUND[family.key] = family
    return _FOUND


def families() -> list[Family]:
    """Every family, simplest first (by rank): the built-in ones and those `register`-ed."""
    return sorted({**_found(), **_REGISTERED}.values(), key=lambda f: (f.rank, f.key))


def register(family: Family) -> Family:
    """Add `family` (or replace the one of its key) for this process: training, selection, scoring, the
    export, the deployment tests and the pages find it from now on. Returns it."""
    if not family.key.isidentifier() or family.key[-1].isdigit():
        raise ValueError(f"{family.key!r}: a family's key is a name that does not end in a digit")
    if family.kind not in KINDS:
        raise ValueError(f"{family.key}: kind {family.kind!r} is not one of {', '.join(KINDS)}")
    clash = [f.key for f in families() if f.key != family.key and f.rank == family.rank]
    if clash:
        raise ValueError(f"{family.key}: rank {family.rank} is {clash[0]}'s")
    _REGISTERED[family.key] = family
    return family


def unregister(key: str) -> None:
    """Forget a `register`-ed family (a built-in one stays)."""
    _REGISTERED.pop(key, None)


def by_key(key: str) -> Family:
    """The family of `key` (KeyError: none)."""
    return {f.key: f for f in families()}[key]


def nn_name(n_inputs: int) -> str:
    """The network with `n_inputs` inputs per sensor: nn7, nn13."""
    return by_key(NN).name(n_inputs)


def poly_name(order: int) -> str:
    """The polynomial of `order`: poly2, ..."""
    return by_key(POLY).name(order)


def patterns() -> list[str]:
    """Every family's model name, simplest first: raw, affine, poly<n>, play, arx, nn<n>, win."""
    return [f"{f.key}<n>" if f.numbered else f.key for f in families()]


def family_of(name: str) -> Family | None:
    """The family of model `name` (None: not a model of any family, e.g. ``oracle``)."""
    for family in families():
        if family.numbered:
            tail = name[len(family.key) :]
            if name.startswith(family.key) and tail.isdigit():
                return family
        elif name == family.key:
            return family
    return None


def number_of(name: str) -> int | None:
    """The number of a numbered family's model (poly3 -> 3, nn13 -> 13), else None."""
    family = family_of(name)
    return int(name[len(family.key) :]) if family is not None and family.numbered else None


def complexity(name: str) -> tuple[float, int]:
    """Sort key, simplest first: the family's rank, then its number (poly1 < poly4, nn7 < nn13); a name of
    no family last."""
    family = family_of(name)
    if family is None:
        return (float("inf"), 0)
    return (family.rank, number_of(name) or 0)


def kind_of(name: str) -> str | None:
    """IDENTITY, LINEAR or NETWORK for a model of a family, else None."""
    family = family_of(name)
    return family.kind if family is not None else None


def has_memory(name: str) -> bool:
    """Whether model `name` carries a state from sample to sample."""
    family = family_of(name)
    return family is not None and family.memory


def in_family(name: str, key: str) -> bool:
    """Whether model `name` belongs to the family `key` (e.g. ``in_family("poly3", POLY)``)."""
    family = family_of(name)
    return family is not None and family.key == key


def colour(name: str) -> str:
    """A model's figure colour (the same in every figure)."""
    family = family_of(name)
    if family is None:
        return OTHER_COLOUR
    return dict(family.colours).get(number_of(name) or 0, family.colour)


def describe(name: str) -> str:
    """What a model is, for the pages and the manifest."""
    family = family_of(name)
    return family.title if family is not None else name
