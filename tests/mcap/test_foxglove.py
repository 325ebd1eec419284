"""Viewer-ready MCAPs: every Foxglove message logpipe writes is a message of Foxglove's own Protobuf classes
(and of the schema embedded in the file), every agent of every step is an entity, every frame a message uses
hangs off one transform tree, and prediction files carry the true future and the raster under the scene."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders
from mcap_ros1.decoder import DecoderFactory as Ros1Decoders
from mcap_ros2.decoder import DecoderFactory as Ros2Decoders

from logpipe.dataset.reader import Dataset
from logpipe.dataset.sample_filter import parse_filter
from logpipe.maps import MapSource
from logpipe.mcap import forecast_scene as ff
from logpipe.mcap import foxglove as fx
from logpipe.mcap import raster_image as fr
from logpipe.mcap.tracks import EGO_TOPIC, LOG_FRAME, SCENE_TOPIC, TF_TOPIC, WORLD_FRAME
from logpipe.model.synthetic import make_scene, world_to_raster_affine
from logpipe.prediction.mcap_logs import RASTER_FRAME, RASTER_GRID_TOPIC, RASTER_TF_TOPIC, RASTER_TOPIC
from logpipe.prediction.mcap_logs import SCENE_TOPIC as FORECAST_TOPIC
from logpipe.raster.rasteriser import RasterSpec, world_to_pixel
from logpipe.raster.runs import find_raster_run
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.predict import predict_dataset
from logpipe.stages.rasterise import rasterise_dataset
from logpipe.types import OBJECT_TYPES

REPO = Path(__file__).resolve().parents[2]
BUNDLED = REPO / "tests" / "data"
TF_SCHEMAS = ("tf2_msgs/TFMessage", "tf2_msgs/msg/TFMessage", "tf/tfMessage")


# ---------------------------------------------------------------------------------------------------------
# Reading an MCAP back.


@dataclass
class Opened:
    """What a test needs of one MCAP: decoded Foxglove messages by topic (log-time order), the transform tree
    (child -> parent, from Foxglove FrameTransforms and ROS /tf) and every frame a message is in."""

    topics: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)
    parents: dict[str, str] = field(default_factory=dict)
    frames: set[str] = field(default_factory=set)

    def add_edge(self, parent: str, child: str) -> None:
        parent, child = parent.lstrip("/"), child.lstrip("/")
        assert self.parents.setdefault(child, parent) == parent, f"{child} has two parents"

    def root_of(self, frame: str) -> str:
        chain = [frame.lstrip("/")]
        while chain[-1] in self.parents:
            chain.append(self.parents[chain[-1]])
            assert len(chain) < 64, f"transform cycle through {chain}"
        return chain[-1]


def open_mcap(path: Path) -> Opened:
    """Decode every Foxglove channel with Foxglove's class, check it round-trips and equals what the schema
    embedded in the file decodes; collect /tf from ROS logs."""
    out = Opened()
    embedded = ProtobufDecoders()
    ros = [Ros1Decoders(), Ros2Decoders()]
    with path.open("rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=True):
            if schema is not None and schema.name in fx.MESSAGE_CLASSES:
                assert (schema.encoding, channel.message_encoding) == ("protobuf", "protobuf")
                cls = fx.MESSAGE_CLASSES[schema.name]
                msg = cls.FromString(message.data)
                assert cls.FromString(msg.SerializeToString()) == msg
                decode = embedded.decoder_for("protobuf", schema)
                assert decode is not None and decode(message.data).SerializeToString() == msg.SerializeToString()
                out.topics.setdefault(channel.topic, []).append((message.log_time, msg))
                _collect_frames(out, schema.name, msg)
            elif schema is not None and schema.name.startswith("foxglove."):
                raise AssertionError(f"{channel.topic}: {schema.name} is not Protobuf-encoded")
            elif schema is not None and schema.name in TF_SCHEMAS:
                decoder = next(d for f in ros if (d := f.decoder_for(channel.message_encoding, schema)))
                for tf in decoder(message.data).transforms:
                    out.add_edge(tf.header.frame_id, tf.child_frame_id)
    return out


def _collect_frames(out: Opened, name: str, msg: Any) -> None:
    if name == "foxglove.FrameTransform":
        out.add_edge(msg.parent_frame_id, msg.child_frame_id)
    elif name == "foxglove.SceneUpdate":
        out.frames.update(e.frame_id for e in msg.entities)
    else:
        out.frames.add(msg.frame_id)


def assert_one_tree(opened: Opened, root: str | None) -> None:
    """Every frame used reaches the same root through the transforms (``root`` when given)."""
    assert opened.frames
    roots = {opened.root_of(f) for f in opened.frames}
    assert len(roots) == 1, f"frames {sorted(opened.frames)} reach several roots {sorted(roots)}"
    if root is not None:
        assert roots == {root}


def _png_rgb(data: bytes) -> np.ndarray:
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert bgr is not None
    return np.asarray(bgr)[..., ::-1]


def _yaw(q: Any) -> float:
    return 2.0 * math.atan2(q.z, q.w)


# ---------------------------------------------------------------------------------------------------------
# Ingest MCAPs against the track table.


def check_ingest_mcap(path: Path, tracks: pa.Table) -> None:
    """One ingest MCAP against its log's rows: an entity per row at its step (id, place, metadata), the agents
    that left deleted, the ego's poses and frame, the root centred on the log, every frame reachable."""
    opened = open_mcap(path)
    assert_one_tree(opened, LOG_FRAME)
    cols = {n: tracks.column(n).to_pylist() for n in ("step", "timestamp_ns", "track_id", "object_type", "role")}
    x, y = tracks.column("x").to_numpy(), tracks.column("y").to_numpy()
    sx, sy = fx.snap(x, fx.POSITION_QUANTUM), fx.snap(y, fx.POSITION_QUANTUM)  # what is drawn: ~1 mm
    heading = pc.fill_null(tracks.column("heading"), math.nan).to_numpy()
    steps = np.asarray(cols["step"])
    starts = np.concatenate([[0], np.flatnonzero(np.diff(steps)) + 1, [len(steps)]]).tolist()
    scenes = opened.topics[SCENE_TOPIC]
    assert len(scenes) == len(starts) - 1
    before: set[str] = set()
    for (lo, hi), (log_time, update) in zip(itertools.pairwise(starts), scenes, strict=True):
        t = cols["timestamp_ns"][lo]
        assert log_time == t
        assert [e.id for e in update.entities] == cols["track_id"][lo:hi]
        for row, e in zip(range(lo, hi), update.entities, strict=True):
            assert e.frame_id == WORLD_FRAME and e.timestamp.seconds * 10**9 + e.timestamp.nanos == t
            assert {kv.key: kv.value for kv in e.metadata} == {
                "track_id": cols["track_id"][row], "object_type": cols["object_type"][row], "role": cols["role"][row]}
            cube = e.cubes[0]
            assert (cube.pose.position.x, cube.pose.position.y) == (sx[row], sy[row])
            assert abs(cube.pose.position.x - x[row]) <= fx.POSITION_QUANTUM / 2
            size = fx.AGENT_SHAPES.get(cols["object_type"][row], fx.AGENT_SHAPES["unknown"])
            assert (cube.size.x, cube.size.y, cube.size.z) == size
            if np.isfinite(heading[row]):  # a heading the log gives is drawn as given
                turn = math.remainder(_yaw(cube.pose.orientation) - heading[row], math.tau)
                assert len(e.arrows) == 1 and abs(turn) < 1e-3
        now = set(cols["track_id"][lo:hi])
        deleted = {d.id for d in update.deletions}
        assert deleted == before - now and all(d.type == SceneEntityDeletion.MATCHING_ID for d in update.deletions)
        before = now
    transforms = [m for _, m in opened.topics[TF_TOPIC]]
    centre = ((x.min() + x.max()) / 2, (y.min() + y.max()) / 2)
    roots = [m for m in transforms if m.parent_frame_id == LOG_FRAME]
    assert len(roots) == 1 and roots[0].child_frame_id == WORLD_FRAME
    assert (roots[0].translation.x, roots[0].translation.y) == pytest.approx((-centre[0], -centre[1]))
    ego = [i for i, r in enumerate(cols["role"]) if r == "ego"]
    poses = [m for _, m in opened.topics.get(EGO_TOPIC, [])]
    to_ego = [m for m in transforms if m.parent_frame_id != LOG_FRAME]
    assert len(poses) == len(ego) == len(to_ego)
    for row, pose, tf in zip(ego, poses, to_ego, strict=True):
        assert (pose.pose.position.x, pose.pose.position.y) == (sx[row], sy[row])
        assert (tf.parent_frame_id, tf.child_frame_id) == (WORLD_FRAME, "ego")
        assert (tf.translation.x, tf.translation.y) == (sx[row], sy[row])
        assert tf.rotation == pose.pose.orientation


