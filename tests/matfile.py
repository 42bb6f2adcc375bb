"""Test fixtures: YarpRobotLoggerDevice-layout .mat files, written the way MATLAB / matio lay them out.

v7.3: an HDF5 file with MATLAB's 512-byte header block (128-byte text header "MATLAB 7.3 MAT-file...",
subsystem offset, version 0x0200, endian "IM"); structs are groups with ``MATLAB_class = 'struct'`` and
a ``MATLAB_fields`` attribute (field order); doubles / uint64 datasets with their ``MATLAB_class``; char
arrays uint16 with ``MATLAB_int_decode = 2``; cell arrays datasets of object references into ``#refs#``;
empty arrays store their dimensions with ``MATLAB_empty = 1``. MATLAB arrays are column-major, HDF5
row-major: a MATLAB ``k x 1 x N`` array is stored as the ``(N, 1, k)`` array of the same bytes.
v5 (MATLAB's re-save without -v7.3) goes through scipy.io.savemat.

`mcap_to_mat` turns an MCAP contract log into the logger layout with one of the logger's three naming
generations, plus the experiment sidecar YAML.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import yaml

from pipeline.core.config import TopicParams
from pipeline.logs import rosmsg
from pipeline.logs.matlog import ns_to_seconds

ROOT_NAME = "robot_logger_device"
NAMINGS = {  # logger names of the URDF sensor s: FT (and temperature), accelerometer, gyroscope
    "2022": ("{s}_sensor", "{s}_acc", "{s}_gyro"),
    "2023": ("{s}", "{s}_acc", "{s}_gyro"),
    "2024": ("{s}", "{s}_imu", "{s}_imu"),
}
WRENCH_NAMES = ["f_x", "f_y", "f_z", "mu_x", "mu_y", "mu_z"]


class EmptyStruct:
    """A channel whose buffer was empty at save time: a struct without fields."""


class Cell(list):
    """A MATLAB cell array of char rows, n x 1 (a list of str)."""


def leaf(name: str, t_s: np.ndarray, values: np.ndarray, elements: Sequence[str] = ()) -> dict[str, Any]:
    """The robometry leaf struct of one channel: values (N, k) at t_s (N,) seconds."""
    values = np.asarray(values, dtype=np.float64).reshape(len(t_s), -1)
    n, k = values.shape
    return {
        "data": values.T.reshape(k, 1, n),  # MATLAB k x 1 x N
        "dimensions": np.array([[k, 1, n]], dtype=np.uint64),
        "elements_names": Cell(elements),
        "units_of_measure": Cell(),
        "name": name,
        "timestamps": np.asarray(t_s, dtype=np.float64).reshape(1, n),
    }


def logger_tree(
    channels: Mapping[str, dict[str, Any] | EmptyStruct], joints: Sequence[str], robot_name: str
) -> dict[str, Any]:
    """The top-level struct: description_list, yarp_robot_name, then channels split on '/'."""
    tree: dict[str, Any] = {"description_list": Cell(joints), "yarp_robot_name": robot_name}
    for path, value in channels.items():
        node = tree
        *parents, last = path.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    return tree


# --- v7.3 -----------------------------------------------------------------------------------------


def _header(text: str = "") -> bytes:
    stamp = time.strftime("%a %b %d %H:%M:%S %Y", time.gmtime(0))
    line = text or f"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: {stamp} HDF5 schema 1.00 ."
    head = line.encode().ljust(116, b" ") + b" " * 8 + np.uint16(0x0200).tobytes() + b"IM"
    return head.ljust(512, b"\0")


class _Writer73:
    def __init__(self, f: h5py.File, compression: str | None):
        self.f, self.compression, self.refs = f, compression, 0

    def _class(self, obj: Any, name: str) -> None:
        # matio writes a NULLTERM string of len(name) chars. Written so by h5py's HDF5 2.x, matio 1.5.23
        # (HDF5 1.10) reads it back without its last char ('doubl': unknown class), so the NUL is stored.
        tid = h5py.h5t.C_S1.copy()
        tid.set_size(len(name) + 1)
        tid.set_strpad(h5py.h5t.STR_NULLTERM)
        obj.attrs.create("MATLAB_class", np.bytes_(name), dtype=h5py.Datatype(tid))

    def _ref_name(self) -> str:
        self.refs += 1
        return str(self.refs - 1)  # matio's names in #refs# (MATLAB's own are a, b, ...)

    def _empty(self, group: h5py.Group, key: str, dims: Sequence[int], cls: str) -> h5py.Dataset:
        ds = group.create_dataset(key, data=np.array(dims, dtype=np.uint64))
        self._class(ds, cls)
        ds.attrs.create("MATLAB_empty", np.uint32(1))
        return ds

    def char(self, group: h5py.Group, key: str, text: str) -> None:
        if not text:
            self._empty(group, key, (0, 0), "char").attrs.create("MATLAB_int_decode", np.int32(2))
            return
        ds = group.create_dataset(key, data=np.array([[ord(c)] for c in text], dtype=np.uint16))  # 1 x L
        self._class(ds, "char")
        ds.attrs.create("MATLAB_int_decode", np.int32(2))

    def cell(self, group: h5py.Group, key: str, items: Sequence[str]) -> None:
        if not items:
            self._empty(group, key, (0, 1), "cell")
            return
        refs = self.f.require_group("#refs#")
        out = np.empty((1, len(items)), dtype=h5py.ref_dtype)  # MATLAB n x 1
        for k, item in enumerate(items):
            name = self._ref_name()
            self.char(refs, name, item)
            out[0, k] = refs[name].ref
        ds = group.create_dataset(key, data=out, dtype=h5py.ref_dtype)
        self._class(ds, "cell")

    def array(self, group: h5py.Group, key: str, value: np.ndarray) -> None:
        data = np.ascontiguousarray(value.T)  # MATLAB column-major dims reversed
        big = data.ndim and data.shape[0] > 64
        opts = {"chunks": True, "compression": self.compression} if big and self.compression else {}
        ds = group.create_dataset(key, data=data, **opts)
        self._class(ds, {np.dtype(np.float64): "double", np.dtype(np.uint64): "uint64"}[data.dtype])

    def struct(self, group: h5py.Group, tree: Mapping[str, Any]) -> None:
        self._class(group, "struct")
        items = tree
        fields = np.empty(len(items), dtype=h5py.vlen_dtype(np.dtype("S1")))
        for k, name in enumerate(items):
            fields[k] = np.frombuffer(name.encode(), dtype="S1")
        group.attrs.create("MATLAB_fields", fields, dtype=h5py.vlen_dtype(np.dtype("S1")))
        for key, value in items.items():
            if isinstance(value, EmptyStruct):  # as matio writes a 1x1 struct without fields
                self._empty(group, key, (1, 1), "struct")
            elif isinstance(value, dict):
                self.struct(group.create_group(key), value)
            elif isinstance(value, Cell):
                self.cell(group, key, value)
            elif isinstance(value, str):
                self.char(group, key, value)
            else:
                self.array(group, key, np.asarray(value))


def write_v73(
    path: Path, tree: Mapping[str, Any], root: str = ROOT_NAME, *, compression: str | None = "gzip"
) -> Path:
    """A MATLAB v7.3 file holding one variable `root` = the struct `tree` (see the module docstring)."""
    with h5py.File(path, "w", userblock_size=512, libver="earliest") as f:
        _Writer73(f, compression).struct(f.create_group(root), tree)
    with open(path, "r+b") as f:
        f.write(_header())
    return path


# --- v5 -------------------------------------------------------------------------------------------


def _to_scipy(tree: Any) -> Any:
    if isinstance(tree, EmptyStruct):
        return {}  # 1x1 struct without fields
    if isinstance(tree, dict):
        return {k: _to_scipy(v) for k, v in tree.items()}
    if isinstance(tree, Cell):
        out = np.empty((len(tree), 1), dtype=object)
        for k, item in enumerate(tree):
            out[k, 0] = item
        return out
    return tree


def write_v5(path: Path, tree: Mapping[str, Any], root: str = ROOT_NAME) -> Path:
    """The same variable in MATLAB's v5/v7 format (what MATLAB's `save` writes without -v7.3)."""
    from scipy.io import savemat

    savemat(str(path), {root: _to_scipy(tree)}, do_compression=True, long_field_names=True)
    return path


# --- from an MCAP contract log ---------------------------------------------------------------------


def _arrival_then_stamp(batches: Sequence[rosmsg.Batch]) -> dict[str, np.ndarray]:
    """A topic's messages sorted by stamp, equal stamps in arrival order (as a logger buffer holds them)."""
    data = rosmsg.concat_batches(batches)
    arrival = np.lexsort((data["order"], data["log_time_ns"]))
    rank = np.empty_like(arrival)
    rank[arrival] = np.arange(len(arrival))
    perm = np.lexsort((rank, data["stamp_ns"]))
    return {k: v[perm] for k, v in data.items()}


