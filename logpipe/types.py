"""Core types shared by every stage: vocabularies, array aliases and the records passed between layers.

Frames and units, once for the whole package:

* **world frame** — the log's own 2-D metric frame (AV1/AV2 city frame, the ETH/UCY scene plane, a ROS
  ``map``/``odom`` frame). ``x``/``y`` are metres, ``heading`` is radians counter-clockwise from +x.
* **time** — ``timestamp_ns`` is int64 nanoseconds on the log's own clock (AV1: the CSV seconds converted
  exactly; ETH/UCY and ApolloScape: frame number x frame period, since they carry no clock).
* **step** — index of a timestamp among the log's distinct timestamps (0-based). Prediction windows are
  counted in steps, as Social-GAN and the Argoverse protocol do, and keep the true times beside them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, TypeAlias

import numpy as np
import numpy.typing as npt

NDArrayFloat: TypeAlias = npt.NDArray[np.float64]
NDArrayFloat32: TypeAlias = npt.NDArray[np.float32]
NDArrayInt: TypeAlias = npt.NDArray[np.int64]
NDArrayInt32: TypeAlias = npt.NDArray[np.int32]
NDArrayBool: TypeAlias = npt.NDArray[np.bool_]
NDArrayByte: TypeAlias = npt.NDArray[np.uint8]


class ObjectType(StrEnum):
    """Normalised agent class; every adapter maps its own labels onto these (raw label kept in ``source_type``)."""

    VEHICLE = "vehicle"
    PEDESTRIAN = "pedestrian"
    CYCLIST = "cyclist"
    MOTORCYCLIST = "motorcyclist"
    BUS_TRUCK = "bus_truck"
    UNKNOWN = "unknown"


OBJECT_TYPES: tuple[str, ...] = tuple(t.value for t in ObjectType)
"""The vocabulary in a fixed order; ``OBJECT_TYPES.index(t)`` is the integer code used by the model."""


class Role(StrEnum):
    """Why a track is in the log: the recording vehicle, the agent the log was chosen for, or anyone else."""

    EGO = "ego"
    FOCAL = "focal"
    OTHER = "other"


@dataclass(frozen=True)
class SourceFile:
    """One input file (or bag folder) found by an adapter.

    Attributes:
        path: where it is on disk.
        relpath: path relative to the ingest root it was found under (POSIX separators); names it in errors.
        sha256: hex digest of its bytes (for a folder: of its files' digests in name order); ``PENDING_SHA256``
            until the batch that reads the file computes it (ingest leaves it so for inputs it knows unique).
        size: bytes.
        memberships: ``"<scene>/<split>"`` labels read from the folder layout (ETH/UCY), possibly empty.
    """

    path: str
    relpath: str
    sha256: str
    size: int
    memberships: tuple[str, ...] = ()


PENDING_SHA256 = ""
"""``SourceFile.sha256`` of an input whose digest is computed by the batch that reads it."""


@dataclass
class LogMeta:
    """Per-log metadata, one row of ``logs.parquet``.

    Attributes:
        log_id: unique id of the log within a dataset.
        source_format: adapter name (``argoverse1``, ``ethucy``, ``apolloscape``, ...).
        source_file: ``relpath`` of the input the log came from.
        source_sha256: sha256 of that input.
        map_id: city or map name (``MIA``, ``PIT``, ``austin``) or None when the format has no map.
        frame_rate_hz: nominal sampling rate in Hz (10 for Argoverse, 2.5 for ETH/UCY, 2 for ApolloScape).
        memberships: ``"<scene>/<split>"`` labels (see ``SourceFile``).
        attributes: format-specific extras, stored as JSON.
    """

    log_id: str
    source_format: str
    source_file: str
    source_sha256: str
    map_id: str | None
    frame_rate_hz: float
    memberships: tuple[str, ...] = ()
    attributes: dict[str, Any] = field(default_factory=dict)


TARGET_RULES: tuple[str, ...] = ("fully_observed", "focal", "fully_observed_no_ego")
"""Values of ``SampleProtocol.targets``."""

WINDOWS: tuple[str, ...] = ("sliding", "first")
"""Values of ``SampleProtocol.window``."""


@dataclass(frozen=True)
class SampleProtocol:
    """Declarative description of prediction samples cut from continuous logs.

    Attributes:
        name: preset name or ``custom``.
        obs_len: observed steps, including the current one (t = 1..T_obs in the paper).
        pred_len: predicted steps after the current one.
        stride: steps between consecutive window starts (``window="sliding"``).
        window: ``sliding`` (every ``stride`` steps, Social-GAN) or ``first`` (one window at step 0, Argoverse).
        targets: ``fully_observed`` (every agent present at all obs+pred steps), ``focal`` (the focal track) or
            ``fully_observed_no_ego`` (every fully observed agent but the ego: on Argoverse the AV's future is the
            model's planned-trajectory input, ETF, so it cannot also be a target).
        min_targets: keep a window only with at least this many targets (Social-GAN's loader keeps >= 2).
        target_types: when not empty, only agents of these ``ObjectType`` values are targets (AV2 logs label
            pedestrians, buses, ...; AV1 labels only the AV and AGENT as vehicles, its OTHERS are ``unknown``).
            Written to the manifest only when set, so the presets' manifests are unchanged.
    """

    name: str
    obs_len: int
    pred_len: int
    stride: int = 1
    window: str = "sliding"
    targets: str = "fully_observed"
    min_targets: int = 1
    target_types: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        # A manifest read back gives a JSON list; keep the dataclass hashable.
        object.__setattr__(self, "target_types", tuple(self.target_types))

    @property
    def seq_len(self) -> int:
        """Steps in one window (observed + predicted)."""
        return self.obs_len + self.pred_len

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for the manifest."""
        return {
            "name": self.name,
            "obs_len": self.obs_len,
            "pred_len": self.pred_len,
            "stride": self.stride,
            "window": self.window,
            "targets": self.targets,
            "min_targets": self.min_targets,
        } | ({"target_types": list(self.target_types)} if self.target_types else {})


PROTOCOLS: dict[str, SampleProtocol] = {
    # Zhu et al. / Social-GAN: 8 observed + 12 predicted at 2.5 Hz, sliding windows, all fully observed peds.
    "ethucy": SampleProtocol("ethucy", obs_len=8, pred_len=12, stride=1, window="sliding"),
    # ApolloScape trajectory challenge: 6 + 6 at 2 Hz.
    "apolloscape": SampleProtocol("apolloscape", obs_len=6, pred_len=6, stride=1, window="sliding"),
    # Argoverse 1: one sample per CSV, 20 observed + 30 predicted at 10 Hz, the AGENT is the target.
    "argoverse": SampleProtocol("argoverse", obs_len=20, pred_len=30, window="first", targets="focal"),
    # Argoverse 2: 50 observed + 60 predicted at 10 Hz, the focal track is the target.
    "argoverse2": SampleProtocol("argoverse2", obs_len=50, pred_len=60, window="first", targets="focal"),
    # Robot logs resampled to 10 Hz: 2 s observed + 3 s predicted (the Argoverse horizon), a window every second.
    "rosbag": SampleProtocol("rosbag", obs_len=20, pred_len=30, stride=10, window="sliding"),
    # CommonRoad scenarios (NGSIM and drone recordings) at 10 Hz: the Argoverse horizon, a window every second,
    # every agent observed over the whole window a target (the scenarios have no ego and no focal agent).
    "commonroad": SampleProtocol("commonroad", obs_len=20, pred_len=30, stride=10, window="sliding"),
}


@dataclass
class SceneSample:
    """One prediction sample as the model sees it (built from the track table and the sample index).

    Attributes:
        sample_id: ``"<log_id>:<start_step>"``.
        positions: (A, T_obs + T_pred, 2) world-frame metres; NaN where an agent is not observed.
        timestamps_ns: (T_obs + T_pred,) true times of the window's steps.
        track_ids: (A,) track ids, in the order of ``positions``.
        object_types: (A,) integer codes into ``OBJECT_TYPES``.
        target_mask: (A,) True for agents to predict (the protocol's targets).
        ego_index: row of the ego in ``positions``, or -1 when the log has no ego.
        obs_len: T_obs; ``positions[:, obs_len - 1]`` is the current step.
        raster: (C, H, W) uint8 map image centred on the ego/focal agent at the current step, or None.
        world_to_raster: (2, 3) affine mapping world metres to raster pixels, or None.
    """

    sample_id: str
    positions: NDArrayFloat
    timestamps_ns: NDArrayInt
    track_ids: list[str]
    object_types: NDArrayInt
    target_mask: NDArrayBool
    ego_index: int
    obs_len: int
    raster: NDArrayByte | None = None
    world_to_raster: NDArrayFloat | None = None

    @property
    def log_id(self) -> str:
        """The log the sample was cut from."""
        return self.sample_id.rsplit(":", 1)[0]