def check_dataset_mcaps(ds_dir: Path) -> int:
    ds = Dataset.open(ds_dir)
    logs = ds.logs().column("log_id").to_pylist()
    for log_id in logs:
        check_ingest_mcap(ds.mcap_path(log_id), ds.log_tracks(log_id))
    return len(logs)


@pytest.mark.parametrize(("inputs", "logs"), [
    (["argoverse1"], 6),
    (["ethucy"], 3),
    (["apolloscape"], 2),
    (["rosbags", "datmo", "intersection.bag"], 1),
])
def test_ingest_mcaps_draw_every_agent_in_one_tree(inputs: list[str], logs: int, tmp_path: Path) -> None:
    ingest([BUNDLED.joinpath(*inputs)], IngestOptions(out=tmp_path / "ds", workers=1))
    assert check_dataset_mcaps(tmp_path / "ds") == logs


@pytest.mark.parametrize(("inputs", "logs"), [(["mcap", "evo", "nav2_turtlebot.mcap"], 1), (["av2"], 5)])
def test_ingest_mcaps_of_real_mcap_and_av2_inputs(shared: Path, inputs: list[str], logs: int, tmp_path: Path) -> None:
    ingest([shared.joinpath(*inputs)], IngestOptions(out=tmp_path / "ds", workers=1))
    assert check_dataset_mcaps(tmp_path / "ds") == logs


