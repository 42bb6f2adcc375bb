"""Test fixtures: YARP dataDumper runs written from MCAP contract logs, as the dumper prints them.

A run is a folder of port folders ``{info.log,data.log}`` (../shared/reference/yarp-datadumper-format.md):
the dumper's layout ``<run>/<robot>/<part>/<port>/`` (`dumper_folder`), or folders a lab's recorder named
(`recorder_folder`: ``rightLegFT/``, ``joints/rightLegPos/``); info.log names the port
(``/icub/right_leg/analog:o``), and since YARP 3.2 the stamp form (``Stamp: tx;`` or ``tx+rx;``).
Lines are ``<seq> <time> [<reception time>] <payload>``; times with 6 decimals; numbers as YARP prints a
double (6 decimals, trailing zeros dropped, at least one: ``0.0``, ``1.101``). FT parts' ``analog:o``
carry the 6 wrench values; control boards' ``stateExt:o`` 10 groups, each ``(values) [status]``:
positions (deg), velocities (deg/s), accelerations (zeros), motor positions / velocities /
accelerations (copies), torques (Nm; ``[er]`` when the log has none), PWM, and two groups of modes;
their ``state:o`` the positions alone (deg), one plain vector (the control-board wrapper's
``yarp::sig::Vector`` of encoders, printed by the dumper as a Bottle).

`mcap_to_run` writes every part of the maps it is given from the log's joint states and wrenches, in the
log's arrival order (the dumper writes what it receives when it receives it), plus the experiment sidecar
``<run>.yaml`` beside the run. Ports can be left without their ``data.log`` (``info.log`` only), as real
archives keep them: any ``part/port`` (`without_data`), or the joint streams of whole parts
(`without_joints`, e.g. both arms, as the 2016 yoga run of ../shared/data).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import yaml

from pipeline.core.config import TopicParams
from pipeline.logs import rosmsg
from pipeline.logs.matlog import ns_to_seconds

DEG = 180.0 / np.pi


def yarp_number(value: float) -> str:
    """A double as a YARP Bottle prints it: %.6f without trailing zeros (one kept after the point)."""
    if not np.isfinite(value):
        return "nan"
    text = f"{value:.6f}".rstrip("0")
    return text + "0" if text.endswith(".") else text


def _group(values: Sequence[float], status: str = "ok") -> str:
    return "(" + " ".join(yarp_number(v) for v in values) + f") [{status}]"


def _times(stamp_s: float, recv_s: float | None) -> str:
    return f"{stamp_s:.6f}" if recv_s is None else f"{stamp_s:.6f} {recv_s:.6f}"


def _arrival(batches: Sequence[rosmsg.Batch]) -> dict[str, np.ndarray]:
    data = rosmsg.concat_batches(batches)
    order = np.lexsort((data["order"], data["log_time_ns"]))
    return {k: v[order] for k, v in data.items()}


def dumper_folder(robot: str, part: str, port: str) -> str:
    """The dumper's own layout: ``<robot>/<part>/<port>``."""
    return f"{robot}/{part}/{port}"


def recorder_folder(robot: str, part: str, port: str) -> str:
    """Folders a lab's recorder named, at two depths: ``rightLegFT`` (FT ports), ``joints/rightLegPos``."""
    first, *rest = part.split("_")
    name = first + "".join(word.title() for word in rest)
    return f"{name}FT" if port == "analog:o" else f"joints/{name}Pos"


def write_port(
    folder: Path, lines: Sequence[str] | None, port_name: str, t0: float, stamp: str | None = None
) -> None:
    """A port folder: info.log (with the ``Stamp:`` line of `stamp`, ``tx`` or ``tx+rx``, if given), and
    data.log unless `lines` is None (a port that never sent)."""
    folder.mkdir(parents=True, exist_ok=True)
    stamp_line = f"Stamp: {stamp};\n" if stamp else ""
    (folder / "info.log").write_text(
        f"Type: Bottle;\n{stamp_line}[{t0:.6f}] {port_name} [connected]\n"
        f"[{t0 + 60:.6f}] {port_name} [disconnected]\n"
    )
    if lines is not None:
        (folder / "data.log").write_text("".join(line + "\n" for line in lines))


def state_lines(
    stamps_ns: np.ndarray, recv_ns: np.ndarray | None, q: np.ndarray, dq: np.ndarray, tau: np.ndarray | None
) -> list[str]:
    """stateExt:o lines of one board: q (M, A) rad, dq (M, A) rad/s, tau (M, A) Nm or None."""
    t, r = ns_to_seconds(stamps_ns), None if recv_ns is None else ns_to_seconds(recv_ns)
    zeros = [0.0] * q.shape[1]
    lines = []
    for k in range(len(t)):
        groups = [
            _group(q[k] * DEG),
            _group(dq[k] * DEG),
            _group(zeros),
            _group(q[k] * DEG * 100),
            _group(dq[k] * DEG * 100),
            _group(zeros),
            _group(tau[k]) if tau is not None else _group(zeros, "er"),
            _group(zeros),
            _group([1903325044] * q.shape[1]),
            _group([1718187123] * q.shape[1]),
        ]
        head = f"{(20000 + k) % 32768} {_times(t[k], None if r is None else r[k])}"
        lines.append(head + " " + " ".join(groups))
    return lines


