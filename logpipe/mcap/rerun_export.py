"""logpipe's MCAPs as Rerun recordings (``.rrd``, written with ``rerun-sdk``): ``logpipe export --format rrd``.

Rerun's own MCAP importer maps transforms, poses and images but not ``foxglove.SceneUpdate`` or ``foxglove.Grid``,
so agents, forecasts and lanes would stay opaque there. This module reads those messages and logs what they draw
as Rerun archetypes on the ``log_clock`` timeline: the MCAP's log times, i.e. the log's own clock at its sensor rate
(Rerun owns ``log_time`` and stamps it with the wall clock of the export, so that name would lose them; Rerun's own
``log_time``/``log_tick`` are switched off). Every position is in the log's world frame:

==========================  ==========================================================================
entity                      from
==========================  ==========================================================================
``/legend``                 a ``TextDocument``: what each colour means
``/agents``                 ``/logpipe/scene`` cubes: ``Boxes3D``, one batch per step; labels are short (ids up to
                            10 characters as they are, longer ones by their last 6), the full
                            ``track_id`` rides along as a component
``/forecasts/history``      ``/logpipe/predictions/scene`` lines in the history colour: ``LineStrips3D``
``/forecasts/truth``        ... in the truth colour (the true future)
``/forecasts/modes``        ... in the modes' colour (the K forecasts)
``/forecasts/current``      its spheres (each target's current position): ``Points3D``
``/lines``                  any other scene line (e.g. lanes an ingest MCAP draws): ``LineStrips3D``
``/lanes``                  ``/logpipe/raster/grid`` cells with a lane or boundary drawn: ``Points3D``
``/raster``                 ``/logpipe/raster``: the raster PNG, ``EncodedImage``
==========================  ==========================================================================

A default blueprint opens the 3D view with the raster and the legend beside it, on the ``log_clock``
timeline. Other channels (a ROS bag's own) are left out: the prediction MCAP of a ROS log carries its agents on
``/logpipe/scene`` too (``logpipe.prediction.mcap_logs``).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader

from logpipe.errors import DatasetError
from logpipe.mcap.forecast_scene import HISTORY_RGBA, MODE_RGB, TRUTH_RGBA
from logpipe.storage.io import atomic_path
from logpipe.summaries import ExportedFile, ExportSummary

LEGEND = (
    "# logpipe scene\n\n"
    "* **agents**: boxes coloured by object type, labelled with the end of their track id\n"
    "* **history**: grey line, the observed past of each forecast target\n"
    "* **truth**: orange line, the true future\n"
    "* **forecasts**: blue lines, the K modes (more opaque = higher score)\n"
    "* **current**: a sphere at each target's position when forecast\n"
    "* **lanes**: green lines (lane centrelines), blue lines (boundaries, crossings) traced from the raster\n"
)
TIMELINE = "log_clock"
"""The recording's timeline: the log's own times (``log_time`` is Rerun's own, stamped at export)."""
SHORT_LABEL = 10
"""Agent ids up to this many characters label their box as they are; longer ones (AV1's 36-character UUIDs) by
their end."""


def _u8(rgba: tuple[float, ...]) -> tuple[int, int, int, int]:
    r, g, b, a = (*rgba, 1.0)[:4]
    return round(255 * r), round(255 * g), round(255 * b), round(255 * a)


@dataclass
class Drawn:
    """How many of each kind of thing a recording draws (what ``export`` reports and its test counts)."""

    counts: Counter[str] = field(default_factory=Counter)

    def add(self, kind: str, n: int) -> None:
        if n:
            self.counts[kind] += n


def _rotate(q: Any, v: np.ndarray) -> np.ndarray:
    """Points ``v`` (N, 3) turned by the unit quaternion ``q`` (x, y, z, w attributes)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    if (x, y, z, w) == (0.0, 0.0, 0.0, 0.0):  # an unset orientation is the identity
        return v
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    out: np.ndarray = v @ r.T
    return out


def _vec(v: Any) -> np.ndarray:
    """A Vector3 message as a (3,) array."""
    return np.array([v.x, v.y, v.z], np.float64)


def _line_kind(colour: tuple[int, int, int, int]) -> str:
    """Which forecast line a scene line is, by its colour (``forecast_scene``'s constants)."""
    if colour[:3] == _u8(HISTORY_RGBA)[:3]:
        return "forecasts/history"
    if colour[:3] == _u8(TRUTH_RGBA)[:3]:
        return "forecasts/truth"
    if colour[:3] == _u8((*MODE_RGB, 1.0))[:3]:
        return "forecasts/modes"
    return "lines"


class _Recorder:
    """One log's recording: turns MCAP messages into Rerun archetypes on a ``rerun.RecordingStream``."""

    def __init__(self, rec: Any) -> None:
        import rerun as rr

        self.rr = rr
        self.rec = rec
        self.drawn = Drawn()
        self.raster_tf: dict[str, FrameTransform] = {}  # child frame -> its latest transform
        self.labels: dict[str, str] = {}  # track id -> its short label
        self.first_ns: int | None = None

    def at(self, log_time_ns: int) -> None:
        if self.first_ns is None:  # the recording starts when the log does, not at the export
            self.first_ns = log_time_ns
            self.rec.send_recording_start_time_nanos(log_time_ns)
        self.rec.set_time(TIMELINE, timestamp=np.datetime64(log_time_ns, "ns"))

    def label(self, track_id: str) -> str:
        """A short label for ``track_id``, unique in this recording: the id itself when short, else its last
        6 characters (more when another id of the recording already ends so)."""
        short = self.labels.get(track_id)
        if short is not None:
            return short
        taken = set(self.labels.values())
        n = 6
        short = track_id if len(track_id) <= SHORT_LABEL else track_id[-n:]
        while short in taken and n < len(track_id):
            n += 1
            short = track_id[-n:]
        self.labels[track_id] = short
        return short

    def scene(self, msg: SceneUpdate) -> None:
        """A scene update: cubes → agent boxes, lines by colour, spheres → current positions."""
        rr = self.rr
        centres, sizes, quats, box_colours, labels = [], [], [], [], []
        lines: dict[str, tuple[list[np.ndarray], list[tuple[int, int, int, int]]]] = {}
        points, point_colours = [], []
        for entity in msg.entities:
            for cube in entity.cubes:
                p, o = cube.pose.position, cube.pose.orientation
                centres.append((p.x, p.y, p.z))
                sizes.append((cube.size.x, cube.size.y, cube.size.z))
                quats.append((o.x, o.y, o.z, o.w) if (o.x, o.y, o.z, o.w) != (0, 0, 0, 0) else (0, 0, 0, 1))
                box_colours.append(_u8((cube.color.r, cube.color.g, cube.color.b, cube.color.a)))
                labels.append(entity.id)
            for line in entity.lines:
                pts = np.array([(q.x, q.y, q.z) for q in line.points], np.float64).reshape(-1, 3)
                pts = _rotate(line.pose.orientation, pts) + _vec(line.pose.position)
                colour = _u8((line.color.r, line.color.g, line.color.b, line.color.a))
                strips, colours = lines.setdefault(_line_kind(colour), ([], []))
                strips.append(pts)
                colours.append(colour)
            for sphere in entity.spheres:
                p = sphere.pose.position
                points.append((p.x, p.y, p.z))
                point_colours.append(_u8((sphere.color.r, sphere.color.g, sphere.color.b, sphere.color.a)))
        if centres:
            self.rec.log("agents", rr.Boxes3D(centers=centres, sizes=sizes, quaternions=quats, colors=box_colours,
                                              labels=[self.label(i) for i in labels], fill_mode="solid"),
                         rr.AnyValues(track_id=labels))
            self.drawn.add("boxes", len(centres))
        for kind, (strips, colours) in lines.items():
            radius = 0.12 if kind == "forecasts/truth" else 0.06
            self.rec.log(kind, rr.LineStrips3D(strips, colors=colours, radii=radius))
            self.drawn.add(kind.rsplit("/", 1)[-1], len(strips))
        if points:
            self.rec.log("forecasts/current", rr.Points3D(points, colors=point_colours, radii=0.4))
            self.drawn.add("current", len(points))

    def transform(self, msg: FrameTransform) -> None:
        self.raster_tf[msg.child_frame_id] = msg

    def image(self, msg: CompressedImage) -> None:
        self.rec.log("raster", self.rr.EncodedImage(contents=msg.data, media_type=f"image/{msg.format or 'png'}"))
        self.drawn.add("images", 1)

    def grid(self, msg: Grid) -> None:
        """The raster grid's lane cells (green) and boundary cells (blue) traced into line strips in the world
        frame (through the grid's pose and the transform that places its frame)."""
        names = [f.name for f in msg.fields]
        if not {"red", "green", "blue"} <= set(names) or not msg.column_count:
            return
        cells = np.frombuffer(msg.data, np.uint8).reshape(-1, msg.column_count, msg.cell_stride)
        rgb = cells[..., [next(f.offset for f in msg.fields if f.name == c) for c in ("red", "green", "blue")]]
        strips, colours = [], []
        for channel, colour in ((1, LANE_RGBA), (2, BOUNDARY_RGBA)):
            for cols_rows in _outlines(rgb[..., channel] > 0):
                local = np.column_stack([(cols_rows + 0.5) * (msg.cell_size.x, msg.cell_size.y),
                                         np.zeros(len(cols_rows))])
                placed = _rotate(msg.pose.orientation, local) + _vec(msg.pose.position)
                tf = self.raster_tf.get(msg.frame_id)
                if tf is not None:
                    placed = _rotate(tf.rotation, placed) + _vec(tf.translation)
                strips.append(placed)
                colours.append(colour)
        if strips:
            self.rec.log("lanes", self.rr.LineStrips3D(strips, colors=colours, radii=0.25 * msg.cell_size.x))
            self.drawn.add("lane_strips", len(strips))


LANE_RGBA = (0, 200, 0, 255)
BOUNDARY_RGBA = (60, 120, 255, 255)


def _outlines(mask: np.ndarray) -> list[np.ndarray]:
    """The outlines of ``mask``'s cells as (N, 2) column/row polylines (closed, corners only): a lane a cell or
    two wide becomes one strip along it, where its cells would be hundreds of points."""
    import cv2  # here: only an export with rasters loads OpenCV

    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for contour in contours:
        pts = contour.reshape(-1, 2).astype(np.float64)
        if len(pts) > 1:  # a lone cell traces to one point, which a strip cannot draw
            out.append(np.vstack([pts, pts[:1]]))
    return out


_DECODERS: dict[str, tuple[type[Any], str]] = {
    "foxglove.SceneUpdate": (SceneUpdate, "scene"),
    "foxglove.FrameTransform": (FrameTransform, "transform"),
    "foxglove.CompressedImage": (CompressedImage, "image"),
    "foxglove.Grid": (Grid, "grid"),
}


def _messages(path: Path) -> Iterator[tuple[str, int, Any]]:
    """(handler name, log time, decoded message) of the Foxglove Protobuf messages of an MCAP, in log-time order."""
    with path.open("rb") as fh:
        for schema, _channel, message in make_reader(fh).iter_messages(log_time_order=True):
            if schema is None or schema.encoding != "protobuf" or schema.name not in _DECODERS:
                continue
            cls, handler = _DECODERS[schema.name]
            yield handler, message.log_time, cls.FromString(message.data)


def mcap_to_rrd(mcap_path: Path, target: Path, recording_id: str) -> dict[str, int]:
    """Write ``target`` (atomically): the Rerun recording of what ``mcap_path``'s Foxglove channels draw; returns
    the counts of what it draws (``boxes``, ``history``, ``truth``, ``modes``, ``current``, ``lines``,
    ``lane_strips``, ``images``)."""
    import rerun as rr

    rec = rr.RecordingStream("logpipe", recording_id=recording_id, send_properties=False)
    rec.set_log_time_enabled(False)  # Rerun's own log_time / log_tick: the export's wall clock, not the log's
    recorder = _Recorder(rec)
    with atomic_path(target) as tmp:
        rec.save(tmp, default_blueprint=blueprint())
        rec.log("legend", rr.TextDocument(LEGEND, media_type=rr.MediaType.MARKDOWN), static=True)
        try:
            for handler, log_time, msg in _messages(mcap_path):
                recorder.at(log_time)
                getattr(recorder, handler)(msg)
        except Exception as err:  # mcap raises many types for a damaged file
            raise DatasetError(f"{mcap_path}: cannot read it as an MCAP: {err}") from None
        finally:
            rec.flush()
            rec.disconnect()
    return dict(recorder.drawn.counts)


def blueprint() -> Any:
    """The layout a recording opens with: the 3D scene (without the raster image and the legend) beside the
    raster and the legend, the time panel on the log's own clock."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="scene", origin="/", contents=["+ /**", "- /raster", "- /legend"]),
            rrb.Vertical(rrb.Spatial2DView(name="raster", origin="/raster"),
                         rrb.TextDocumentView(name="legend", origin="/legend"), row_shares=[2, 1]),
            column_shares=[3, 1]),
        rrb.TimePanel(timeline=TIMELINE),
    )


def find_mcaps(paths: list[Path]) -> list[Path]:
    """The MCAP files of ``paths``: a file itself, or every ``*.mcap`` under a folder's ``mcap/`` (a dataset or
    prediction run), sorted.

    Raises:
        DatasetError: a path that does not exist or holds no MCAP.
    """
    found: list[Path] = []
    for path in paths:
        if path.is_file():
            found.append(path)
        elif path.is_dir():
            inside = sorted((path / "mcap").rglob("*.mcap")) or sorted(path.rglob("*.mcap"))
            if not inside:
                raise DatasetError(f"{path}: no MCAP files in it (ingested or predicted with --no-mcap?)")
            found += inside
        else:
            raise DatasetError(f"{path}: no such file or folder")
    return found


def rrd_name(mcap_path: Path) -> str:
    """``<log>.rrd`` for ``.../<log>.mcap`` (a log id is one safe file name)."""
    return mcap_path.stem + ".rrd"



def export_rrd(paths: list[Path], out: Path) -> ExportSummary:
    """``out/<log>.rrd`` for every MCAP of ``paths`` (``find_mcaps``), each written atomically.

    Raises:
        DatasetError: no MCAP found, two MCAPs of the same log name, or an unreadable MCAP.
    """
    import time

    started = time.perf_counter()
    mcaps = find_mcaps(paths)
    names = [rrd_name(m) for m in mcaps]
    clash = next((n for n in names if names.count(n) > 1), None)
    if clash is not None:
        raise DatasetError(f"two MCAPs would both be written as {out / clash}: export one folder at a time")
    out.mkdir(parents=True, exist_ok=True)
    files: list[ExportedFile] = []
    for mcap_path, name in zip(mcaps, names, strict=True):
        drawn = mcap_to_rrd(mcap_path, out / name, recording_id=mcap_path.stem)
        files.append({"mcap": str(mcap_path), "rrd": str(out / name), "drawn": drawn})
    return {"format": "rrd", "out": str(out), "files": files, "seconds": round(time.perf_counter() - started, 3)}