# ---------------------------------------------------------------------------------------------------------
# Prediction MCAPs.


def check_prediction_mcap(path: Path, ds: Dataset, log_id: str, frame: str, *, raster: bool,
                          root: str | None) -> int:
    """Per sample an entity per predicted target with the true future, a marker and K modes; with rasters
    an image, a grid and the transform placing them, at the sample's time. Returns the samples seen."""
    opened = open_mcap(path)
    assert_one_tree(opened, root)
    tracks = ds.log_tracks(log_id)
    drawn = [fx.snap(tracks.column(c).to_numpy(), fx.POSITION_QUANTUM).tolist() for c in ("x", "y")]
    by_key = {(s, t): (x, y) for s, t, x, y in zip(tracks.column("step").to_pylist(),
                                                   tracks.column("track_id").to_pylist(), *drawn, strict=True)}
    samples = {r["sample_id"]: r for r in ds.samples().to_pylist() if r["log_id"] == log_id}
    updates = opened.topics.get(FORECAST_TOPIC, [])
    for log_time, update in updates:
        assert update.entities
        for e in update.entities:
            meta = {kv.key: kv.value for kv in e.metadata}
            sample = samples[meta["sample_id"]]
            assert e.frame_id == frame and e.id == meta["track_id"] in sample["target_track_ids"]
            assert e.timestamp.seconds * 10**9 + e.timestamp.nanos == log_time == sample["current_ns"]
            current = by_key[(sample["current_step"], e.id)]
            assert (e.spheres[0].pose.position.x, e.spheres[0].pose.position.y) == current
            truth = [by_key[(s, e.id)] for s in range(sample["current_step"] + 1, sample["end_step"] + 1)
                     if (s, e.id) in by_key]
            styled = {(ln.color.r, ln.color.g, ln.color.b): ln for ln in e.lines}
            assert bool(truth) == (ff.TRUTH_RGBA[:3] in styled)
            if truth:
                points = [(p.x, p.y) for p in styled[ff.TRUTH_RGBA[:3]].points]
                assert points == [current, *truth]
            modes = [ln for ln in e.lines if (ln.color.r, ln.color.g, ln.color.b) == ff.MODE_RGB]
            assert modes and all((ln.points[0].x, ln.points[0].y) == current for ln in modes)
    images = opened.topics.get(RASTER_TOPIC, [])
    grids = opened.topics.get(RASTER_GRID_TOPIC, [])
    transforms = opened.topics.get(RASTER_TF_TOPIC, [])
    if raster:
        assert len(images) == len(grids) == len(transforms) == len(updates)
        for (t0, image), (t1, grid), (t2, tf) in zip(images, grids, transforms, strict=True):
            assert t0 == t1 == t2 and image.frame_id == grid.frame_id == tf.child_frame_id == RASTER_FRAME
            assert tf.parent_frame_id == frame and image.format == "png"
            rgb = _png_rgb(image.data)
            rgba = np.frombuffer(grid.data, np.uint8).reshape(-1, grid.column_count, 4)
            assert np.array_equal(rgba[::-1, :, :3], rgb)  # the grid is the image, bottom row first
    else:
        assert not images and not grids and not transforms
    return len(updates)


