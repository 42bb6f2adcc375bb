"""The model families of ftcal: one entry each, where training, scoring, export, the deployment tests and the
pages find a family by the name of one of its models.

A model's name is its family's key, followed for a numbered family by its number: ``raw``, ``offset`` (the
factory map with a constant correction: what a re-zeroing does), ``affine``,
``poly2`` (a polynomial of order 2), ``play`` (the affine map with play-operator features of the raw
wrench: memory), ``arx`` (the affine map with low-pass departures of the raw wrench: memory), ``nn7`` (a
network of 7 inputs per sensor), ``win`` (a network over a causal window of the raw wrench correcting the play
model: memory). The families, simplest first (the order in which cross-validation walks
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

from dataclasses import dataclass

IDENTITY, LINEAR, NETWORK, WINDOW = "identity", "linear", "network", "window"
KINDS = (IDENTITY, LINEAR, NETWORK, WINDOW)


@dataclass(frozen=True)
class Family:
    """One family of models."""

    key: str  # the name of its model, or of every model with a number after it (numbered)
    rank: int  # complexity: cross-validation prefers a lower rank unless a higher one wins by the margin
    kind: str  # IDENTITY (the raw wrench), LINEAR (closed-form, baselines.json), NETWORK (nn<k>.json + .pt),
    # WINDOW (win.json: the play model and its networks' weights)
    memory: bool  # calibrates from a state carried over the past samples as well as the present ones
    numbered: bool  # its names end in a number: poly<order>, nn<inputs per sensor>
    title: str  # what the pages and the manifest say it is
    colour: str  # its figure colour (the same in every figure) ...
    colours: tuple[tuple[int, str], ...] = ()  # ... or, per number of a numbered family, another

    def name(self, number: int | None = None) -> str:
        """The name of a model of this family (`number`: a numbered family's order or inputs)."""
        if self.numbered != (number is not None):
            raise ValueError(f"{self.key}: {'a number is needed' if self.numbered else 'takes no number'}")
        return self.key if number is None else f"{self.key}{number}"


FAMILIES = (
    Family("raw", 0, IDENTITY, False, False, "the factory map (the raw wrench)", "#8c8c8c"),
    Family("offset", 1, LINEAR, False, False, "the factory map and a constant offset (least squares: the "
           "factory's gains kept, as a re-zeroing does)", "#393b79"),
    Family("affine", 2, LINEAR, False, False, "affine map with temperature (least squares)", "#bcbd22"),
    Family("poly", 3, LINEAR, False, True, "polynomial of wrench and temperature (ridge)", "#c8553d",
           ((1, "#d9b36c"), (2, "#e0894a"), (3, "#c8553d"), (4, "#8c2d04"))),
    Family("play", 4, LINEAR, True, False, "affine map and play operators of the raw wrench (memory: "
           "hysteresis)", "#9467bd"),
    Family("arx", 5, LINEAR, True, False, "affine map and low-pass departures of the raw wrench (memory: a "
           "lagged linear map, ARX with fixed poles)", "#17becf"),
    Family("nn", 6, NETWORK, False, True, "neural network (a Lipschitz-bounded correction of the affine map)",
           "#1f77b4", ((13, "#d62728"),)),
    Family("win", 7, WINDOW, True, False, "windowed network (a Lipschitz-bounded correction of the play "
           "model over a causal window of the raw wrench: memory)", "#8c564b"),
)  # fmt: skip
BY_KEY = {f.key: f for f in FAMILIES}
RAW, OFFSET, AFFINE, POLY, PLAY, ARX, NN, WIN = (f.key for f in FAMILIES)
OTHER_COLOUR = "#7f7f7f"  # a name of no family (the oracle and the labels have their own colours)


def nn_name(n_inputs: int) -> str:
    """The network with `n_inputs` inputs per sensor: nn7, nn13."""
    return BY_KEY[NN].name(n_inputs)


def poly_name(order: int) -> str:
    """The polynomial of `order`: poly2, ..."""
    return BY_KEY[POLY].name(order)


def patterns() -> list[str]:
    """Every family's model name, simplest first: raw, affine, poly<n>, play, arx, nn<n>, win."""
    return [f"{f.key}<n>" if f.numbered else f.key for f in sorted(FAMILIES, key=lambda f: f.rank)]


def family_of(name: str) -> Family | None:
    """The family of model `name` (None: not a model of any family, e.g. ``oracle``)."""
    for family in FAMILIES:
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


def complexity(name: str) -> tuple[int, int]:
    """Sort key, simplest first: the family's rank, then its number (poly1 < poly4, nn7 < nn13); a name of
    no family last."""
    family = family_of(name)
    if family is None:
        return (len(FAMILIES), 0)
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