def vector_lines(
    stamps_ns: np.ndarray, recv_ns: np.ndarray | None, values: np.ndarray, seq0: int
) -> list[str]:
    """Plain-vector lines ``<seq> <time> [<time>] v1 ... vn`` of one port: values (M, n)."""
    t, r = ns_to_seconds(stamps_ns), None if recv_ns is None else ns_to_seconds(recv_ns)
    return [
        f"{(seq0 + k) % 32768} {_times(t[k], None if r is None else r[k])} "
        + " ".join(yarp_number(v) for v in values[k])
        for k in range(len(t))
    ]


def analog_lines(stamps_ns: np.ndarray, recv_ns: np.ndarray | None, wrench: np.ndarray) -> list[str]:
    """analog:o lines of one FT board: wrench (M, 6) N, Nm."""
    return vector_lines(stamps_ns, recv_ns, wrench, 29000)


def mcap_to_run(
    mcap: Path,
    run: Path,
    topics: TopicParams,
    ft_ports: Mapping[str, str],
    joint_map: Mapping[str, Sequence[str | None]],
    *,
    two_times: bool = False,
    without_data: Sequence[str] = (),
    without_joints: Sequence[str] = (),
    robot: str = "icub",
    sidecar: Mapping[str, object] | None = None,
    joint_port: str = "stateExt:o",
    folder: Callable[[str, str, str], str] = dumper_folder,
    stamp_line: bool = False,
) -> Path:
    """Write the MCAP log's joint states and wrenches as the dataDumper run `run`.

    `ft_ports`: part -> sensor; `joint_map`: part -> joint per axis (None: an axis the log does not have,
    written as 0). `without_data`: ``part/port`` ports written with info.log only; `without_joints`: parts
    whose joint port gets info.log only (an absent joint stream). `two_times`: lines carry the reception time
    (the MCAP log time) after the stamp. `joint_port`: the boards' ``stateExt:o`` or ``state:o``; `folder`:
    (robot, part, port) -> the port's folder under the run; `stamp_line`: info.log says the stamp form, as
    dumpers since YARP 3.2 do. The experiment record (or `sidecar`) goes to ``<run>.yaml``.
    """
    without_data = [*without_data, *(f"{part}/{joint_port}" for part in without_joints)]
    with rosmsg.LogReader(mcap) as reader:
        experiment = dict(reader.metadata.get("experiment", {}))
        read = reader.read()
    js = _arrival(read[topics.joint_states])
    names = list(read[topics.joint_states][0].names or ())
    t0 = float(ns_to_seconds(js["stamp_ns"][:1])[0]) - 0.1
    recv = js["log_time_ns"] if two_times else None
    stamp = ("tx+rx" if two_times else "tx") if stamp_line else None
    for part, axes in joint_map.items():
        cols = [names.index(j) if j is not None else -1 for j in axes]

        def pick(a: np.ndarray, cols: list[int] = cols) -> np.ndarray:
            out = a[:, [max(c, 0) for c in cols]].copy()
            out[:, [k for k, c in enumerate(cols) if c < 0]] = 0.0
            return out

        tau = pick(js["effort"]) if js["effort"].shape[1] else None
        name = f"{part}/{joint_port}"
        if name in without_data:
            lines = None
        elif joint_port == "state:o":
            lines = vector_lines(js["stamp_ns"], recv, pick(js["position"]) * DEG, 20000)
        else:
            lines = state_lines(js["stamp_ns"], recv, pick(js["position"]), pick(js["velocity"]), tau)
        write_port(run / folder(robot, part, joint_port), lines, f"/{robot}/{name}", t0, stamp)
    for part, sensor in ft_ports.items():
        m = _arrival(read[topics.sensor_topic("ft_wrench", sensor)])
        name = f"{part}/analog:o"
        lines = (
            None
            if name in without_data
            else analog_lines(m["stamp_ns"], m["log_time_ns"] if two_times else None, m["wrench"])
        )
        write_port(run / folder(robot, part, "analog:o"), lines, f"/{robot}/{name}", t0, stamp)
    side = dict(sidecar) if sidecar is not None else {k: v for k, v in experiment.items() if k != "sim"}
    run.with_name(run.name + ".yaml").write_text(yaml.safe_dump(side, sort_keys=False))
    return run