def test_text_logs_predictions_show_truth_in_the_ingest_tree(tmp_path: Path) -> None:
    ingest([BUNDLED / "ethucy"], IngestOptions(out=tmp_path / "ds", workers=1))
    predict_dataset(tmp_path / "ds", tmp_path / "out", predictor="cv_sampler", modes=3,
                    sample_filter=parse_filter(["time=:30000000000"]))
    ds = Dataset.open(tmp_path / "ds")
    seen = 0
    for log_id in ds.logs().column("log_id").to_pylist():
        written = tmp_path / "out" / "mcap" / ds.mcap_path(log_id).parent.name / f"{log_id}.mcap"
        seen += check_prediction_mcap(written, ds, log_id, WORLD_FRAME, raster=False, root=LOG_FRAME)
    assert seen > 0


def test_predictions_with_rasters_lay_the_map_under_the_scene(tmp_path: Path) -> None:
    src = tmp_path / "csv"
    src.mkdir()
    for name in ("2645.csv", "3861.csv"):
        (src / name).write_bytes((BUNDLED / "maps" / name).read_bytes())
    ingest([src], IngestOptions(out=tmp_path / "ds", workers=1))
    rasterise_dataset(tmp_path / "ds", MapSource(roots=(BUNDLED / "maps",)), rotate=True)
    predict_dataset(tmp_path / "ds", tmp_path / "out", predictor="cv")
    ds = Dataset.open(tmp_path / "ds")
    rasters = find_raster_run(tmp_path / "ds", None, None)
    assert rasters is not None
    for log_id in ("2645", "3861"):
        written = tmp_path / "out" / "mcap" / ds.mcap_path(log_id).parent.name / f"{log_id}.mcap"
        assert check_prediction_mcap(written, ds, log_id, WORLD_FRAME, raster=True, root=LOG_FRAME) == 1
        opened = open_mcap(written)
        (_, image), (_, tf) = opened.topics[RASTER_TOPIC][0], opened.topics[RASTER_TF_TOPIC][0]
        sample_id = next(r["sample_id"] for r in ds.samples().to_pylist() if r["log_id"] == log_id)
        raster, affine = rasters.get(sample_id)
        rgb = _png_rgb(image.data)
        assert np.array_equal(rgb, fr.raster_rgb(np.asarray(raster), rasters.spec.channels)) and rgb.any()
        _assert_transform_matches_affine(tf, affine)


