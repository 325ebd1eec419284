"""The per-log MCAP of ``logpipe predict``: originals copied byte for byte, ``logpipe.Predictions`` valid
against its JSON Schema, the Foxglove channels Protobuf messages of Foxglove's own classes (what they draw:
tests/mcap/test_foxglove.py)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from logpipe.mcap import foxglove as fx
from logpipe.mcap.forecast_scene import TargetForecasts, forecast_scene_updates
from logpipe.mcap.merge import NewChannel, NewMessage, Source, write_merged
from logpipe.model.synthetic import make_scene
from logpipe.stages.ingest import IngestOptions, ingest

REPO = Path(__file__).resolve().parents[2]


def read_all(path: Path) -> tuple[dict[str, Any], list[tuple[str, int, int, int, bytes]]]:
    """(channels by topic: encoding, schema name/encoding/data, metadata), messages in file order."""
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        channels = {}
        for c in summary.channels.values():
            s = summary.schemas.get(c.schema_id)
            channels[c.topic] = (c.message_encoding, c.metadata, None if s is None else (s.name, s.encoding, s.data))
        messages = [(ch.topic, m.log_time, m.publish_time, m.sequence, m.data)
                    for _, ch, m in reader.iter_messages(log_time_order=False)]
    return channels, messages


def test_forecast_points_are_the_samples_and_forecasts_numbers_to_a_millimetre() -> None:
    rng = np.random.default_rng(0)
    sample = make_scene(rng, 4, obs_len=8, pred_len=12)
    sample.positions += rng.uniform(-5e3, 5e3, size=(4, 1, 2))  # city-frame metres
    targets = np.flatnonzero(sample.target_mask)
    futures = rng.normal(size=(len(targets), 5, 12, 2)) * 1e3
    forecasts = TargetForecasts.of_sample(sample, targets, futures, np.full((len(targets), 5), 0.2))
    update = fx.MESSAGE_CLASSES["foxglove.SceneUpdate"].FromString(forecast_scene_updates(
        forecasts, ["map"], [1_700_000_000_123_456_789], [4_800_000_000])[0])
    assert len(update.entities) == len(targets)
    drawn = fx.snap(sample.positions, fx.POSITION_QUANTUM)
    assert np.abs(drawn - sample.positions).max() <= fx.POSITION_QUANTUM / 2
    for j, entity in enumerate(update.entities):
        lines = [[(p.x, p.y) for p in line.points] for line in entity.lines]
        window = [tuple(p) for p in drawn[targets[j]].tolist()]
        assert lines[0] == window[:8] and lines[1] == window[7:]  # history, then the current point + truth
        modes = fx.snap(futures[j], fx.POSITION_QUANTUM)
        assert lines[2:] == [[window[7], *map(tuple, f.tolist())] for f in modes]


def test_merge_copies_every_record_of_an_mcap(tmp_path: Path) -> None:
    src = tmp_path / "src.mcap"
    with src.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="x-test", library="test")
        a = w.register_schema("a.A", "jsonschema", b'{"type":"object"}')
        b = w.register_schema("b.B", "protobuf", b"\x01\x02\x03")
        ca = w.register_channel("/a", "json", a, {"k": "v"})
        cb = w.register_channel("/b", "protobuf", b)
        cn = w.register_channel("/raw", "cbor", 0)
        for i in range(50):
            w.add_message([ca, cb, cn][i % 3], log_time=1000 - i, publish_time=i, data=bytes([i]) * i, sequence=i)
        w.add_metadata("m", {"x": "1"})
        w.add_attachment(create_time=1, log_time=2, name="calib.yaml", media_type="text/yaml", data=b"k: 1\n")
        w.finish()  # type: ignore[no-untyped-call]
    out = tmp_path / "out.mcap"
    extra = NewChannel("/p", "p.P", "jsonschema", b"{}", "json", {"frame_id": "world"})
    stats = write_merged(out, [Source((src,), "mcap", "src.mcap")], [extra],
                         [NewMessage(0, 5, 5, b'{"a":1}'), NewMessage(0, 6, 6, b"{}")], metadata={"n": {"y": "2"}})
    assert (stats.messages, stats.channels, stats.schemas, stats.appended) == (50, 3, 2, 2)
    channels_in, messages_in = read_all(src)
    channels_out, messages_out = read_all(out)
    assert {k: v for k, v in channels_out.items() if k != "/p"} == channels_in
    assert messages_out[:50] == messages_in  # same order, times, sequence numbers and bytes
    assert messages_out[50:] == [("/p", 5, 5, 0, b'{"a":1}'), ("/p", 6, 6, 1, b"{}")]
    with out.open("rb") as fh:
        reader = make_reader(fh)
        assert reader.get_header().profile == "x-test"
        assert {m.name: m.metadata for m in reader.iter_metadata()} == {"m": {"x": "1"}, "n": {"y": "2"}}
        assert [(a.name, a.data) for a in reader.iter_attachments()] == [("calib.yaml", b"k: 1\n")]


@pytest.fixture(scope="module")
def eth_predicted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from logpipe.dataset.sample_filter import parse_filter
    from logpipe.stages.predict import predict_dataset

    root = tmp_path_factory.mktemp("eth")
    ingest([REPO / "tests" / "data" / "ethucy"], IngestOptions(out=root / "ds"))
    # Samples of the first 60 s of each log keep the test short; every log still gets its MCAP.
    summary = predict_dataset(root / "ds", root / "out", predictor="cv_sampler", modes=5,
                              sample_filter=parse_filter(["time=:60000000000"]))
    assert summary["mcap_files"] == 3 and 0 < summary["samples"] < 400
    return root / "ds", root / "out"


def test_text_logs_keep_the_ingest_mcap_and_gain_valid_prediction_channels(eth_predicted: tuple[Path, Path]) -> None:
    from logpipe.dataset.reader import Dataset

    ds, out = eth_predicted
    dataset = Dataset.open(ds)
    raw_schema = None
    for log_id in dataset.logs().column("log_id").to_pylist():
        original = dataset.mcap_path(log_id)
        written = out / "mcap" / original.parent.name / original.name
        channels_in, messages_in = read_all(original)
        channels_out, messages_out = read_all(written)
        assert {k: channels_out[k] for k in channels_in} == channels_in
        assert messages_out[: len(messages_in)] == messages_in
        added = messages_out[len(messages_in):]
        assert {t for t, *_ in added} == {"/logpipe/predictions", "/logpipe/predictions/scene", "/logpipe/legend"}
        legend = [fx.MESSAGE_CLASSES["foxglove.SceneUpdate"].FromString(d) for t, *_, d in added
                  if t == "/logpipe/legend"]
        assert len(legend) == 1 and [x.text for x in legend[0].entities[0].texts] == [
            "history", "truth", "forecasts", "lanes"]  # once per log; the ingest MCAP has the agents already
        raw_schema = jsonschema.Draft202012Validator(json.loads(channels_out["/logpipe/predictions"][2][2]))
        assert channels_out["/logpipe/predictions/scene"][2][:2] == ("foxglove.SceneUpdate", "protobuf")
        assert channels_out["/logpipe/predictions/scene"][2][2] == fx.schema_data(
            fx.MESSAGE_CLASSES["foxglove.SceneUpdate"])
        for topic, log_time, _, _, data in added[::7]:  # validating every message of a log takes seconds
            if topic == "/logpipe/predictions/scene":
                update = fx.MESSAGE_CLASSES["foxglove.SceneUpdate"].FromString(data)
                assert update.entities and all(e.frame_id == "world" for e in update.entities)
                continue
            doc = json.loads(data)
            raw_schema.validate(doc)
            assert doc["timestamp_ns"] == log_time and doc["frame_id"] == "world"
            assert np.asarray(doc["x"]).shape == (len(doc["track_id"]), 5, 12)
    assert raw_schema is not None
