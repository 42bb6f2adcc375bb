"""`ftcal calibrate`: on a real export of tiny trained models and a synthetic multi-chunk MCAP log, every
original message byte-identical (read back with mcap's own reader), one calibrated message per raw wrench
with the same header and times, values equal to an independent causal computation (mcap_ros2's decoder,
a plain loop for the latest temperature/IMU, the project's float64 model); directory form; bad input."""

from __future__ import annotations

import bisect
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.core.config import load_params
from pipeline.export.trained import read_group
from pipeline.stages import export as E
from tests.factories.labelled import FRONT, LEG, PAIR, REAR
from tests.factories.readback import mcap_records, ros2_messages, stamp_ns, xyz
from tests.mcap_factory import write_log

pytestmark = pytest.mark.slow  # trains and exports a group first

OTHER = "l_leg_ft"  # a sensor of the log without a model
SENSORS = (LEG, FRONT, REAR, OTHER)
RECOMMENDED = {LEG: "nn13", PAIR: "nn7"}
SERIALS = {LEG: "FT58-0001", FRONT: "FT45-0002", REAR: "FT45-0003"}  # robot.serials of the export's params


def _metrics_dir(tmp: Path, recommended: dict[str, str]) -> Path:
    """evaluate's reports/metrics directory: <group>/<headline>.json naming the recommended model."""
    path = tmp / "metrics"
    path.mkdir(exist_ok=True)
    for group, model in recommended.items():
        (path / group).mkdir(exist_ok=True)
        (path / group / f"{group}.json").write_text(json.dumps({"deployed": model}))
    return path


@pytest.fixture(scope="module")
def setup(trained_models: dict, tmp_path_factory: pytest.TempPathFactory) -> dict:
    import yaml

    tmp = tmp_path_factory.mktemp("calibrate")
    report = _metrics_dir(tmp, RECOMMENDED)
    data = yaml.safe_load(Path(trained_models["params"]).read_text())
    data["robot"]["serials"] = SERIALS  # the training tables record none: the export records these
    params_path = tmp / "params.yaml"
    params_path.write_text(yaml.safe_dump(data, sort_keys=False))
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
    try:
        params = load_params(params_path)
        E.run(params, trained_models["models"], report, trained_models["labelled"], tmp / "exported")
    finally:
        patch.undo()
    log = tmp / "logs" / "walk.mcap"
    # ~15 chunks: inputs cross chunk bounds
    write_log(log, SENSORS, 10.0, seed=3, chunk_size=32 * 1024, serials=SERIALS)
    return {
        **trained_models,
        "tmp": tmp,
        "export": tmp / "exported",
        "log": log,
        "params": params_path,
    }


def _cli(setup: dict, src: Path, out: Path, *extra: str, models: Path | None = None) -> list[str]:
    return [
        "calibrate",
        str(src),
        str(out),
        "--models",
        str(models or setup["export"]),
        "--params",
        str(setup["params"]),
        *extra,
    ]


def _expected(
    decoded: dict[str, list[Any]], sensor: str, n_inputs: int
) -> list[tuple[int, np.ndarray] | None]:
    """Per raw wrench message of `sensor`: (stamp, inputs) with the latest temperature/IMU stamped at or
    before it (None where there is none yet)."""
    temps = sorted((stamp_ns(m.ros_msg), m.ros_msg.temperature) for m in decoded[f"/ft/{sensor}/temperature"])
    imus = sorted(
        (stamp_ns(m.ros_msg), xyz(m.ros_msg.linear_acceleration) + xyz(m.ros_msg.angular_velocity))
        for m in decoded[f"/ft/{sensor}/imu"]
    )
    out = []
    for m in decoded[f"/ft/{sensor}/wrench"]:
        stamp = stamp_ns(m.ros_msg)
        k = bisect.bisect_right([t for t, _ in temps], stamp) - 1
        j = bisect.bisect_right([t for t, _ in imus], stamp) - 1
        if k < 0 or (n_inputs == 13 and j < 0):
            out.append(None)
            continue
        x = xyz(m.ros_msg.wrench.force) + xyz(m.ros_msg.wrench.torque) + [temps[k][1]]
        out.append((stamp, np.array(x + (imus[j][1] if n_inputs == 13 else []))))
    return out