def test_ros_bag_predictions_hang_off_the_bags_own_tree(tmp_path: Path) -> None:
    bag = BUNDLED / "rosbags" / "datmo" / "intersection.bag"
    ingest([bag], IngestOptions(out=tmp_path / "ds", workers=1))
    predict_dataset(tmp_path / "ds", tmp_path / "out", predictor="kalman")
    ds = Dataset.open(tmp_path / "ds")
    written = next((tmp_path / "out" / "mcap").glob("*/intersection.mcap"))
    assert check_prediction_mcap(written, ds, "intersection", "map", raster=False, root=None) == 2
    assert open_mcap(written).parents  # the frames used reach the root through the bag's own /tf


def test_mcap_input_predictions_hang_off_the_originals_tree(shared: Path, tmp_path: Path) -> None:
    original = shared / "mcap" / "evo" / "nav2_turtlebot.mcap"
    ingest([original], IngestOptions(out=tmp_path / "ds", workers=1))
    predict_dataset(tmp_path / "ds", tmp_path / "out", predictor="cv", inputs=[original])
    ds = Dataset.open(tmp_path / "ds")
    log = ds.logs().to_pylist()[0]
    frame = json.loads(log["attributes"] or "{}").get("world_frame") or WORLD_FRAME
    written = next((tmp_path / "out" / "mcap").glob(f"*/{log['log_id']}.mcap"))
    assert check_prediction_mcap(written, ds, log["log_id"], frame, raster=False, root=None) > 0
    assert frame in open_mcap(written).parents.values()  # the original's /tf reaches it


# ---------------------------------------------------------------------------------------------------------
# The builders against messages made field by field with Foxglove's classes.


def _turn(yaw: float) -> Quaternion:
    """The rotation by ``yaw`` about z as drawn (components snapped)."""
    half = np.array([math.sin(yaw / 2), math.cos(yaw / 2)])
    z, w = fx.snap(half, fx.ROTATION_QUANTUM).tolist()
    return Quaternion(z=z, w=w)


def _reference_update(rows: list[dict[str, Any]], deleted: list[str], t: int) -> SceneUpdate:
    stamp = fx.timestamp(t)
    update = SceneUpdate(deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletion.MATCHING_ID, id=i)
                                    for i in deleted])
    for r in rows:
        length, width, height = fx.AGENT_SHAPES[r["type"]]
        rgb = fx.TYPE_COLOURS[r["type"]]
        turn = _turn(r["yaw"]) if r["yaw"] is not None else Quaternion(w=1.0)
        entity = SceneEntity(timestamp=stamp, frame_id="world", id=r["id"], metadata=[
            KeyValuePair(key="track_id", value=r["id"]), KeyValuePair(key="object_type", value=r["type"]),
            KeyValuePair(key="role", value=r["role"])])
        entity.cubes.append(CubePrimitive(pose=Pose(position=Vector3(x=r["x"], y=r["y"], z=height / 2),
                                                    orientation=turn),
                                          size=Vector3(x=length, y=width, z=height),
                                          color=Color(r=rgb[0], g=rgb[1], b=rgb[2], a=0.85)))
        if r["yaw"] is not None:
            entity.arrows.append(ArrowPrimitive(
                pose=Pose(position=Vector3(x=r["x"], y=r["y"], z=height + 0.05), orientation=turn),
                shaft_length=max(0.55 * length, 0.4), shaft_diameter=max(0.12 * width, 0.06),
                head_length=max(0.3 * length, 0.25), head_diameter=max(0.35 * width, 0.18),
                color=Color(r=rgb[0], g=rgb[1], b=rgb[2], a=1.0)))
        update.entities.append(entity)
    return update


