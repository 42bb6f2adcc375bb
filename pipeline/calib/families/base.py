"""What a model family is: its name, rank, colour and title, and the hooks training, cross-validation,
scoring, the export and the deployment tests call (`Family`); what a fitted model offers them (`Trained`).

Light on purpose (no numpy, no torch at import): the registry (`pipeline.calib.registry`) imports every
family to list them, and params and pages import the registry. A family's hooks import what they run.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import numpy as np

    from pipeline.calib.data import Group, GroupData
    from pipeline.calib.params import GroupParams
    from pipeline.calib.parts import GroupModel
    from pipeline.core.progress import ProgressLog

IDENTITY, LINEAR, NETWORK, WINDOW = "identity", "linear", "network", "window"
KINDS = (IDENTITY, LINEAR, NETWORK, WINDOW)  # the export forms (`pipeline.calib.parts`)


class Trained(Protocol):
    """One fitted model of a group, as training and cross-validation use it."""

    name: str
    n_inputs: int  # inputs per sensor it reads (6, 7 or 13)

    def predict(self, data: GroupData) -> np.ndarray:
        """(N, S, 6) calibrated wrenches (N, Nm, sensor frame) of `data`'s samples (with memory: from the
        state its logs' samples carry, `GroupData.memory`)."""

    def fidelity(self, data: GroupData) -> tuple[Callable[[np.ndarray], np.ndarray], np.ndarray | None]:
        """(x (N, S, n_inputs) -> (N, S, 6), the memory before each of `data`'s samples or None): what
        `pipeline.calib.fidelity` pushes on."""


@dataclass
class Task:
    """What a family fits on: one fold's training and validation samples of a group.

    On fold 0 the networks search their hyperparameters (`search`); on the other folds `first` holds fold
    0's models, whose hyperparameters and seeds a family refits with. `fitted` holds the models of the
    families this one starts from (`Family.after`), fitted on the same fold.
    """

    gp: GroupParams
    group: Group
    train: GroupData  # samples with at least one loss term
    val: GroupData  # every validation sample with ok inputs
    seed: int  # the group's derived seed (virtual pushes, initialisations)
    fold: int = 0
    fitted: Mapping[str, Trained] = field(default_factory=dict)
    first: Mapping[str, Trained] = field(default_factory=dict)  # fold 0's models (folds > 0)
    search: Any = None  # fold 0: the networks' studies (`Search`)


@dataclass(frozen=True)
class Job:
    """One unit of a family's fit, run in a forked process beside the others of its batch."""

    label: str  # what it fits (its timing's key in metrics.json)
    run: Callable[[], dict[str, Trained]]  # -> model name -> fitted model
    cost: float = 1.0  # relative wall time: the costliest start first
    what: str = ""  # what it does, in an error (default: its label)


@dataclass
class Saving:
    """What the families write into a group's output directory, and what they log to MLflow."""

    out: Path
    group: Group
    example: GroupData  # a few test samples (a logged model's input example)
    metrics: Mapping[str, Any]  # metrics.json so far (scores, cross-validation)
    baselines: dict[str, Any] = field(default_factory=dict)  # baselines.json: name -> closed-form model
    files: list[str] = field(default_factory=list)  # the files written, relative to `out`
    versions: dict[str, dict[str, str]] = field(default_factory=dict)  # registered MLflow model versions
    timings: dict[str, float] = field(default_factory=dict)  # s


@dataclass(frozen=True)
class Family:
    """One family of models (one module of `pipeline.calib.families`, or a `register`-ed instance).

    The hooks below are the defaults of a family that fits one model in one job; a family overrides what
    differs. Every hook is called with the family's own models only.
    """

    key: str  # the name of its model, or of every model with a number after it (numbered)
    rank: float  # complexity: cross-validation prefers a lower rank unless a higher one wins by the margin
    kind: str  # its export form: IDENTITY, LINEAR, NETWORK or WINDOW (`pipeline.calib.parts`)
    memory: bool  # calibrates from a state carried over the past samples as well as the present ones
    numbered: bool  # its names end in a number: poly<order>, nn<inputs per sensor>
    title: str  # what the pages and the manifest say it is
    colour: str  # its figure colour (the same in every figure) ...
    colours: tuple[tuple[int, str], ...] = ()  # ... or, per number of a numbered family, another
    after: tuple[str, ...] = ()  # the families whose models it starts from (fitted before it)
    inline: bool = False  # fitted in the training process before the others' jobs (cheap, and started from)
    float32: bool = False  # its stored predictions are computed in float32 (the reference on float32 inputs)
    one_on_tables: bool = False  # the per-phase tables show its best model on validation only ...
    on_tables: bool = True  # ... or none of its models (unless recommended)

    def name(self, number: int | None = None) -> str:
        """The name of a model of this family (`number`: a numbered family's order or inputs)."""
        if self.numbered != (number is not None):
            raise ValueError(f"{self.key}: {'a number is needed' if self.numbered else 'takes no number'}")
        return self.key if number is None else f"{self.key}{number}"

    # training ---------------------------------------------------------------------------------------------
    def names(self, gp: GroupParams, group: Group) -> list[str]:
        """The models it trains for a group (none: the group trains no model of it)."""
        return [] if self.numbered else [self.key]

    def fit(self, task: Task) -> dict[str, Trained]:
        """Its models fitted on `task`'s fold (fold 0, or a later fold from `task.first`)."""
        raise NotImplementedError(f"{self.key}: no fit")

    def jobs(self, task: Task) -> list[Job]:
        """Its fit as jobs that may run beside other families' (default: one job, `fit`)."""
        return [Job(self.key, lambda: self.fit(task))]

    def line(self, group: Group, fold: int, model: Trained) -> str | None:
        """A progress line on a model fitted on a fold (None: nothing to say)."""
        return None

    def record(self, models: Mapping[str, Trained], gp: GroupParams) -> dict[str, Any]:
        """Entries of metrics.json of its own (e.g. ``networks``: the searches' trials)."""
        return {}

    def save(self, saving: Saving, models: Mapping[str, Trained]) -> None:
        """Write its models into `saving.out` (or `saving.baselines`), log them to MLflow."""
        raise NotImplementedError(f"{self.key}: no save")

    # reading back: the export and the deployment tests --------------------------------------------------
    def read(self, model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
        """Model `name` of the train output `model_dir` in its export form (`pipeline.calib.parts`).

        Raises:
            DataError: its files are missing or unusable.
        """
        raise NotImplementedError(f"{self.key}: no export")

    def loaded(
        self, model_dir: Path, name: str, sensors: Sequence[str]
    ) -> tuple[Callable[[np.ndarray], np.ndarray], int] | None:
        """(one log's inputs x (N, S, n) in time order -> (N, S, 6) wrench, n): model `name` as the
        deployment tests run it (None: it has no predictor of its own, as raw)."""
        return None


@dataclass(frozen=True)
class Search:
    """Where fold 0's networks keep their Optuna studies (`pipeline.calib.studies`)."""

    seed: int  # params' seed
    url: str | None  # train.storage's database (None: a journal under `studies`)
    studies: Path
    heartbeat: float
    identity: Mapping[str, Any]  # what a study's result depends on (`pipeline.calib.run.study_identity`)
    ui: ProgressLog  # lines, no bars (a forked search)