def test_calibrate_copies_every_message_and_adds_causal_calibration(
    setup: dict, tmp_path: Path, capsys: Any
) -> None:
    out = tmp_path / "walk_calibrated.mcap"
    assert main(_cli(setup, setup["log"], out)) == 0
    captured = capsys.readouterr()
    assert f"no model for {OTHER}" in captured.err and "calibrated wrenches added" in captured.out

    original, copied = mcap_records(setup["log"]), mcap_records(out)
    assert [m for m in copied if not m[0].endswith("_calibrated")] == original  # byte for byte, same order
    decoded_in, decoded_out = ros2_messages(setup["log"]), ros2_messages(out)
    assert f"/ft/{OTHER}/wrench_calibrated" not in decoded_out
    for sensor, group in ((LEG, LEG), (FRONT, PAIR), (REAR, PAIR)):
        model = read_group(setup["models"] / group, RECOMMENDED[group])
        slot = model.sensors.index(sensor)
        raw = decoded_in[f"/ft/{sensor}/wrench"]
        expected = _expected(decoded_in, sensor, model.n_inputs)
        calibrated = decoded_out[f"/ft/{sensor}/wrench_calibrated"]
        kept = [(m, e) for m, e in zip(raw, expected, strict=True) if e is not None]
        assert len(calibrated) == len(kept) >= len(raw) - 2  # at most the messages before the first inputs
        x = np.stack([e[1] for _, e in kept])
        y = model.reference(np.tile(x, (1, len(model.sensors))))[:, slot * 6 : (slot + 1) * 6]
        got = np.array([xyz(m.ros_msg.wrench.force) + xyz(m.ros_msg.wrench.torque) for m in calibrated])
        np.testing.assert_allclose(got, y, rtol=0, atol=1e-9)
        assert np.abs(got - x[:, :6]).max() > 0.1  # the calibration changes the wrench
        for (m_raw, _), m_cal in zip(kept, calibrated, strict=True):
            assert stamp_ns(m_cal.ros_msg) == stamp_ns(m_raw.ros_msg)
            assert m_cal.ros_msg.header.frame_id == m_raw.ros_msg.header.frame_id
            assert (m_cal.log_time_ns, m_cal.publish_time_ns) == (m_raw.log_time_ns, m_raw.publish_time_ns)
    # the experiment metadata is kept
    from mcap.reader import make_reader

    with out.open("rb") as f:
        assert {m.name for m in make_reader(f).iter_metadata()} == {"experiment"}


def test_directory_form_and_existing_output(setup: dict, tmp_path: Path, capsys: Any) -> None:
    src = tmp_path / "in"
    (src / "day2").mkdir(parents=True)
    shutil.copy(setup["log"], src / "a.mcap")
    shutil.copy(setup["log"], src / "day2" / "b.mcap")
    out = tmp_path / "out"
    assert main(_cli(setup, src, out)) == 0
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*.mcap")) == ["a.mcap", "day2/b.mcap"]
    capsys.readouterr()
    assert main(_cli(setup, src, out)) == 2
    assert "a.mcap: exists (use --force to replace it)" in capsys.readouterr().err
    assert main(_cli(setup, src, out, "--force")) == 0


def _bad_cases(setup: dict, tmp: Path) -> dict[str, tuple[list[str], str]]:
    other_robot = tmp / "other_robot"
    shutil.copytree(setup["export"], other_robot)
    manifest = json.loads((other_robot / "manifest.json").read_text())
    manifest["robot"] = "ergoCubSN001"
    (other_robot / "manifest.json").write_text(json.dumps(manifest))
    no_temperature = tmp / "no_temperature.mcap"
    write_log(no_temperature, SENSORS, 2.0, temperature=False)
    truncated = tmp / "truncated.mcap"
    data = setup["log"].read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    arms = tmp / "arms.mcap"
    write_log(arms, ("l_arm_ft",), 2.0)
    mismatch = tmp / "inputs_mismatch"
    shutil.copytree(setup["export"], mismatch)
    manifest = json.loads((mismatch / "manifest.json").read_text())
    manifest["graphs"][LEG]["inputs"][6]["field"] = "variance"
    (mismatch / "manifest.json").write_text(json.dumps(manifest))
    existing = tmp / "existing.mcap"
    existing.write_bytes(b"keep")
    swapped = tmp / "swapped.mcap"  # the leg's board replaced since the calibration
    write_log(swapped, SENSORS, 2.0, serials={**SERIALS, LEG: "FT58-0999"})
    return {
        "models missing": (
            _cli(setup, setup["log"], tmp / "o1.mcap", models=tmp / "nowhere"),
            "models directory",
        ),
        "another robot": (
            _cli(setup, setup["log"], tmp / "o2.mcap", models=other_robot),
            "recorded on robot 'iCubGenova09', but the models",
        ),
        "no temperature": (
            _cli(setup, no_temperature, tmp / "o3.mcap"),
            f"has /ft/{LEG}/wrench but no /ft/{LEG}/temperature",
        ),
        "truncated": (_cli(setup, truncated, tmp / "o4.mcap"), "truncated MCAP file"),
        "no modelled sensor": (_cli(setup, arms, tmp / "o5.mcap"), "none of the sensors of"),
        "output exists": (_cli(setup, setup["log"], existing), "existing.mcap: exists (use --force"),
        "inputs mismatch": (
            _cli(setup, setup["log"], tmp / "o6.mcap", models=mismatch),
            f"inputs of {LEG} in {LEG}'s graph are",
        ),
        "another serial": (
            _cli(setup, swapped, tmp / "o7.mcap"),
            f"{LEG} is serial 'FT58-0999' in this log, but the calibration in {setup['export']} belongs to "
            f"serial '{SERIALS[LEG]}'",
        ),
    }