def test_agent_updates_equal_messages_built_field_by_field() -> None:
    # Three steps at 1 s, positions on the 1/1024 m grid drawn positions snap to: "car" drives east then stops
    # (keeps its heading), "ped" has a given heading and leaves after step 1, "box" stands still at the origin (no
    # heading: axis-aligned, no arrow).
    kinds = [("vehicle", "ego"), ("pedestrian", "other"), ("unknown", "focal")]
    rows = [  # step, track, kind, x, y, heading
        (0, 0, 0, 10.5, 3.25, math.nan), (0, 1, 1, -2.0, 7.5, 0.75), (0, 2, 2, 0.0, 0.0, math.nan),
        (1, 0, 0, 12.5, 3.25, math.nan), (1, 1, 1, -2.5, 7.75, 1.25), (1, 2, 2, 0.0, 0.0, math.nan),
        (2, 0, 0, 12.5, 3.25, math.nan), (2, 2, 2, 0.0, 0.0, math.nan),
    ]
    step, track, kind, x, y, heading = (np.array(c) for c in zip(*rows, strict=True))
    ts = 1_700_000_000_000_000_000 + step * 1_000_000_000
    yaw, ok = fx.display_headings(track, ts, x, y, heading)
    assert ok.tolist() == [True, True, False, True, True, False, True, False]
    assert yaw[[0, 3, 6]].tolist() == [0.0, 0.0, 0.0] and yaw[[1, 4]].tolist() == [0.75, 1.25]
    agents = fx.LogAgents(steps=step, ts=ts, x=x.astype(float), y=y.astype(float), yaw=yaw, has_heading=ok,
                          track=track, track_names=["car", "ped", "box"], kind=kind, kinds=kinds)
    got = fx.agent_scene_updates(agents, "world")
    assert len(got) == 3
    names = ["car", "ped", "box"]
    for s, data in enumerate(got):
        mine = [i for i in range(len(rows)) if step[i] == s]
        expected = _reference_update(
            [{"id": names[track[i]], "type": kinds[kind[i]][0], "role": kinds[kind[i]][1], "x": float(x[i]),
              "y": float(y[i]), "yaw": float(yaw[i]) if ok[i] else None} for i in mine],
            ["ped"] if s == 2 else [], int(ts[mine[0]]))
        assert SceneUpdate.FromString(data) == expected
    # Where no double is exactly zero the bytes are the classes' own serialization.
    nonzero = fx.LogAgents(steps=step[:2], ts=ts[:2], x=x[:2] + 0.5, y=y[:2], yaw=np.array([0.5, 0.75]),
                           has_heading=np.array([True, True]), track=track[:2], track_names=names, kind=kind[:2],
                           kinds=kinds)
    data = fx.agent_scene_updates(nonzero, "world")[0]
    assert SceneUpdate.FromString(data).SerializeToString() == data


def test_poses_and_transforms_equal_messages_built_field_by_field() -> None:
    ts = np.array([5, 1_000_000_007], np.int64)
    x, y, yaw = np.array([1.5, -2.0]), np.array([3.0, 4.25]), np.array([0.3, math.nan])
    poses = fx.poses_in_frame("world", ts, x, y, yaw)
    tfs = fx.frame_transforms("world", "ego", ts, x, y, yaw)
    for i in range(2):
        turn = _turn(float(yaw[i])) if i == 0 else Quaternion(w=1.0)
        pose = fx.MESSAGE_CLASSES["foxglove.PoseInFrame"](
            timestamp=fx.timestamp(int(ts[i])), frame_id="world",
            pose=Pose(position=Vector3(x=float(x[i]), y=float(y[i])), orientation=turn))
        tf = fx.MESSAGE_CLASSES["foxglove.FrameTransform"](
            timestamp=fx.timestamp(int(ts[i])), parent_frame_id="world", child_frame_id="ego",
            translation=Vector3(x=float(x[i]), y=float(y[i])), rotation=turn)
        assert poses[i] == pose.SerializeToString() and tfs[i] == tf.SerializeToString()


def test_display_headings_keep_the_last_direction_and_ignore_jitter() -> None:
    # 10 Hz: moving north at 5 m/s, then stopped with 1 cm jitter; a second track only jitters.
    n = 6
    ts = np.arange(n, dtype=np.int64) * 100_000_000
    x = np.array([0.0, 0.0, 0.0, 0.01, 0.0, 0.01])
    y = np.array([0.0, 0.5, 1.0, 1.0, 1.01, 1.0])
    yaw, ok = fx.display_headings(np.zeros(n, np.int64), ts, x, y, np.full(n, np.nan))
    assert ok.all() and np.allclose(yaw, math.pi / 2)
    _, still = fx.display_headings(np.zeros(3, np.int64), ts[:3], x[3:], y[3:], np.full(3, np.nan))
    assert not still.any()


