"""``logpipe predict`` end to end on the real data of ../shared/data: the datmo ROS1 bag (every original
message byte-identical in the output MCAP), Argoverse 1 with rasters and the environment net, ETH/UCY."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader
from mcap_ros1.decoder import DecoderFactory
from rosbags.highlevel import AnyReader

from logpipe.dataset.reader import Dataset
from logpipe.dataset.sample_filter import parse_filter
from logpipe.errors import LogpipeError
from logpipe.maps import MapSource
from logpipe.mcap.foxglove import MESSAGE_CLASSES
from logpipe.model.zhu2020.checkpoint import save_checkpoint
from logpipe.model.zhu2020.config import Features, ModelConfig, TrainConfig
from logpipe.model.zhu2020.network import TrajectoryNet
from logpipe.prediction.runs import PredictionRun
from logpipe.raster.rasteriser import RasterSpec
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.predict import predict_dataset
from logpipe.stages.rasterise import rasterise_dataset

pytestmark = pytest.mark.shared
REPO = Path(__file__).resolve().parents[2]


def _foxglove(name: str, data: bytes) -> Any:
    """A Foxglove message decoded by Foxglove's own Protobuf class."""
    return MESSAGE_CLASSES[name].FromString(data)


def test_datmo_bag_is_copied_unchanged_with_predictions_in_its_map_frame(shared: Path, tmp_path: Path) -> None:
    real = shared / "rosbags" / "datmo" / "intersection.bag"
    bag = tmp_path / "src" / "intersection.bag"
    bag.parent.mkdir()
    bag.write_bytes(real.read_bytes())
    ingest([bag.parent], IngestOptions(out=tmp_path / "ds"))
    bag.parent.rename(tmp_path / "moved")  # the recorded input root is gone: predict must be told where it is
    bag = tmp_path / "moved" / "intersection.bag"
    with pytest.raises(LogpipeError, match="--inputs"):
        predict_dataset(tmp_path / "ds", tmp_path / "out", predictor="cv")
    other = tmp_path / "other" / "intersection.bag"
    other.parent.mkdir()
    other.write_bytes((shared / "rosbags" / "datmo" / "parallel.bag").read_bytes())
    with pytest.raises(LogpipeError, match="sha256"):
        predict_dataset(tmp_path / "ds", tmp_path / "out", predictor="cv", inputs=[other.parent])
    summary = predict_dataset(tmp_path / "ds", tmp_path / "out", predictor="kalman", inputs=[bag.parent])
    assert summary["samples"] == 2 and summary["mcap_files"] == 1
    written = next((tmp_path / "out" / "mcap").glob("*/intersection.mcap"))

    with AnyReader([bag]) as reader:
        expected = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
        defs = {c.topic: (c.msgdef.data, c.digest) for c in reader.connections}
    with written.open("rb") as fh:
        out = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert out.get_header().profile == "ros1"
        got = []
        poses = boxes = 0
        for schema, channel, message in out.iter_messages(log_time_order=False):
            if channel.topic.startswith("/logpipe/"):
                assert schema is not None
                if channel.topic in ("/logpipe/predictions/scene", "/logpipe/legend"):
                    scene = _foxglove(schema.name, message.data)
                    assert scene.entities[0].frame_id == "map"  # the bag's world frame
                elif channel.topic == "/logpipe/scene":  # the agents' boxes, which the bag lacks
                    scene = _foxglove(schema.name, message.data)
                    assert {e.id for e in scene.entities} <= {"ego", "red"} and all(e.cubes for e in scene.entities)
                    assert scene.entities[0].frame_id == "map"
                    boxes += 1
                else:
                    doc = json.loads(message.data)
                    jsonschema.validate(doc, json.loads(schema.data))
                    assert doc["frame_id"] == "map" and sorted(doc["track_id"]) == ["ego", "red"]
                continue
            assert schema is not None and channel.message_encoding == "ros1" and schema.encoding == "ros1msg"
            assert (schema.data.decode(), channel.metadata["md5sum"]) == defs[channel.topic]
            got.append((channel.topic, message.log_time, message.data))
        for _, _, _, decoded in out.iter_decoded_messages(topics=["/ego_pose"]):
            poses += 1
            assert decoded.header.frame_id == "map"
    assert got == expected  # every original message, same bytes, same times, same order
    assert poses == sum(1 for topic, _, _ in expected if topic == "/ego_pose")
    assert boxes == len(Dataset.open(tmp_path / "ds").tracks().column("step").unique())  # one per step
    table = pq.read_table(tmp_path / "out" / "predictions" / "part-00000.parquet")
    assert table.num_rows == 2 * 2 * 6 and PredictionRun.open(tmp_path / "out").meta.predictor == "kalman"


