"""The ``nn<k>`` family: a network of k inputs per sensor (a Lipschitz-bounded correction of the affine map,
`pipeline.calib.models`), one per size of ``inputs``; its hyperparameters searched with Optuna on fold 0
(`pipeline.calib.search`), refitted with them on the other folds.

Saved as ``<name>.json`` + ``<name>.pt`` and logged to MLflow's model registry with its trials; exported as
one `pipeline.calib.parts.NetworkPart` per sensor.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.calib.families.base import NETWORK, Family, Job, Saving, Task
from pipeline.core.errors import DataError

if TYPE_CHECKING:
    import numpy as np

    from pipeline.calib.data import Group, GroupData
    from pipeline.calib.models import GroupNet
    from pipeline.calib.params import GroupParams
    from pipeline.calib.parts import GroupModel
    from pipeline.calib.search import NetResult


@dataclass
class NetModel:
    """A trained network (`Trained`): its search's result on fold 0, its refit's history on another."""

    name: str
    model: GroupNet
    history: list[dict[str, float]] = field(default_factory=list)
    seconds: float = 0.0
    result: NetResult | None = None  # fold 0: the search (trials, hyperparameters, seed)

    @property
    def n_inputs(self) -> int:
        return int(self.model.config.n_inputs)

    def predict(self, data: GroupData) -> np.ndarray:
        from pipeline.calib.training import predict

        return predict(self.model, data)

    def fidelity(self, data: GroupData) -> tuple[Callable[..., np.ndarray], None]:
        from pipeline.calib.training import predict_inputs

        return partial(predict_inputs, self.model), None


class Networks(Family):
    def names(self, gp: GroupParams, group: Group) -> list[str]:
        return [self.name(n) for n in gp.inputs]

    def jobs(self, task: Task) -> list[Job]:
        fit = self._search if task.fold == 0 else self._refit
        names = self.names(task.gp, task.group)
        sizes = [int(name[len(self.key) :]) for name in names]
        what = [f"search of the {n}-input network" if task.fold == 0 else "" for n in sizes]
        return [Job(nm, partial(fit, task, n), 2.0, w) for nm, n, w in zip(names, sizes, what, strict=True)]

    def _search(self, task: Task, n_inputs: int) -> dict[str, NetModel]:
        from pipeline.calib.search import search_network
        from pipeline.calib.studies import open_storage
        from pipeline.calib.training import one_thread

        one_thread()
        s = task.search
        storage = open_storage(s.url, s.studies, s.heartbeat)
        start = task.fitted["affine"].model
        r = search_network(
            task.gp,
            task.group,
            task.train,
            task.val,
            n_inputs,
            s.seed,
            storage,
            s.identity,
            s.ui,
            None,
            start,
        )
        name = self.name(n_inputs)
        return {name: NetModel(name, r.model, r.history, r.seconds, r)}

    def _refit(self, task: Task, n_inputs: int) -> dict[str, NetModel]:
        from pipeline.calib.training import NetSetting, one_thread, train_network

        name, t = self.name(n_inputs), time.perf_counter()
        one_thread()
        r = task.first[name].result
        setting = NetSetting.of(task.gp, n_inputs, r.values)
        start = task.fitted["affine"].model
        model, history = train_network(task.group, task.train, task.val, setting, r.seed, None, start)
        return {name: NetModel(name, model, history, time.perf_counter() - t)}

    def line(self, group: Group, fold: int, model: NetModel) -> str | None:
        if fold == 0:  # the search said it
            return None
        best = min(model.history, key=lambda h: h["val_rmse"])
        return (
            f"{group.name} fold {fold + 1}: {model.name} val RMSE {best['val_rmse']:.4g} "
            f"(epoch {int(best['epoch']) + 1}) {model.seconds:.1f} s"
        )

    def record(self, models: Mapping[str, NetModel], gp: GroupParams) -> dict[str, Any]:
        from pipeline.calib.training import NetSetting

        return {
            "networks": {
                name: {
                    "trial": r.trial,
                    "hyperparameters": asdict(NetSetting.of(gp, r.model.config.n_inputs, r.values)),
                    "seed": r.seed,
                    "best_epoch": r.best_epoch,
                    "val_rmse_labelled": r.val_rmse,
                    "study": r.study,
                    "trials_run": r.trials_run,
                    "trials_reused": r.trials_reused,
                    "trials_pruned": r.trials_pruned,
                    "history": r.history,
                }
                for name, m in models.items()
                for r in [m.result]
            }
        }

    def save(self, saving: Saving, models: Mapping[str, NetModel]) -> None:
        """``<name>.json`` + ``.pt`` each, its trials as nested MLflow runs, the network registered."""
        from pipeline.calib.data import input_cols
        from pipeline.calib.models import save_model
        from pipeline.calib.records import log_network, log_trial_run
        from pipeline.calib.training import flat_inputs
        from pipeline.logs import schema as S

        group = saving.group
        for name, m in models.items():
            r = m.result
            info = {
                "group": group.name,
                "sensors": list(group.sensors),
                "input_columns": [c for s in group.sensors for c in input_cols(s, m.n_inputs)],
                "output_columns": [c for s in group.sensors for c in S.wrench_cols(S.FT, s)],
                "hyperparameters": saving.metrics["networks"][name]["hyperparameters"],
                "study": r.study,
                "trial": r.trial,
            }
            save_model(saving.out / name, m.model, info)
            saving.files += [f"{name}.json", f"{name}.pt"]
            t = time.perf_counter()
            log = log_trial_run(group.name, name)
            for record in r.trials:
                log(*record)
            columns = {k: info[k] for k in ("group", "sensors", "input_columns", "output_columns")}
            x = flat_inputs(saving.example, m.n_inputs)
            saving.versions[name] = log_network(group, name, m.model, x, columns)
            saving.timings[f"log_{name}"] = time.perf_counter() - t

    def read(self, model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
        return read_network(model_dir, name, group, sensors, self.key)

    def loaded(self, model_dir: Path, name: str, sensors: Sequence[str]) -> tuple[Callable, int]:
        """The network in float32, as trained (a sample with a non-finite input: NaN)."""
        import numpy as np
        import torch

        from pipeline.calib.models import load_model

        net, config = load_model(model_dir / name)
        n = int(config["net"]["n_inputs"])

        def predict(x: np.ndarray) -> np.ndarray:
            x = x[:, :, :n]
            bad = ~np.isfinite(x).all(axis=(1, 2))
            with torch.no_grad():
                flat = torch.as_tensor(np.nan_to_num(x).reshape(len(x), -1), dtype=torch.float32)
                y = net(flat).numpy()
            y = y.astype(np.float64).reshape(len(x), len(sensors), 6)
            y[bad] = np.nan
            return y

        return predict, n


def read_network(model_dir: Path, name: str, group: str, sensors: tuple[str, ...], family: str) -> GroupModel:
    """A saved network in its export form: one `NetworkPart` per sensor, its reference in float64."""
    import numpy as np
    import torch
    from torch import nn

    from pipeline.calib.models import load_model
    from pipeline.calib.parts import Dense, GroupModel, NetworkPart, input_columns, output_columns

    model, config = load_model(model_dir / name)
    n_inputs = int(model.config.n_inputs)
    if tuple(config.get("sensors", sensors)) != sensors:
        raise DataError(
            f"{model_dir / name}.json: sensors {config.get('sensors')} differ from metrics.json's"
        )
    kinds = {nn.ReLU: ("relu", 0.0), nn.Tanh: ("tanh", 0.0)}
    parts = []
    for net in model.nets:
        layers: list[Dense] = []
        for module in net.mlp:
            if isinstance(module, nn.Linear):
                w = module.weight.detach().double().numpy().copy()
                layers.append(Dense(w, module.bias.detach().double().numpy().copy()))
                continue
            if isinstance(module, nn.LeakyReLU):
                kind = ("leaky_relu", float(module.negative_slope))
            elif isinstance(module, nn.ELU):
                kind = ("elu", float(module.alpha))
            elif type(module) in kinds:
                kind = kinds[type(module)]
            else:
                raise DataError(f"{model_dir / name}: layer {type(module).__name__} cannot be exported")
            last = layers[-1]
            layers[-1] = Dense(last.weight, last.bias, kind[0], kind[1])
        f64 = [t.double().numpy().copy() for t in (net.in_offset, net.in_scale, net.out_scale)]
        affine = [t.double().numpy().copy() for t in (net.affine_weight, net.affine_bias)]
        parts.append(NetworkPart(*f64, tuple(layers), *affine))
    reference_model = model.double().eval()

    def reference(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return reference_model(torch.tensor(np.asarray(x, dtype=np.float64))).numpy()

    info = {k: config[k] for k in ("hyperparameters", "study", "trial") if k in config}
    inputs = [c for s in sensors for c in input_columns(s, n_inputs)]
    outputs = [c for s in sensors for c in output_columns(s)]
    return GroupModel(group, name, family, sensors, n_inputs, tuple(parts), inputs, outputs, reference, info)


FAMILY = Networks(
    "nn", 6, NETWORK, False, True, "neural network (a Lipschitz-bounded correction of the affine map)",
    "#1f77b4", ((13, "#d62728"),),
    after=("affine",), float32=True,
)  # fmt: skip