def test_forecast_update_draws_history_truth_marker_and_modes() -> None:
    sample = make_scene(np.random.default_rng(1), 4, obs_len=8, pred_len=12)
    sample.positions = fx.snap(sample.positions, fx.POSITION_QUANTUM)  # on the drawn grid: points compare exactly
    sample.positions[1, 15:] = np.nan  # target 1 leaves the window early; target 2 is never seen after now
    sample.positions[2, 8:] = np.nan
    targets = np.array([0, 1, 2])
    futures = np.cumsum(np.ones((3, 5, 12, 2)), axis=2)
    scores = np.array([[0.5, 0.2, 0.1, 0.1, 0.1]] * 3)
    forecasts = ff.TargetForecasts.of_sample(sample, targets, futures, scores)
    update = SceneUpdate.FromString(ff.forecast_scene_updates(forecasts, ["map"], [1_700_000_000_123_456_789],
                                                              [4_800_000_000])[0])
    assert [e.id for e in update.entities] == [sample.track_ids[i] for i in targets]
    for j, e in enumerate(update.entities):
        assert (e.frame_id, e.timestamp.seconds, e.timestamp.nanos) == ("map", 1_700_000_000, 123_456_789)
        assert e.lifetime.seconds == 4 and e.lifetime.nanos == 800_000_000
        current = tuple(sample.positions[targets[j], 7])
        assert (e.spheres[0].pose.position.x, e.spheres[0].pose.position.y) == current
        lines = {(ln.color.r, ln.color.g, ln.color.b, ln.color.a): [(p.x, p.y) for p in ln.points] for ln in e.lines}
        assert lines[ff.HISTORY_RGBA] == [tuple(p) for p in sample.positions[targets[j], :8]]
        future = sample.positions[targets[j], 8:]
        future = future[np.isfinite(future).all(axis=1)]
        assert lines.get(ff.TRUTH_RGBA) == ([current, *map(tuple, future)] if len(future) else None)
        modes = [ln for ln in e.lines if (ln.color.r, ln.color.g, ln.color.b) == ff.MODE_RGB]
        assert [ln.color.a for ln in modes] == [1.0, 0.55, 0.4, 0.4, 0.4]  # 0.25 + 0.75 x score / best
        assert [(p.x, p.y) for p in modes[0].points] == [current, *map(tuple, futures[j, 0])]


@pytest.mark.parametrize("heading", [None, 0.0, 0.7, -2.9, math.pi])
def test_raster_frame_puts_each_pixel_where_the_affine_says(heading: float | None) -> None:
    spec = RasterSpec(rotate=heading is not None)
    affines = [world_to_pixel(spec, 2661.4, 1145.2, heading), world_to_raster_affine(np.array([-30.0, 12.5]))]
    for affine in affines:
        tf = fx.MESSAGE_CLASSES["foxglove.FrameTransform"].FromString(
            fr.raster_transform("world", "raster", 7, affine))
        _assert_transform_matches_affine(tf, affine)


def _rotation(q: Any) -> np.ndarray:
    """3x3 matrix of a unit quaternion message."""
    w, x, y, z = q.w, q.x, q.y, q.z
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def test_grid_cells_lie_on_their_pixels_facing_up() -> None:
    spec = RasterSpec(rotate=True, size_px=8, extent_m=4.0)
    affine = world_to_pixel(spec, 2661.4, 1145.2, 0.7)
    rgb = np.zeros((8, 8, 3), np.uint8)
    tf = fx.MESSAGE_CLASSES["foxglove.FrameTransform"].FromString(fr.raster_transform("world", "r", 0, affine))
    grid = fx.MESSAGE_CLASSES["foxglove.Grid"].FromString(fr.raster_grid("r", 0, rgb, fr.raster_resolution(affine)))
    to_world = _rotation(tf.rotation) @ _rotation(grid.pose.orientation)
    assert np.isclose(to_world[2, 2], 1.0)  # the grid's +z, the side the 3D panel draws, is up
    rows, cols = np.mgrid[0:8, 0:8]
    cell = np.column_stack([(cols.ravel() + 0.5) * grid.cell_size.x, (rows.ravel() + 0.5) * grid.cell_size.y,
                            np.zeros(64)])
    origin = np.array([grid.pose.position.x, grid.pose.position.y, grid.pose.position.z])
    in_raster = cell @ _rotation(grid.pose.orientation).T + origin
    world = in_raster @ _rotation(tf.rotation).T + np.array([tf.translation.x, tf.translation.y, tf.translation.z])
    pixel = world[:, :2] @ affine[:, :2].T + affine[:, 2]
    # Grid row r' is stored bottom first: it holds image row 7 - r'.
    assert np.allclose(pixel, np.column_stack([cols.ravel(), 7 - rows.ravel()]), atol=1e-6)