def test_argoverse1_with_rasters_and_the_environment_net(shared: Path, tmp_path: Path) -> None:
    ds = tmp_path / "av1"
    ingest([shared / "argoverse1" / "data"], IngestOptions(out=ds))
    cfg = ModelConfig(obs_len=20, pred_len=30, embed_dim=16, gru_dim=16, lstm_dim=16, noise_dim=4,
                      raster_channels=len(RasterSpec().channels), features=Features(True, True, True, True, True))
    ckpt = save_checkpoint(tmp_path / "ckpt", TrajectoryNet(cfg), TrainConfig(model=cfg), dataset_kind="argoverse1",
                           manifest_hash="x", step=0)
    with pytest.raises(LogpipeError, match="rasterise"):  # the env net needs rasters: refused before any work
        predict_dataset(ds, tmp_path / "out", checkpoint=ckpt)
    assert not (tmp_path / "out").exists()
    rasterise_dataset(ds, MapSource(roots=(shared / "argoverse1" / "maps",)), rotate=True)
    few = parse_filter(["log=1,10,11,12"])
    summary = predict_dataset(ds, tmp_path / "out", checkpoint=ckpt, seed=5, sample_filter=few)
    assert summary["samples"] == 4 and summary["num_modes"] == 6 and summary["mcap_files"] == 4
    table = pq.read_table(tmp_path / "out" / "predictions" / "part-00000.parquet")
    assert table.num_rows == 4 * 1 * 6 and np.isfinite(table.column("x").combine_chunks().flatten().to_numpy()).all()
    focal = Dataset.open(ds).samples().to_pydict()
    assert set(table.column("track_id").to_pylist()) <= {t for ts in focal["target_track_ids"] for t in ts}
    with next((tmp_path / "out" / "mcap").glob("*/1.mcap")).open("rb") as fh:
        topics: dict[str, list[tuple[str, bytes]]] = {}
        for schema, channel, message in make_reader(fh).iter_messages():
            topics.setdefault(channel.topic, []).append((schema.name if schema else "", message.data))
    assert {"/logpipe/agents", "/logpipe/scene", "/logpipe/tf", "/logpipe/ego_pose", "/logpipe/predictions",
            "/logpipe/predictions/scene", "/logpipe/raster", "/logpipe/raster/grid",
            "/logpipe/raster/tf"} <= set(topics)
    image = _foxglove(*topics["/logpipe/raster"][0])
    grid = _foxglove(*topics["/logpipe/raster/grid"][0])
    assert image.format == "png" and image.frame_id == grid.frame_id == "logpipe_raster"
    assert grid.column_count == RasterSpec().size_px
    assert _foxglove(*topics["/logpipe/raster/tf"][0]).child_frame_id == "logpipe_raster"
    assert _foxglove(*topics["/logpipe/predictions/scene"][0]).entities
    # All 69 logs with the constant-velocity baseline (rasters shown, not needed).
    every = predict_dataset(ds, tmp_path / "cv", predictor="cv")
    assert every["samples"] == 69 and every["mcap_files"] == 69 and every["rows"] == 69 * 6


def test_ethucy_test_split_end_to_end(shared: Path, tmp_path: Path) -> None:
    ingest([shared / "ethucy"], IngestOptions(out=tmp_path / "eth"))
    summary = predict_dataset(tmp_path / "eth", tmp_path / "out", predictor="cv",
                              sample_filter=parse_filter(["split=eth/test"]))
    samples = Dataset.open(tmp_path / "eth").samples().to_pydict()
    chosen = [t for log, t in zip(samples["log_id"], samples["target_track_ids"], strict=True) if log == "biwi_eth"]
    assert summary["logs_selected"] == 1 and summary["samples"] == len(chosen) == 253
    assert summary["rows"] == sum(len(t) for t in chosen) * 20
    table = pq.read_table(tmp_path / "out" / "predictions" / "part-00000.parquet", columns=["log_id", "x"])
    assert set(table.column("log_id").to_pylist()) == {"biwi_eth"}
    assert np.isfinite(table.column("x").combine_chunks().flatten().to_numpy()).all()


def test_ros2_sqlite_bags_and_plain_mcap_copy_unchanged(shared: Path, tmp_path: Path) -> None:
    from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

    from logpipe.mcap.merge import Source, write_merged

    folder = shared / "rosbags" / "rosbag2" / "rosbag2_tests" / "resources" / "sqlite3" / "cdr_test"
    write_merged(tmp_path / "ros2.mcap", [Source((folder,), "rosbag", folder.name)], [], [])
    with AnyReader([folder]) as reader:
        expected = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
    with (tmp_path / "ros2.mcap").open("rb") as fh:
        out = make_reader(fh, decoder_factories=[Ros2DecoderFactory()])
        assert out.get_header().profile == "ros2"
        got = [(ch.topic, m.log_time, m.data) for _, ch, m in out.iter_messages(log_time_order=False)]
        decoded = [d for _, _, _, d in out.iter_decoded_messages(topics=["/test_topic"])]
    assert got == expected and decoded  # the generated ros2msg schemas decode the CDR bytes
    plain = shared / "mcap" / "evo" / "nav2_turtlebot.mcap"
    write_merged(tmp_path / "plain.mcap", [Source((plain,), "mcap", plain.name)], [], [])

    def messages(path: Path) -> list[tuple[str, int, int, int, bytes]]:
        with path.open("rb") as fh:
            return [(c.topic, m.log_time, m.publish_time, m.sequence, m.data)
                    for _, c, m in make_reader(fh).iter_messages(log_time_order=False)]

    assert messages(tmp_path / "plain.mcap") == messages(plain)


def test_recorded_input_root_is_found_without_inputs_option(bundled: Path, tmp_path: Path) -> None:
    bag = bundled / "rosbags" / "datmo" / "intersection.bag"
    ingest([bag], IngestOptions(out=tmp_path / "ds"))
    summary = predict_dataset(tmp_path / "ds", tmp_path / "out", predictor="cv")
    assert summary["mcap_files"] == 1