def mcap_to_mat(
    mcap: Path,
    out: Path,
    topics: TopicParams,
    sensors: Sequence[str],
    *,
    naming: str = "2024",
    version: str = "7.3",
    root: str = ROOT_NAME,
    sidecar: bool = True,
    empty: Sequence[str] = (),
    drop: Sequence[str] = (),
    compression: str | None = "gzip",
) -> Path:
    """Write the MCAP log's joint states, wrenches, IMUs and temperatures as a logger .mat file.
    `compression` None: every dataset contiguous (no HDF5 chunks, as the logger writes by default).

    Channels in `empty` are written as empty structs (buffer empty at save time), those in `drop` not
    at all; `naming` is a key of NAMINGS. The experiment record goes to the sidecar ``<stem>.yaml``.
    """
    ft_name, acc_name, gyro_name = NAMINGS[naming]
    with rosmsg.LogReader(mcap) as reader:
        experiment = dict(reader.metadata.get("experiment", {}))
        read = reader.read()
    js_batches = read[topics.joint_states]
    js = _arrival_then_stamp(js_batches)
    joints = list(js_batches[0].names or ())
    t = ns_to_seconds(js["stamp_ns"])
    channels: dict[str, Any] = {"joints_state/positions": leaf("positions", t, js["position"], joints)}
    if js["velocity"].shape[1]:
        channels["joints_state/velocities"] = leaf("velocities", t, js["velocity"], joints)
    if js["effort"].shape[1]:
        channels["joints_state/torques"] = leaf("torques", t, js["effort"], joints)
    for s in sensors:
        ft, acc, gyro = (n.format(s=s) for n in (ft_name, acc_name, gyro_name))
        if (batches := read.get(topics.sensor_topic("ft_wrench", s))) is not None:
            m = _arrival_then_stamp(batches)
            channels[f"FTs/{ft}"] = leaf(ft, ns_to_seconds(m["stamp_ns"]), m["wrench"], WRENCH_NAMES)
        if (batches := read.get(topics.sensor_topic("ft_temperature", s))) is not None:
            m = _arrival_then_stamp(batches)
            channels[f"temperatures/{ft}"] = leaf(
                ft, ns_to_seconds(m["stamp_ns"]), m["temperature"], ["temperature"]
            )
        if (batches := read.get(topics.sensor_topic("ft_imu", s))) is not None:
            m = _arrival_then_stamp(batches)
            ts = ns_to_seconds(m["stamp_ns"])
            channels[f"accelerometers/{acc}"] = leaf(acc, ts, m["linear_acceleration"], ["a_x", "a_y", "a_z"])
            channels[f"gyros/{gyro}"] = leaf(
                gyro, ts, m["angular_velocity"], ["omega_x", "omega_y", "omega_z"]
            )
    for path in empty:
        channels[path] = EmptyStruct()
    for path in drop:
        channels.pop(path, None)
    tree = logger_tree(channels, joints, experiment.get("robot", "iCubGenova09"))
    if version == "7.3":  # compression None: contiguous datasets, as matio writes them uncompressed
        write_v73(out, tree, root, compression=compression)
    else:
        write_v5(out, tree, root)
    if sidecar:
        out.with_suffix(".yaml").write_text(yaml.safe_dump(experiment, sort_keys=False))
    return out
