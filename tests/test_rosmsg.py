"""pipeline.logs.rosmsg: our MCAP writer and fast decoder against the standard mcap / mcap_ros2 libraries."""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import IndexType
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from pipeline.core.errors import DataError
from pipeline.logs.rosmsg import (
    IMU,
    JOINT_STATE,
    SCHEMAS,
    STRING,
    TEMPERATURE,
    WRENCH_STAMPED,
    LogReader,
    LogWriter,
    schema_layout,
)

T0 = 1_700_000_000_123_456_789  # ns
# Extreme doubles: bit patterns must survive (signed zero, subnormal, max, inf, nan).
EXTREMES = np.array(
    [
        0.0,
        -0.0,
        5e-324,
        -1.7976931348623157e308,
        1.7976931348623157e308,
        np.inf,
        -np.inf,
        np.nan,
        1e-300,
        -123.456,
    ]
)
FRAMES = ["", "a", "ab", "abc", "abcd", "l_leg_ft", "r_foot_front_ft_sensor", "ünïcødé_frame"]


def _values(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    out = rng.standard_normal(shape) * 100
    flat = out.reshape(-1)
    flat[: min(len(flat), len(EXTREMES))] = EXTREMES[: len(flat)]
    return out


def _write_everything(path: Path) -> dict[str, str]:
    """A log with every supported type, odd frame_id lengths, many joints, extreme and bad values."""
    rng = np.random.default_rng(0)
    n = 25
    stamps = T0 + np.arange(n, dtype=np.int64) * 10_000_000
    stamps[[3, 4]] = stamps[[4, 3]]  # non-monotonic
    stamps[7] = stamps[6]  # duplicated
    stamps[0] = 0
    stamps[1] = (2**31 - 1) * 1_000_000_000 + 999_999_999  # the last representable ROS 2 time
    log_times = stamps + rng.integers(0, 5_000_000, n)
    types = {}
    meta = {"experiment": {"type": "walking", "robot": "iCubGenova09", "contacts": ""}}
    with LogWriter(path, meta, chunk_size=4096) as w:  # small chunks: many chunk boundaries
        names = [f"joint_{i}_{'x' * (i % 7)}" for i in range(120)]
        w.joint_states(
            "/joint_states",
            stamps,
            names,
            _values(rng, (n, 120)),
            _values(rng, (n, 120)),
            _values(rng, (n, 120)),
            log_times_ns=log_times,
        )
        types["/joint_states"] = JOINT_STATE
        w.joint_states(
            "/js_no_effort", stamps, ["a"], rng.standard_normal((n, 1)), rng.standard_normal((n, 1))
        )
        types["/js_no_effort"] = JOINT_STATE
        w.joint_states("/js_empty", stamps[:3], [], np.empty((3, 0)), np.empty((3, 0)))
        types["/js_empty"] = JOINT_STATE
        for k, frame in enumerate(FRAMES):
            w.wrenches(f"/ft/{k}/wrench", stamps, frame, _values(rng, (n, 6)))
            w.imus(f"/ft/{k}/imu", stamps, frame, _values(rng, (n, 3)), _values(rng, (n, 3)), log_times)
            w.temperatures(f"/ft/{k}/temperature", stamps, frame, _values(rng, (n,)))
            types.update(
                {f"/ft/{k}/wrench": WRENCH_STAMPED, f"/ft/{k}/imu": IMU, f"/ft/{k}/temperature": TEMPERATURE}
            )
            w.flush()
        w.strings("/sim/contacts", stamps[:6], ["", "l_sole", "l_sole,r_sole", "ü", "abc", "abcd"])
        types["/sim/contacts"] = STRING
    return types


def _standard_messages(path: Path) -> dict[str, list]:
    """Per topic, (log_time, publish_time, decoded message) in file order, by mcap_ros2."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append((message.log_time, message.publish_time, decoded))
    return out


def _same(a: object, b: object) -> bool:
    """Equality that tells -0.0 from 0.0 and takes NaN == NaN (bit patterns of doubles)."""
    if isinstance(a, float) or isinstance(b, float):
        return np.array(a, dtype=np.float64).tobytes() == np.array(b, dtype=np.float64).tobytes()
    return a == b


def _assert_batches_match(batches: list, standard: list, msgtype: str) -> None:
    rows = []
    for batch in batches:
        for k in range(len(batch)):
            rows.append((int(batch.order[k]), batch, k))
    rows.sort(key=lambda r: r[0])
    assert len(rows) == len(standard)
    for (_, batch, k), (log_time, publish_time, msg) in zip(rows, standard, strict=True):
        assert batch.msgtype == msgtype
        assert int(batch.log_time_ns[k]) == log_time
        assert int(batch.publish_time_ns[k]) == publish_time
        f = batch.fields
        if msgtype == STRING:
            assert f["data"][k] == msg.data
            assert int(batch.stamp_ns[k]) == publish_time
            continue
        assert int(batch.stamp_ns[k]) == msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert f["frame_id"][k] == msg.header.frame_id
        if msgtype == WRENCH_STAMPED:
            w = msg.wrench
            expected = [w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z]
            assert all(_same(x, y) for x, y in zip(f["wrench"][k].tolist(), expected, strict=True))
        elif msgtype == IMU:
            for key, vec in (
                ("orientation", "xyzw"),
                ("angular_velocity", "xyz"),
                ("linear_acceleration", "xyz"),
            ):
                expected = [getattr(getattr(msg, key), c) for c in vec]
                assert all(_same(x, y) for x, y in zip(f[key][k].tolist(), expected, strict=True))
                cov = f"{key}_covariance"
                assert all(
                    _same(x, y) for x, y in zip(f[cov][k].tolist(), list(getattr(msg, cov)), strict=True)
                )
        elif msgtype == TEMPERATURE:
            assert _same(float(f["temperature"][k]), msg.temperature)
            assert _same(float(f["variance"][k]), msg.variance)
        elif msgtype == JOINT_STATE:
            assert list(batch.names) == list(msg.name)
            for key in ("position", "velocity", "effort"):
                assert all(
                    _same(x, y) for x, y in zip(f[key][k].tolist(), list(getattr(msg, key)), strict=True)
                )


def test_every_message_decodes_identically_fast_and_standard(tmp_path: Path) -> None:
    path = tmp_path / "all.mcap"
    types = _write_everything(path)
    standard = _standard_messages(path)
    assert set(standard) == set(types)
    with LogReader(path) as reader:
        assert reader.metadata["experiment"]["type"] == "walking"
        assert {t: info.msgtype for t, info in reader.topics.items()} == types
        fast = reader.read()
        slow = reader.read(fast=False)
    for topic, msgtype in types.items():
        assert all(b.fast for b in fast[topic]), topic  # the vectorised path knew every layout
        assert not any(b.fast for b in slow[topic])
        _assert_batches_match(fast[topic], standard[topic], msgtype)
        _assert_batches_match(slow[topic], standard[topic], msgtype)


def test_log_time_order_and_summary(tmp_path: Path) -> None:
    path = tmp_path / "all.mcap"
    _write_everything(path)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        times = [m.log_time for _, _, m in reader.iter_messages(log_time_order=False)]
        assert summary.statistics.message_count == len(times)
    # each flush block is sorted by log time (the writer sorts what it buffered)
    assert len(times) > 100
    assert sum(b < a for a, b in zip(times, times[1:], strict=False)) < 10


def _standard_bytes(messages: list[tuple[str, str, dict]]) -> list[bytes]:
    """CDR payloads written by mcap_ros2's own serializer (its public Writer)."""
    buf = io.BytesIO()
    writer = Ros2Writer(buf)
    schemas = {}
    for k, (topic, msgtype, msg) in enumerate(messages):
        if msgtype not in schemas:
            schemas[msgtype] = writer.register_msgdef(msgtype, SCHEMAS[msgtype])
        writer.write_message(topic, schemas[msgtype], msg, log_time=k, publish_time=k)
    writer.finish()
    buf.seek(0)
    return [m.data for _, _, m in make_reader(buf).iter_messages(log_time_order=False)]


def _our_bytes(path: Path) -> list[bytes]:
    with open(path, "rb") as f:
        return [m.data for _, _, m in make_reader(f).iter_messages(log_time_order=False)]


@pytest.mark.parametrize("frame", FRAMES)
def test_encoder_bytes_identical_to_mcap_ros2_serializer(tmp_path: Path, frame: str) -> None:
    stamp = T0 + 7
    sec, nsec = divmod(stamp, 1_000_000_000)
    header = {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": frame}
    wrench = [1.5, -2.25, 3e10, -0.0, 5e-324, -7.0]
    acc, gyr = [0.1, -9.81, 1e-5], [3.0, -2.0, 0.5]
    names = ["a", "bb", "ccc", "dddd", "eeeee"]
    q = np.arange(5) * 0.5
    messages = [
        (
            "/w",
            WRENCH_STAMPED,
            {
                "header": header,
                "wrench": {
                    "force": dict(zip("xyz", wrench[:3], strict=True)),
                    "torque": dict(zip("xyz", wrench[3:], strict=True)),
                },
            },
        ),
        (
            "/i",
            IMU,
            {
                "header": header,
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                "orientation_covariance": [-1.0] + [0.0] * 8,
                "angular_velocity": dict(zip("xyz", gyr, strict=True)),
                "angular_velocity_covariance": [0.0] * 9,
                "linear_acceleration": dict(zip("xyz", acc, strict=True)),
                "linear_acceleration_covariance": [0.0] * 9,
            },
        ),
        ("/t", TEMPERATURE, {"header": header, "temperature": 36.6, "variance": 0.0}),
        (
            "/j",
            JOINT_STATE,
            {
                "header": {**header, "frame_id": ""},
                "name": names,
                "position": list(q),
                "velocity": list(-q),
                "effort": [],
            },
        ),
        (
            "/j2",
            JOINT_STATE,
            {
                "header": {**header, "frame_id": frame},
                "name": names[:3],
                "position": list(q[:3]),
                "velocity": [],
                "effort": list(q[:3] * 2),
            },
        ),
        ("/s", STRING, {"data": frame}),
    ]
    path = tmp_path / "ours.mcap"
    st = np.array([stamp])
    with LogWriter(path) as w:
        w.wrenches("/w", st, frame, np.array([wrench]))
        w.imus("/i", st, frame, np.array([acc]), np.array([gyr]))
        w.temperatures("/t", st, frame, np.array([36.6]))
        w.joint_states("/j", st, names, q[None], -q[None])
        w.joint_states("/j2", st, names[:3], q[None, :3], np.empty((1, 0)), q[None, :3] * 2, frame_id=frame)
        w.strings("/s", st, [frame])
    assert _our_bytes(path) == _standard_bytes(messages)


def test_atomic_write(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "log.mcap"
    with pytest.raises(RuntimeError, match="boom"), LogWriter(path) as w:
        w.wrenches("/w", np.arange(3), "f", np.zeros((3, 6)))
        w.flush()
        assert (tmp_path / "sub" / "log.mcap.part").exists()
        raise RuntimeError("boom")
    assert list((tmp_path / "sub").iterdir()) == []
    with LogWriter(path) as w:
        w.wrenches("/w", np.arange(3), "f", np.zeros((3, 6)))
        assert not path.exists()
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["log.mcap"]


def test_topic_type_is_fixed_on_first_use(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="registered as"), LogWriter(tmp_path / "x.mcap") as w:
        w.wrenches("/a", np.arange(2), "f", np.zeros((2, 6)))
        w.temperatures("/a", np.arange(2), "f", np.zeros(2))
    assert not list(tmp_path.iterdir())


def _standard_writer_log(path: Path, index_types: IndexType, schema_text: str | None = None) -> None:
    """A log written by mcap_ros2 (schemas and channels inside chunks), JointState names changing."""
    with open(path, "wb") as f:
        # mcap_ros2's Writer has no index_types option: swap in an mcap Writer that has it.
        writer = Ros2Writer(io.BytesIO(), chunk_size=2048)
        writer._writer = McapWriter(f, chunk_size=2048, index_types=index_types)
        writer._writer.start(profile="ros2", library="test")
        js = writer.register_msgdef(JOINT_STATE, SCHEMAS[JOINT_STATE])
        w = writer.register_msgdef(WRENCH_STAMPED, schema_text or SCHEMAS[WRENCH_STAMPED])
        for k in range(40):
            names = [f"j{i}" for i in range(k % 20 + 1)]  # 20 layouts: more than the fast path caches
            writer.write_message(
                "/joint_states",
                js,
                {
                    "header": {"stamp": {"sec": k, "nanosec": 5}, "frame_id": "base" * (k % 3)},
                    "name": names,
                    "position": [float(i) for i in range(len(names))],
                    "velocity": [],
                    "effort": [],
                },
                log_time=k,
                publish_time=k,
            )
            writer.write_message(
                "/w",
                w,
                {
                    "header": {"stamp": {"sec": k, "nanosec": 0}, "frame_id": "f" * (k % 5)},
                    "wrench": {"force": {"x": k}, "torque": {"z": -k}},
                },
                log_time=k,
                publish_time=k,
            )
        writer.finish()


@pytest.mark.parametrize("index_types", [IndexType.ALL, IndexType.CHUNK])
def test_reads_logs_of_the_standard_writer(tmp_path: Path, index_types: IndexType) -> None:
    path = tmp_path / "std.mcap"
    _standard_writer_log(path, index_types)
    standard = _standard_messages(path)
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) > 3
    assert all(bool(c.message_index_offsets) == (index_types == IndexType.ALL) for c in chunks)
    with LogReader(path) as reader:
        got = reader.read()
    _assert_batches_match(got["/joint_states"], standard["/joint_states"], JOINT_STATE)
    _assert_batches_match(got["/w"], standard["/w"], WRENCH_STAMPED)
    assert all(b.fast for b in got["/w"])


def test_unknown_layout_falls_back_to_the_standard_decoder(tmp_path: Path) -> None:
    # Same type name, one more field: the fast path must not guess, mcap_ros2 decodes it.
    text = SCHEMAS[WRENCH_STAMPED].replace("Wrench wrench", "Wrench wrench\nfloat64 extra", 1)
    path = tmp_path / "custom.mcap"
    _standard_writer_log(path, IndexType.ALL, schema_text=text)
    standard = _standard_messages(path)
    with LogReader(path) as reader:
        got = reader.read(["/w"])
    assert not any(b.fast for b in got["/w"])
    _assert_batches_match(got["/w"], standard["/w"], WRENCH_STAMPED)


def test_schema_layout_ignores_formatting() -> None:
    commented = "# a comment\n" + SCHEMAS[IMU].replace("float64 x 0", "float64 x   0  # x").replace(
        "MSG: std_msgs/Header", "MSG: std_msgs/msg/Header"
    )
    assert schema_layout(IMU, commented) == schema_layout(IMU, SCHEMAS[IMU])
    assert schema_layout(IMU, SCHEMAS[IMU].split("=" * 80)[0]) is None  # nested types undefined
    assert schema_layout(STRING, "string data\nint32 X=3\n") == (("data", "string"),)


def test_reader_errors_name_file_and_problem(tmp_path: Path) -> None:
    good = tmp_path / "good.mcap"
    with LogWriter(good) as w:
        w.wrenches("/w", T0 + np.arange(5000), "frame", np.random.default_rng(1).standard_normal((5000, 6)))
    data = good.read_bytes()
    cases = {
        "empty.mcap": (b"", "empty file"),
        "truncated.mcap": (data[: len(data) // 2], "truncated"),
        "text.mcap": (b"hello world, not a log", "not an MCAP file"),
    }
    with open(good, "rb") as f:
        chunk = make_reader(f).get_summary().chunk_indexes[0]
    corrupted = bytearray(data)
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    corrupted[middle] ^= 0xFF
    cases["corrupted.mcap"] = (bytes(corrupted), "corrupted chunk")
    for name, (content, problem) in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(DataError, match=problem) as info, LogReader(path) as reader:
            reader.read()
        assert str(path) in str(info.value)
        assert "\n" not in str(info.value)


def test_split_stamps_round_trip() -> None:
    from pipeline.logs.rosmsg import join_stamps, split_stamps

    stamps = np.array([0, 1, 999_999_999, 1_000_000_000, -1, T0, (2**31 - 1) * 10**9])
    sec, nsec = split_stamps(stamps)
    assert (nsec < 1_000_000_000).all()
    np.testing.assert_array_equal(join_stamps(sec, nsec), stamps)
    assert math.isclose(float(sec[-1]), 2**31 - 1)
