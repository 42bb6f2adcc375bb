"""Would a recurrent network calibrate better than the play model? Measured on a run of simulated logs.

For each single-sensor group of the run (``models/<group>`` with a ``play`` model), a GRU correction of the
group's own affine map (``baselines.json``'s ``affine``, fitted with the virtual pushes, held fixed; with
``--base play`` of its play model, run over each log from a fresh state: what a recurrent network adds to the
hysteresis the play operators already carry) is trained on the group's training logs, whole logs in time
order: truncated back-propagation over chunks of consecutive samples, the hidden state carried from chunk to
chunk and reset at each log's start (as a runtime carries it), the switched loss on the exact samples
(``sw.<sensor>``), per axis scaled by the label's spread, the epoch kept that is best on the run's validation
logs (its `train` split, seeded from params).
On the test logs, run from a fresh state over every sample, it is scored against the true wrench on every
test sample (the evaluate stage's own join, `pipeline.evaluation.inputs.load_group`), beside the run's
affine, play and recommended models and the oracle, the 6 axes pooled (N and Nm). Then a held push: +20 N
on the raw fx for 100 samples from each of 200 seeded onsets, the calibrated fx's change / 20 at the onset,
10 and 99 samples later (a faithful calibration reads about the oracle's slope, the same at all three), for
the GRU and the play model.

    python benchmarks/recurrent.py [--run .] [--groups r_arm_ft l_arm_ft] [--hidden 16] [--epochs 40]
    python benchmarks/recurrent.py --base play
    python benchmarks/recurrent.py --base play --model window [--slope 0.05]
    python benchmarks/recurrent.py --quick   # 1 epoch, hidden 4, the first group: every step, no figure

``--model window`` trains a windowed network instead of the GRU: an MLP over a causal window of the raw
wrench (the samples `LAGS` back, a log's first sample before its start) and the temperature, whose
correction is Lipschitz-bounded as the project's networks are (`pipeline.calib.models.LipschitzLinear`, in
push units, `pipeline.calib.pushes.residual_units`): a push held over the whole window changes it by at most
``--slope`` times the push. Its samples are shuffled (each carries its own past), the epoch best on the
validation logs kept.

Needs a run of simulated logs after `dvc repro` (truth tables in data/ingested). The last line is the
largest ratio model / play of the RMSE against truth over the groups.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.calib.data import GroupData, find_logs, load_group_data  # noqa: E402
from pipeline.calib.fit import prepare  # noqa: E402
from pipeline.calib.linear import LinearBaseline  # noqa: E402
from pipeline.calib.models import LipschitzLinear  # noqa: E402
from pipeline.calib.pushes import residual_units  # noqa: E402
from pipeline.calib.scores import WRENCH  # noqa: E402
from pipeline.core.config import load_params, stage_section  # noqa: E402
from pipeline.evaluation.inputs import load_group  # noqa: E402
from pipeline.evaluation.params import EvaluateParams  # noqa: E402
from pipeline.logs import schema as S  # noqa: E402

CHUNK = 512  # samples per step of truncated back-propagation
PUSH_N, HELD, ONSETS = 20.0, 100, 200  # the held push: N on fx, samples, onsets
DIRS = (("labelled", "data/labelled"), ("ingested", "data/ingested"), ("models", "models"))
LAGS = np.array([0, 2, 5, 10, 20, 50, 100, 200])  # the window's samples, this many back
BATCH = 512  # the windowed network's minibatch
Base = Callable[[np.ndarray], np.ndarray]  # one log's raw inputs (N, 7) in time order -> calibrated (N, 6)


class Correction(nn.Module):
    """The GRU's correction (N, Nm) of the affine map: a linear head on a GRU over the standardised inputs."""

    def __init__(self, n_inputs: int, hidden: int, scale: np.ndarray) -> None:
        super().__init__()
        self.gru = nn.GRU(n_inputs, hidden, batch_first=True)
        self.head = nn.Linear(hidden, WRENCH)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)  # starts at the affine map
        self.register_buffer("scale", torch.tensor(scale, dtype=torch.float32))

    def forward(self, z: torch.Tensor, h: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        y, h = self.gru(z, h)
        return self.head(y) * self.scale, h


def _logs(data: GroupData, names: list[str]) -> list[dict[str, np.ndarray]]:
    """Per log of `data` (a one-sensor GroupData), in time order: x (N, 7), labels (N, 6), exact, stamp."""
    out = []
    for k in dict.fromkeys(data.log.tolist()):
        rows = np.flatnonzero(data.log == k)
        rows = rows[np.argsort(data.stamp[rows], kind="stable")]
        out.append({"name": names[k], "x": data.x[rows, 0, :7], "labels": data.labels[rows, 0],
                    "exact": data.switches[rows, 0], "stamp": data.stamp[rows]})  # fmt: skip
    return out


def _correction(net: Correction, x: np.ndarray, mu: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """(N, 6) the GRU's correction (N, Nm) over one log's raw inputs x (N, 7) from a fresh state."""
    z = torch.tensor((x - mu) / sd, dtype=torch.float32)[None]
    with torch.no_grad():
        return net(z)[0][0].numpy().astype(np.float64)


def _run(net: Correction, base: Base, log: dict, mu: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """(N, 6) the calibrated wrench of one log from a fresh state: the base model's plus the GRU's."""
    return base(log["x"]) + _correction(net, log["x"], mu, sd)


def _train(logs: list[dict], val: list[dict], base: Base, hidden: int, epochs: int, seed: int):
    """The GRU correction trained on `logs`, the epoch best on `val` kept (module docstring)."""
    torch.manual_seed(seed)
    x = np.concatenate([g["x"] for g in logs])
    mu, sd = x.mean(axis=0), np.where(x.std(axis=0) > 1e-9, x.std(axis=0), 1.0)
    targets = [g["labels"] - base(g["x"]) for g in logs]  # what the GRU must add
    exact = np.concatenate([t[g["exact"]] for t, g in zip(targets, logs, strict=True)])
    scale = np.nanstd(exact, axis=0) + 1e-6
    net = Correction(x.shape[1], hidden, scale)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    best, state = np.inf, None
    val_targets = [g["labels"] - base(g["x"]) for g in val]  # the base model's part, once
    for _ in range(epochs):
        for g, target in zip(logs, targets, strict=True):
            z = torch.tensor((g["x"] - mu) / sd, dtype=torch.float32)[None]
            t = torch.tensor(np.nan_to_num(target) / scale, dtype=torch.float32)[None]
            m = torch.tensor(g["exact"], dtype=torch.float32)[None, :, None]
            h = None
            for lo in range(0, z.shape[1], CHUNK):
                out, h = net(z[:, lo : lo + CHUNK], h)
                err = (out / net.scale - t[:, lo : lo + CHUNK]) ** 2 * m[:, lo : lo + CHUNK]
                loss = err.sum() / m[:, lo : lo + CHUNK].sum().clamp(min=1.0) / WRENCH
                opt.zero_grad()
                loss.backward()
                opt.step()
                h = h.detach()
        score = np.mean(
            [
                np.nanmean(((_correction(net, g["x"], mu, sd) - target)[g["exact"]]) ** 2)
                for g, target in zip(val, val_targets, strict=True)
            ]
        )
        if score < best:
            best, state = score, {k: v.clone() for k, v in net.state_dict().items()}
    net.load_state_dict(state)
    return net, mu, sd


class Window(nn.Module):
    """The windowed network's correction (N, Nm): a Lipschitz-bounded MLP over `window_inputs` (module
    docstring); its output layer starts at zero (the base model)."""

    def __init__(self, n_inputs: int, hidden: int, out: np.ndarray) -> None:
        super().__init__()
        self.mlp = nn.Sequential(
            LipschitzLinear(n_inputs, hidden), nn.LeakyReLU(), LipschitzLinear(hidden, hidden), nn.ReLU(),
            LipschitzLinear(hidden, WRENCH),
        )  # fmt: skip
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)
        self.register_buffer("mean", torch.zeros(n_inputs))
        self.register_buffer("out", torch.tensor(out, dtype=torch.float32))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.mlp(z - self.mean) * self.out


def window_inputs(x: np.ndarray, units: np.ndarray) -> np.ndarray:
    """(N, 6 len(LAGS) + 1) one log's window (raw wrench at each lag, then the temperature) in push units;
    x (N, 7) in time order."""
    rows = np.maximum(np.arange(len(x))[:, None] - LAGS[None], 0)
    return np.concatenate(
        [(x[:, :WRENCH][rows] / units[:WRENCH]).reshape(len(x), -1), x[:, 6:7] / units[6]], 1
    )


def _train_window(logs: list[dict], val: list[dict], base: Base, units: np.ndarray, slope: float, hidden: int,
                  epochs: int, seed: int) -> Base:  # fmt: skip
    """The windowed network trained on `logs`' exact samples, best epoch on `val`: its calibration."""
    torch.manual_seed(seed)

    def samples(group: list[dict]) -> tuple[torch.Tensor, torch.Tensor]:
        z = np.concatenate([window_inputs(g["x"], units) for g in group])
        t = np.concatenate([g["labels"] - base(g["x"]) for g in group])
        ok = np.concatenate([g["exact"] for g in group]) & np.isfinite(t).all(1) & np.isfinite(z).all(1)
        return torch.tensor(z[ok], dtype=torch.float32), torch.tensor(t[ok], dtype=torch.float32)

    (z, t), (zv, tv) = samples(logs), samples(val)
    scale = t.std(dim=0) + 1e-6
    # a push held over the whole window moves every lag: the bound shared among them
    net = Window(z.shape[1], hidden, slope / np.sqrt(len(LAGS)) * units[:WRENCH])
    net.mean.copy_(z.mean(dim=0))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    best, state, order = np.inf, None, torch.Generator().manual_seed(seed)
    for _ in range(epochs):
        perm = torch.randperm(len(z), generator=order)
        for lo in range(0, len(z), BATCH):
            b = perm[lo : lo + BATCH]
            loss = (((net(z[b]) - t[b]) / scale) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            score = float((((net(zv) - tv) / scale) ** 2).mean())
        if score < best:
            best, state = score, {k: v.clone() for k, v in net.state_dict().items()}
    net.load_state_dict(state)

    def calibrate(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            z = torch.tensor(window_inputs(x, units), dtype=torch.float32)
            return base(x) + net(z).numpy().astype(np.float64)

    return calibrate


def _push_slopes(predict, log: dict, rng: np.random.Generator) -> list[float]:
    """The mean change of the calibrated fx / PUSH_N at the onset, 10 and 99 samples into a held push."""
    x = log["x"]
    base = predict(x)
    onsets = rng.choice(np.arange(20, len(x) - HELD), size=min(ONSETS, len(x) - HELD - 20), replace=False)
    out = []
    for k in onsets:
        pushed = x[: k + HELD].copy()
        pushed[k:, 0] += PUSH_N  # predict on the prefix: a causal model's output there is the whole log's
        y = predict(pushed)
        out.append([(y[k + d, 0] - base[k + d, 0]) / PUSH_N for d in (0, 10, HELD - 1)])
    return np.mean(out, axis=0).round(3).tolist()


def _group(dirs: dict[str, Path], params, name: str, args: argparse.Namespace) -> dict:
    """One group's figures (module docstring); `dirs`: labelled, ingested and models directories."""
    labelled, gdir = dirs["labelled"], dirs["models"] / name
    prep = prepare(params, name, labelled)
    logs = find_logs(labelled)
    by_name = {log.name: log for log in logs}
    baselines = json.loads((gdir / "baselines.json").read_text())
    affine, play = (LinearBaseline.from_dict(baselines[m]) for m in ("affine", "play"))
    bases: dict[str, Base] = {
        "affine": lambda x: affine.predict(x[:, None])[:, 0],
        "play": lambda x: play.predict_log(x[:, None])[:, 0],  # the memory from a fresh state
    }
    base = bases[args.base]
    names = prep.log_names

    def read(split: str) -> list[dict]:
        data = load_group_data(prep.group, [by_name[n] for n in prep.split[split]])
        data.log = np.array([names.index(n) for n in prep.split[split]])[data.log]
        return _logs(data, names)

    train, val, test = read("train"), read("val"), _logs(prep.test, names)
    if args.model == "gru":
        net, mu, sd = _train(train, val, base, args.hidden, args.epochs, params.seed)
        calibrate = lambda x: _run(net, base, {"x": x}, mu, sd)  # noqa: E731
    else:
        units = residual_units(prep.gp.push_force_n, prep.gp.push_lever_m, 7)
        calibrate = _train_window(train, val, base, units, args.slope, args.hidden, args.epochs, params.seed)
    cfg = stage_section(params, "evaluate", EvaluateParams)
    frame = load_group(name, gdir, labelled, dirs["ingested"], cfg).frame  # evaluate's own join
    sensor = prep.group.sensors[0]
    true = frame[S.wrench_cols(S.TRUE, sensor)].to_numpy(np.float64)
    runs = {g["name"]: dict(zip(g["stamp"].tolist(), calibrate(g["x"]), strict=True)) for g in test}
    nan = np.full(WRENCH, np.nan)
    keys = zip(frame[S.LOG], frame[S.STAMP], strict=True)
    ours = np.array([runs.get(log, {}).get(int(t), nan) for log, t in keys])
    ok = np.isfinite(true).all(axis=1) & np.isfinite(ours).all(axis=1)  # the same samples for every model
    out = {"group": name, "samples": int(ok.sum()), "unmatched": int((~np.isfinite(ours).all(axis=1)).sum())}
    for model in ("affine", "play", "oracle"):
        pred = frame[S.prediction_cols(model, sensor)].to_numpy(np.float64)
        out[model] = float(np.sqrt(np.mean((pred[ok] - true[ok]) ** 2)))
    out["model"] = float(np.sqrt(np.mean((ours[ok] - true[ok]) ** 2)))
    rng = np.random.default_rng(params.seed)
    longest = max(test, key=lambda g: len(g["x"]))
    if args.quick:
        longest = {**longest, "x": longest["x"][: HELD + 60]}
    out["push_model"] = _push_slopes(calibrate, longest, rng)
    out["push_play"] = _push_slopes(bases["play"], longest, rng)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, default=Path("."), help="a run directory after dvc repro")
    ap.add_argument("--params", type=Path, help="its params.yaml (default RUN/params.yaml)")
    for n, where in DIRS:
        ap.add_argument(f"--{n}", type=Path, help=f"default RUN/{where}")
    ap.add_argument("--groups", nargs="*", help="single-sensor groups (default: every one with a play model)")
    ap.add_argument(
        "--base", choices=("affine", "play"), default="affine", help="the model the network corrects"
    )
    ap.add_argument("--model", choices=("gru", "window"), default="gru", help="the network with memory")
    ap.add_argument("--slope", type=float, default=0.05, help="the windowed network's bound, push units")
    ap.add_argument("--hidden", type=int, help="hidden units (default: GRU 16, windowed network 64)")
    ap.add_argument("--epochs", type=int, default=40, help="passes over the training logs")
    ap.add_argument("--quick", action="store_true", help="1 epoch, hidden 4, the first group: no figure")
    args = ap.parse_args()
    torch.set_num_threads(1)
    params = load_params(args.params or args.run / "params.yaml")
    dirs = {n: getattr(args, n) or args.run / where for n, where in DIRS}
    metrics = {p.parent.name: json.loads(p.read_text()) for p in dirs["models"].glob("*/metrics.json")}
    groups = args.groups or sorted(
        g for g, m in metrics.items() if len(m.get("sensors", [])) == 1 and "play" in m.get("test", {})
    )
    if not groups or not any(dirs["ingested"].glob("*.truth.parquet")):
        sys.exit(f"recurrent: {args.run}: no single-sensor group with a play model, or no truth tables")
    args.hidden = args.hidden or (16 if args.model == "gru" else 64)
    if args.quick:
        groups, args.epochs, args.hidden = groups[:1], 1, 4
    t0, rows = time.perf_counter(), []
    for name in groups:
        rows.append(_group(dirs, params, name, args))
    kind = "GRU" if args.model == "gru" else f"windowed network (bound {args.slope:g})"
    m = args.model
    print(
        f"{kind}, {args.hidden} hidden, {args.epochs} epochs, correcting the {args.base} model; "
        "RMSE against truth, every test sample, 6 axes"
    )
    print(f"{'group':<12} {'affine':>7} {'play':>7} {m:>7} {'oracle':>7}  push fx / 20 N: onset, 10, 99")
    for r in rows:
        print(f"{r['group']:<12} {r['affine']:7.3f} {r['play']:7.3f} {r['model']:7.3f} {r['oracle']:7.3f}  "
              f"{m} {r['push_model']}  play {r['push_play']}")  # fmt: skip
        print(f"{'':<12} on {r['samples']} test samples ({r['unmatched']} without the {m}'s output)")
    print(f"{time.perf_counter() - t0:.0f} s")
    print(f"largest ratio {m} / play (RMSE against truth): {max(r['model'] / r['play'] for r in rows):.3f}")


if __name__ == "__main__":
    main()