@pytest.mark.parametrize(
    "case",
    ["models missing", "another robot", "no temperature", "truncated", "no modelled sensor", "output exists"]
    + ["inputs mismatch", "another serial"],
)
def test_bad_input_is_one_line_and_writes_nothing(
    setup: dict, tmp_path: Path, case: str, capsys: Any
) -> None:
    args, message = _bad_cases(setup, tmp_path)[case]
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("ftcal: error: ") and message in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no output, no .part left
    if case == "output exists":
        assert (tmp_path / "existing.mcap").read_bytes() == b"keep"


def test_attachments_metadata_and_foreign_records_survive(setup: dict, tmp_path: Path) -> None:
    """A log written by mcap's own writer (one message per chunk, an attachment and metadata between the
    chunks): everything read back identical, the attachment and metadata at their moved offsets."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from pipeline.logs.cdr import (
        RECORD_HEADER_SIZE,
        SCHEMAS,
        TEMPERATURE,
        WRENCH_STAMPED,
        fixed_records,
        fixed_template,
    )

    src = tmp_path / "foreign.mcap"
    t0 = 1_700_000_000_000_000_000
    with src.open("wb") as f:
        w = Writer(f, chunk_size=200)
        w.start(profile="ros2", library="test")
        ids = {}
        for msgtype, topic in (
            (WRENCH_STAMPED, f"/ft/{LEG}/wrench"),
            (TEMPERATURE, f"/ft/{LEG}/temperature"),
        ):
            schema = w.register_schema(name=msgtype, encoding="ros2msg", data=SCHEMAS[msgtype].encode())
            ids[msgtype] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=schema)
        w.add_metadata("experiment", {"robot": "iCubGenova09", "role": "test"})
        for k in range(30):
            stamp = np.array([t0 + k * 10_000_000])
            rec = fixed_records(
                fixed_template(TEMPERATURE, b"t"),
                0,
                np.zeros(1, np.uint32),
                stamp,
                stamp,
                stamp,
                {"temperature": np.array([30.0 + k])},
            )
            w.add_message(
                ids[TEMPERATURE],
                int(stamp[0]),
                rec[0, RECORD_HEADER_SIZE:].tobytes(),
                int(stamp[0]),
                sequence=k,
            )
            rec = fixed_records(
                fixed_template(WRENCH_STAMPED, b"w"),
                0,
                np.zeros(1, np.uint32),
                stamp + 5,
                stamp + 5,
                stamp + 5,
                {"wrench": np.full((1, 6), float(k))},
            )
            w.add_message(
                ids[WRENCH_STAMPED],
                int(stamp[0]) + 5,
                rec[0, RECORD_HEADER_SIZE:].tobytes(),
                int(stamp[0]) + 5,
            )
            if k == 10:
                w.add_attachment(
                    create_time=1, log_time=2, name="notes.txt", media_type="text/plain", data=b"hello"
                )
        w.finish()
    out = tmp_path / "out.mcap"
    assert main(_cli(setup, src, out)) == 2  # a 13-input model needs the IMU this log lacks
    models = tmp_path / "leg7"
    report = _metrics_dir(tmp_path, {LEG: "nn7", PAIR: "nn7"})
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'm.db'}")
    try:
        E.run(load_params(setup["params"]), setup["models"], report, setup["labelled"], models)
    finally:
        patch.undo()
    assert main(_cli(setup, src, out, models=models)) == 0
    assert [m for m in mcap_records(out) if not m[0].endswith("_calibrated")] == mcap_records(src)
    assert sum(m[0].endswith("_calibrated") for m in mcap_records(out)) == 30
    with out.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        (attachment,) = list(reader.iter_attachments())
        assert (attachment.name, attachment.data) == ("notes.txt", b"hello")
        assert [m.metadata for m in reader.iter_metadata()] == [{"robot": "iCubGenova09", "role": "test"}]


@pytest.mark.parametrize("layout", ["no_chunks", "chunks_without_chunk_index", "no_summary"])
def test_logs_without_chunk_index_are_scanned_as_ingest_reads_them(
    setup: dict, tmp_path: Path, layout: str
) -> None:
    """The log rewritten by mcap's own writer without chunk indexes (or chunks, or summary), which `ftcal
    ingest` reads by scanning: calibrated to the same messages as the indexed log, every original record
    kept in order, and the copy read back by mcap's reader and by ours."""
    from pipeline.logs.mcap_read import LogReader
    from tests.factories.logs import LAYOUTS, copy_log

    src = copy_log(setup["log"], tmp_path / f"{layout}.mcap", **LAYOUTS[layout])
    with LogReader(src) as reader:
        assert not reader.indexed
    indexed = tmp_path / "indexed_calibrated.mcap"
    assert main(_cli(setup, setup["log"], indexed)) == 0
    out = tmp_path / "calibrated.mcap"
    assert main(_cli(setup, src, out)) == 0
    copied = mcap_records(out)
    assert [m for m in copied if not m[0].endswith("_calibrated")] == mcap_records(src)

    def calibrated(path: Path) -> list[tuple[str, int, int, bytes]]:
        return sorted((m[0], m[1], m[2], m[4]) for m in mcap_records(path) if m[0].endswith("_calibrated"))

    expected = calibrated(indexed)
    assert len(expected) > 1000 and calibrated(out) == expected
    with LogReader(out) as reader:
        assert reader.topics[f"/ft/{LEG}/wrench_calibrated"].message_count == sum(
            m[0] == f"/ft/{LEG}/wrench_calibrated" for m in expected
        )


def test_the_export_records_which_boards_it_belongs_to(setup: dict, tmp_path: Path, capsys: Any) -> None:
    """The serials recorded at export: the training logs' where they record them (they must agree), else
    robot.serials; a log that records none is calibrated with a warning that it could not be checked."""
    from pipeline.core.errors import DataError
    from pipeline.export.identity import training_serials

    manifest = json.loads((setup["export"] / "manifest.json").read_text())
    assert manifest["graphs"]["all"]["serials"] == SERIALS
    assert manifest["graphs"][PAIR]["serials"] == {FRONT: SERIALS[FRONT], REAR: SERIALS[REAR]}
    logs = {"a.parquet": {f"serial.{LEG}": "FT58-7"}, "b.parquet": {"type": "pole"}}
    assert training_serials(logs, [LEG, FRONT], SERIALS) == {LEG: "FT58-7", FRONT: SERIALS[FRONT]}
    with pytest.raises(
        DataError, match=f"c.parquet: {LEG} is serial 'FT58-8' there but 'FT58-7' in a.parquet"
    ):
        training_serials({**logs, "c.parquet": {f"serial.{LEG}": "FT58-8"}}, [LEG], None)
    unrecorded = tmp_path / "unrecorded.mcap"
    write_log(unrecorded, SENSORS, 2.0)
    assert main(_cli(setup, unrecorded, tmp_path / "out.mcap")) == 0
    assert f"records no serial of {LEG}, {FRONT}, {REAR}: cannot check" in capsys.readouterr().err


@pytest.fixture(scope="module", params=["play", "arx", "win"])
def memory_export(setup: dict, tmp_path_factory: pytest.TempPathFactory, request: Any) -> tuple[str, Path]:
    """The same trained groups exported with a model with memory recommended: (its name, the export)."""
    tmp = tmp_path_factory.mktemp(f"calibrate_{request.param}")
    report = _metrics_dir(tmp, {LEG: request.param, PAIR: request.param})
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
    try:
        params = load_params(setup["params"])
        E.run(params, setup["models"], report, setup["labelled"], tmp / "exported")
    finally:
        patch.undo()
    return request.param, tmp / "exported"


def _spike(sensor: str, t: np.ndarray, w: np.ndarray) -> None:
    """The leg's fx 60 N higher at one message, 6 s into the log."""
    if sensor == LEG:
        w[np.abs(t - 6.0) < 1e-6, 0] += 60.0


def test_calibrate_with_memory_is_causal_and_carries_the_state(
    setup: dict, memory_export: tuple[str, Path], tmp_path: Path
) -> None:
    """A play, arx or windowed model's calibration of every raw message equals the project's model run over
    the sensor's messages in stamp order from the log's first (the state carried across ~15 chunks); a
    message changed 6 s into the log changes no earlier output, and later ones too (the state remembers
    it)."""
    logs = {"plain": setup["log"], "spiked": tmp_path / "spiked.mcap"}
    write_log(logs["spiked"], SENSORS, 10.0, seed=3, chunk_size=32 * 1024, serials=SERIALS, edit=_spike)
    got = {}
    for name, log in logs.items():
        out = tmp_path / f"{name}_calibrated.mcap"
        assert main(_cli(setup, log, out, models=memory_export[1])) == 0
        got[name] = ros2_messages(out)
    decoded = ros2_messages(setup["log"])
    for sensor, group in ((LEG, LEG), (FRONT, PAIR)):
        model = read_group(setup["models"] / group, memory_export[0])
        slot = model.sensors.index(sensor)
        expected = _expected(decoded, sensor, model.n_inputs)  # in log-time order: sorted by stamp here
        raw = [(stamp_ns(m.ros_msg), xyz(m.ros_msg.wrench.force) + xyz(m.ros_msg.wrench.torque), e)
               for m, e in zip(decoded[f"/ft/{sensor}/wrench"], expected, strict=True)]  # fmt: skip
        raw.sort(key=lambda r: r[0])
        x = np.array([r[2][1] if r[2] is not None else [*r[1], np.nan] for r in raw])
        y = model.reference(np.tile(x, (1, len(model.sensors))))[:, slot * 6 : (slot + 1) * 6]
        calibrated = sorted(
            got["plain"][f"/ft/{sensor}/wrench_calibrated"], key=lambda m: stamp_ns(m.ros_msg)
        )
        np.testing.assert_allclose(_wrenches(calibrated), y[np.isfinite(y).all(axis=1)], rtol=0, atol=1e-9)
    plain, spiked = (sorted(got[k][f"/ft/{LEG}/wrench_calibrated"], key=lambda m: stamp_ns(m.ros_msg))
                     for k in ("plain", "spiked"))  # fmt: skip
    stamps = np.array([stamp_ns(m.ros_msg) for m in plain])
    diff = np.abs(_wrenches(spiked) - _wrenches(plain)).max(axis=1)
    first = int(np.flatnonzero(diff > 0)[0])
    assert 5.9 < (stamps[first] - stamps[0]) / 1e9 < 6.1  # nothing before the changed message moved
    assert diff[first + 1 :].max() > 1e-3  # the memory carries it on (a memoryless model: 0)


def _wrenches(messages: list[Any]) -> np.ndarray:
    return np.array([xyz(m.ros_msg.wrench.force) + xyz(m.ros_msg.wrench.torque) for m in messages])


def test_filters_refuse_a_log_at_another_rate(
    setup: dict, memory_export: tuple[str, Path], tmp_path: Path, capsys: Any
) -> None:
    """An arx or windowed model's filters were trained at 100 Hz: a 50 Hz log is refused, naming the topic
    and both periods, and nothing is written; a play model reads the path alone and calibrates it."""
    name, export = memory_export
    log, out = tmp_path / "slow.mcap", tmp_path / "slow_calibrated.mcap"
    write_log(log, SENSORS, 4.0, rate_hz=50.0, seed=4, serials=SERIALS)
    code = main(_cli(setup, log, out, models=export))
    err = capsys.readouterr().err
    if name in ("arx", "win"):
        assert code != 0 and not out.exists()
        assert f"/ft/{LEG}/wrench: messages 20 ms apart" in err and "run at 10 ms" in err, err
    else:
        assert code == 0 and out.exists()