def _assert_transform_matches_affine(tf: Any, affine: np.ndarray) -> None:
    """Pixel (u, v)'s centre, at ((u + 0.5) res, (v + 0.5) res, 0) in the raster frame, lands on the world point
    the affine maps to (u, v), just under the ground."""
    res = fr.raster_resolution(affine)
    rot = _rotation(tf.rotation)
    pixels = np.array([[0, 0], [223, 0], [0, 223], [111.0, 57.0]])
    local = np.column_stack([(pixels + 0.5) * res, np.zeros(len(pixels))])
    world = local @ rot.T + np.array([tf.translation.x, tf.translation.y, tf.translation.z])
    back = world[:, :2] @ np.asarray(affine)[:, :2].T + np.asarray(affine)[:, 2]
    assert np.allclose(back, pixels, atol=1e-6) and np.allclose(world[:, 2], world[0, 2]) and world[0, 2] < 0
    assert np.isclose(rot[2, 2], -1.0)  # z into the ground: the image's camera looks down


def test_raster_transform_refuses_an_affine_with_rows_growing_up() -> None:
    with pytest.raises(ValueError, match="rows"):
        fr.raster_transform("world", "raster", 0, np.array([[2.24, 0.0, 10.0], [0.0, 2.24, 5.0]]))


def test_raster_image_and_grid_hold_the_same_pixels() -> None:
    rgb = np.zeros((6, 4, 3), np.uint8)
    rgb[0, 0] = (255, 0, 0)
    rgb[5, 3] = (0, 9, 200)
    rgb[2, 1], rgb[3, 2] = (0, 0, 7), (0, 5, 0)  # one channel drawn is a drawn cell
    image = fx.MESSAGE_CLASSES["foxglove.CompressedImage"].FromString(fr.compressed_raster("r", 3, rgb))
    decoded = _png_rgb(image.data)
    assert image.format == "png" and np.array_equal(decoded, rgb)
    grid = fx.MESSAGE_CLASSES["foxglove.Grid"].FromString(fr.raster_grid("r", 3, rgb, 0.5))
    assert (grid.column_count, grid.row_stride, grid.cell_stride) == (4, 16, 4)
    assert [f.name for f in grid.fields] == ["red", "green", "blue", "alpha"]
    cells = np.frombuffer(grid.data, np.uint8).reshape(6, 4, 4)
    assert np.array_equal(cells[::-1, :, :3], rgb)
    assert cells[5, 0, 3] == 255 and cells[0, 0, 3] == 64  # drawn cells opaque, empty ones dim
    assert np.array_equal(cells[::-1, :, 3], np.where(rgb.any(axis=-1), 255, 64))
    assert (grid.pose.position.y, grid.pose.orientation.x, grid.cell_size.x) == (3.0, 1.0, 0.5)
    layers = fr.raster_rgb(np.stack([np.full((2, 2), 9, np.uint8)] * 3), ("drivable_area", "lane_up", "crossing"))
    assert layers.shape == (2, 2, 3) and (layers == 9).all()


def test_every_object_type_has_a_shape_and_a_colour() -> None:
    assert set(fx.AGENT_SHAPES) == set(fx.TYPE_COLOURS) == set(OBJECT_TYPES)
