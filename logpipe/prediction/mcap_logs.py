"""A prediction run's per-log MCAP: the original recording plus the prediction channels, one message of each
per sample at its prediction time (the Foxglove messages are built by ``logpipe.mcap.foxglove``).

Channels::

    /logpipe/predictions        logpipe.Predictions (JSON, schemas/logpipe.Predictions.json)
    /logpipe/predictions/scene  foxglove.SceneUpdate: history, truth, modes
    /logpipe/raster/tf          foxglove.FrameTransform placing frame logpipe_raster      } with raster
    /logpipe/raster             foxglove.CompressedImage (PNG) in frame logpipe_raster    } images only
    /logpipe/raster/grid        foxglove.Grid in frame logpipe_raster                     }
    /logpipe/legend             foxglove.SceneUpdate: once, texts naming the scene's colours
    /logpipe/scene              foxglove.SceneUpdate: the agents' boxes per step, for ROS bags and MCAPs
                                (other logs' originals, ingest's MCAPs, have this channel already)

Positions are metres in the log's world frame (``prediction.originals.world_frame``); times are ns on the log's clock.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from logpipe import __version__
from logpipe.dataset.reader import Dataset
from logpipe.dataset.sample_filter import SelectedLogs
from logpipe.errors import DatasetError
from logpipe.mcap import foxglove as fx
from logpipe.mcap import raster_image as fr
from logpipe.mcap.agent_scene import AGENTS_SCENE_TOPIC, agent_scene_messages
from logpipe.mcap.forecast_scene import TargetForecasts, forecast_scene_updates, legend_scene
from logpipe.mcap.merge import NewChannel, NewMessage, Source, write_merged
from logpipe.mcap.tracks import json_schema_bytes
from logpipe.prediction.originals import ORIGINAL_FORMATS, find_original, world_frame
from logpipe.prediction.output import SamplePrediction
from logpipe.storage.artifact import unsafe_file_name
from logpipe.types import NDArrayInt, SampleProtocol

try:  # orjson encodes numpy arrays ~30x faster than json; the output is the same compact JSON
    import orjson

    def dumps(obj: Any) -> bytes:
        """Compact JSON (numpy arrays as nested lists)."""
        return orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY)

    def array_json(values: np.ndarray) -> Any:
        """``values`` as ``dumps`` takes it. An (N, K, T) array whose K modes are one mode broadcast (stride 0:
        constant velocity's identical modes) becomes the JSON text orjson writes for the whole array, but with
        each target's one mode formatted once and its text repeated K times (float formatting is most of the
        ``logpipe.Predictions`` channel's cost; the bytes are the same)."""
        if values.ndim != 3 or values.shape[1] < 2 or values.strides[1] != 0:
            return values
        if not len(values):
            return orjson.Fragment(b"[]")
        modes = values.shape[1]
        one = orjson.dumps(np.ascontiguousarray(values[:, 0]), option=orjson.OPT_SERIALIZE_NUMPY)
        targets = [b"[" + b",".join([b"[" + row + b"]"] * modes) + b"]" for row in one[2:-2].split(b"],[")]
        return orjson.Fragment(b"[" + b",".join(targets) + b"]")

except ImportError:  # pragma: no cover - orjson is a dependency; keep working without it

    def dumps(obj: Any) -> bytes:
        """Compact JSON (numpy arrays as nested lists)."""
        return json.dumps(obj, separators=(",", ":"), default=lambda a: a.tolist()).encode()

    def array_json(values: np.ndarray) -> Any:
        """``values`` as ``dumps`` takes it."""
        return values


PREDICTIONS_TOPIC = "/logpipe/predictions"
SCENE_TOPIC = "/logpipe/predictions/scene"
RASTER_TOPIC = "/logpipe/raster"
RASTER_GRID_TOPIC = "/logpipe/raster/grid"
RASTER_TF_TOPIC = "/logpipe/raster/tf"
RASTER_FRAME = "logpipe_raster"
LEGEND_TOPIC = "/logpipe/legend"


def check_log_ids(root: Path, log_ids: Iterable[str]) -> None:
    """Refuse, before any output, a log (of the dataset at ``root``) whose id cannot be a file name: MCAPs are
    named after log ids, and an id like ``../../x`` would put one outside the output folder.

    Raises:
        DatasetError: naming the first such id.
    """
    for log_id in log_ids:
        reason = unsafe_file_name(log_id)
        if reason:
            raise DatasetError(f"{root}: log id {log_id[:80]!r} {reason}; log ids become file names, so "
                               "predict refuses it (damaged or hand-made dataset? re-ingest it)")


def new_channels(with_raster: bool, frame: str) -> list[NewChannel]:
    """Appended channels, indexed by ``NewMessage.channel``: predictions, scene and, with rasters, the raster
    frame's transform, the PNG and the grid the 3D panel draws."""
    channels = [
        NewChannel(PREDICTIONS_TOPIC, "logpipe.Predictions", "jsonschema", json_schema_bytes("logpipe.Predictions"),
                   metadata={"frame_id": frame}),
        fx.new_channel(SCENE_TOPIC, "foxglove.SceneUpdate", frame),
    ]
    if with_raster:
        channels += [fx.new_channel(RASTER_TF_TOPIC, "foxglove.FrameTransform", frame),
                     fx.new_channel(RASTER_TOPIC, "foxglove.CompressedImage", RASTER_FRAME),
                     fx.new_channel(RASTER_GRID_TOPIC, "foxglove.Grid", RASTER_FRAME)]
    return channels


def extra_channels(frame: str, agents: bool) -> list[NewChannel]:
    """Channels after ``new_channels``: the legend and, for a log whose original has no logpipe scene, its
    agents."""
    channels = [fx.new_channel(LEGEND_TOPIC, "foxglove.SceneUpdate", frame)]
    if agents:
        channels.append(fx.new_channel(AGENTS_SCENE_TOPIC, "foxglove.SceneUpdate", frame))
    return channels


@dataclass(frozen=True)
class PredictionMcaps:
    """What every log MCAP of a run shares; ``write`` is a ``prediction.output.LogMcapWriter``.

    Attributes:
        protocol: the dataset's sample protocol; ``predictor``, ``checkpoint_id``, ``modes``, ``seed``: the run's.
        raster_channels: the raster layers, when raster images are added (None: no raster channels).
        frames: the world frame of each log's positions (``originals.world_frame``); ``dt_ns``: its median step
            (ns); ``originals``: its original recording.
        dataset_root: the dataset; ``agent_logs``: the logs whose original (a ROS bag or MCAP) has no logpipe
            scene, whose agents are drawn from the dataset's tracks.
    """

    protocol: SampleProtocol
    predictor: str
    checkpoint_id: str
    modes: int
    seed: int
    raster_channels: tuple[str, ...] | None
    frames: dict[str, str]
    dt_ns: dict[str, int]
    originals: dict[str, Source]
    dataset_root: Path | None = None
    agent_logs: frozenset[str] = frozenset()

    @classmethod
    def of_run(cls, dataset: Dataset, logs: SelectedLogs, inputs: Sequence[Path], predictor: str,
               checkpoint_id: str, modes: int, seed: int, raster_channels: tuple[str, ...] | None) -> PredictionMcaps:
        """The writer of a run over ``logs`` of ``dataset``, their originals found under ``inputs``
        (``originals.find_original``).

        Raises:
            DatasetError: an original is missing or has other contents.
        """
        frames, dt_ns, originals, agent_logs = {}, {}, {}, set()
        for row in logs.rows():
            log_id = str(row["log_id"])
            frames[log_id], dt_ns[log_id] = world_frame(row), int(row["median_dt_ns"])
            originals[log_id] = find_original(row, inputs, dataset)
            if row["source_format"] in ORIGINAL_FORMATS:
                agent_logs.add(log_id)
        return cls(dataset.protocol, predictor, checkpoint_id, modes, seed, raster_channels, frames, dt_ns, originals,
                   dataset.root, frozenset(agent_logs))

    def of_logs(self, log_ids: Iterable[str]) -> PredictionMcaps:
        """This writer for ``log_ids`` only (what a shard job carries)."""
        chosen = list(log_ids)
        return replace(self, frames={i: self.frames[i] for i in chosen}, dt_ns={i: self.dt_ns[i] for i in chosen},
                       originals={i: self.originals[i] for i in chosen})

    def write(self, log_id: str, predictions: Iterator[SamplePrediction], target: Path) -> int:
        """Original log + the prediction channels, one message per sample at its prediction time; returns the
        number of original messages copied."""
        layers = self.raster_channels

        def messages() -> Iterator[NewMessage]:
            for p in predictions:
                now = int(p.row["current_ns"])
                forecasts = TargetForecasts.of_sample(p.sample, p.targets, p.futures, p.scores)
                yield from self.sample_messages(log_id, now, p.step_ns, forecasts,
                                                self.scene_updates([log_id], [now], forecasts)[0])
                affine = p.sample.world_to_raster
                if layers is not None and p.sample.raster is not None and affine is not None:
                    rgb = fr.raster_rgb(np.asarray(p.sample.raster), layers)
                    yield NewMessage(2, now, now, fr.raster_transform(self.frame(log_id), RASTER_FRAME, now, affine))
                    yield NewMessage(3, now, now, fr.compressed_raster(RASTER_FRAME, now, rgb))
                    yield NewMessage(4, now, now, fr.raster_grid(RASTER_FRAME, now, rgb,
                                                                 fr.raster_resolution(affine)))

        return self.write_messages(log_id, messages(), target)

    def write_messages(self, log_id: str, messages: Iterable[NewMessage], target: Path) -> int:
        """Original log + ``messages`` on the prediction channels (``new_channels``); returns the number of
        original messages copied."""
        frame, with_raster = self.frame(log_id), self.raster_channels is not None
        agents = log_id in self.agent_logs and self.dataset_root is not None
        stats = write_merged(
            target, [self.originals[log_id]], new_channels(with_raster, frame) + extra_channels(frame, agents),
            self._with_extras(log_id, messages, 5 if with_raster else 2, agents),
            metadata={"logpipe.predictions": {"log_id": log_id, "frame_id": self.frame(log_id),
                                              "predictor": self.predictor, "checkpoint_id": self.checkpoint_id,
                                              "num_modes": str(self.modes), "seed": str(self.seed),
                                              "logpipe_version": __version__}},
        )
        return stats.messages

    def _with_extras(self, log_id: str, messages: Iterable[NewMessage], legend: int,
                     agents: bool) -> Iterator[NewMessage]:
        """``messages``, then the legend (channel ``legend``) above the first target's current position, and with
        ``agents`` the log's agent boxes (channel ``legend + 1``) from the dataset's tracks."""
        first: NewMessage | None = None
        for m in messages:
            if first is None and m.channel == 0:
                first = m
            yield m
        if first is not None:
            record = json.loads(first.data)
            at = (record["current_x"][0], record["current_y"][0]) if record["current_x"] else (0.0, 0.0)
            yield NewMessage(legend, first.log_time, first.log_time, legend_scene(self.frame(log_id),
                                                                                  first.log_time, at))
        if agents and self.dataset_root is not None:
            tracks = Dataset.open(self.dataset_root).log_tracks(log_id)
            for t, scene in agent_scene_messages(tracks, self.frame(log_id)):
                yield NewMessage(legend + 1, t, t, scene)

    def frame(self, log_id: str) -> str:
        """The world frame of a log's positions."""
        return self.frames[log_id]

    def scene_updates(self, log_ids: Sequence[str], now_ns: Sequence[int], forecasts: TargetForecasts) -> list[bytes]:
        """The scene message of each sample of ``forecasts`` (of ``log_ids`` at ``now_ns``, one each per sample)."""
        pred_len = self.protocol.pred_len
        return forecast_scene_updates(forecasts, [self.frame(i) for i in log_ids], now_ns,
                                      [self.dt_ns[i] * pred_len for i in log_ids])

    def sample_messages(self, log_id: str, now_ns: int, step_ns: NDArrayInt, forecasts: TargetForecasts,
                        scene: bytes) -> tuple[NewMessage, NewMessage]:
        """A sample's predictions and scene messages at its prediction time ``now_ns``: ``forecasts`` of the one
        sample, ``step_ns``: (T_pred,) the times of its future steps, ``scene``: its ``scene_updates`` message."""
        record = self._predictions_json(log_id, self.frame(log_id), now_ns, step_ns, forecasts)
        return NewMessage(0, now_ns, now_ns, record), NewMessage(1, now_ns, now_ns, scene)

    def _predictions_json(self, log_id: str, frame: str, now_ns: int, step_ns: NDArrayInt,
                          f: TargetForecasts) -> bytes:
        columns = f.arrays()
        message = {
            "log_id": log_id,
            "sample_id": f.sample_ids[0],
            "timestamp_ns": now_ns,
            "frame_id": frame,
            "predictor": self.predictor,
            "checkpoint_id": self.checkpoint_id,
            "obs_len": self.protocol.obs_len,
            "pred_len": self.protocol.pred_len,
            "num_modes": self.modes,
            "step_timestamps_ns": step_ns.tolist(),
            "track_id": list(f.track_ids),
            "object_type": list(f.object_types),
            "current_x": columns["current_x"],
            "current_y": columns["current_y"],
            "score": columns["score"],
            "x": array_json(columns["x"]),
            "y": array_json(columns["y"]),
        }
        return dumps(message)
