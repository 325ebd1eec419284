"""ROS bags through ``rosbags.highlevel.AnyReader``: ROS1 ``.bag`` (uncompressed, bz2, lz4) and ROS2 bags
(folders with ``metadata.yaml``, split files, bare ``.db3``/``.mcap`` storage files and split-file folders
without ``metadata.yaml``).

Bags without embedded message definitions (ROS2 sqlite3 before Iron) are decoded with a default typestore
(ROS2 Humble unless told otherwise). One bag = one log; ``log_id`` is the file stem or folder name. A ROS2 MCAP
bag that rosbags refuses as a whole because of one unparsable schema (rosbag2 service events) is read with the
mcap reader instead, which fails only that channel.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Collection, Iterator, Sequence
from pathlib import Path
from typing import Any, ClassVar

import pyarrow as pa
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from logpipe.errors import SourceError
from logpipe.formats.base import ParsedLogs, empty_tracks, read_each, read_head, require_regular_tree
from logpipe.formats.inflation import InflationError, check_ros1_bags
from logpipe.formats.mcapfile import McapAdapter
from logpipe.formats.ros.extract import ROSBAG_PROTOCOL, ExtractOptions, ReadStopped, extract_log
from logpipe.formats.ros.mapping import Mapping, TopicSummary
from logpipe.formats.ros.message_types import normalize_type
from logpipe.types import LogMeta, SampleProtocol, SourceFile

_SPLIT = re.compile(r"^(?P<stem>.+)_(?P<index>\d+)$")
_STORAGE_SUFFIXES = (".db3", ".mcap")
_EMPTY_MD5 = "d41d8cd98f00b204e9800998ecf8427e"  # md5 of the empty string: an empty message definition


def _natural_key(path: Path) -> tuple[str, int]:
    m = _SPLIT.match(path.stem)
    return (m["stem"], int(m["index"])) if m else (path.stem, -1)


def split_parts(folder: Path) -> list[Path]:
    """Storage files of a folder without metadata.yaml that form one split recording (``name_0.db3`` ...)."""
    files = sorted((p for p in folder.iterdir() if p.suffix in _STORAGE_SUFFIXES), key=_natural_key)
    stems = {_natural_key(p)[0] for p in files}
    suffixes = {p.suffix for p in files}
    if len(files) > 1 and len(stems) == 1 and len(suffixes) == 1 and all(_SPLIT.match(p.stem) for p in files):
        return files
    return []


def storage_paths(path: Path) -> list[Path]:
    """What to hand ``AnyReader`` for a discovered input: the bag itself, or the parts of a split folder."""
    if path.is_dir() and not (path / "metadata.yaml").exists():
        return split_parts(path) or sorted(p for p in path.iterdir() if p.suffix in _STORAGE_SUFFIXES)
    return [path]


def log_id_of(path: Path) -> str:
    """The bag's file stem or folder name."""
    return path.name if path.is_dir() else path.stem


@functools.cache
def _typestore(name: str) -> Typestore:
    return get_typestore(Stores[name.upper()])


def _metadata_topics(folder: Path) -> list[dict[str, Any]]:
    """``topic_metadata`` entries of a rosbag2 metadata.yaml, [] when absent or unreadable."""
    try:
        doc = yaml.safe_load((folder / "metadata.yaml").read_text(encoding="utf-8"))
        entries = doc["rosbag2_bagfile_information"]["topics_with_message_count"]
        return [dict(e["topic_metadata"]) for e in entries]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return []


def explain_open_error(path: Path, err: BaseException) -> tuple[str, str | None]:
    """A reason in words and the topic concerned, for a bag that AnyReader refuses to open."""
    text = str(err).strip()
    first = text.splitlines()[0] if text else type(err).__name__
    folder = path if path.is_dir() else path.parent
    if "hash mismatch" in text and _EMPTY_MD5 in text:
        topic = _empty_definition_topic(path)
        reason = (
            "rosbags cannot open the bag: the connection has an EMPTY message definition "
            f"(md5 of '' in the connection header), so its messages cannot be decoded ({first})"
        )
        return reason, topic
    if "Serialization format" in text:
        bad = [t for t in _metadata_topics(folder) if t.get("serialization_format") not in ("cdr", None)]
        topic = bad[0].get("name") if bad else None
        fmt = bad[0].get("serialization_format") if bad else "?"
        return (f"rosbags cannot open the bag: metadata.yaml declares serialization format {fmt!r}, "
                f"not 'cdr' ({first})", topic)  # fmt: skip
    if text.startswith("Could not parse"):
        srv = [t for t in _metadata_topics(folder) if "/srv/" in str(t.get("type", ""))]
        topic = srv[0].get("name") if srv else None
        what = f"the service-event type {srv[0].get('type')!r}" if srv else "an embedded message definition"
        return (f"rosbags cannot open the bag: {what} has a .srv schema (request/response separated by "
                "'---') that rosbags cannot parse; read the .mcap with the mcap adapter to keep the other topics",
                topic)  # fmt: skip
    if "not indexed" in text or "reindex" in text.lower():
        return f"the bag is not indexed (truncated or still being recorded?): {first}", None
    return f"rosbags cannot open the bag: {type(err).__name__}: {first}", None


def _empty_definition_topic(path: Path) -> str | None:
    from rosbags.rosbag1 import Reader as Reader1

    try:
        with Reader1(path) as reader:
            for conn in reader.connections:
                if not conn.msgdef.data.strip():
                    return conn.topic
    except Exception:  # only a nicer message is at stake
        return None
    return None


_MAGIC = {".bag": b"#ROSBAG V2.0\n", ".db3": b"SQLite format 3\x00"}
"""First bytes of a ROS1 bag and of a rosbag2 sqlite3 storage file."""


def _damaged_bag(path: Path) -> bool:
    """A ``.bag`` that fails the sniff but is a damaged bag rather than some other file: empty, not a regular file
    (FIFO, device, dangling link), or a ROS 1 magic with at most two bytes changed."""
    if not path.is_file():
        return True
    head = read_head(path, len(_MAGIC[".bag"]))
    if not head:
        return True
    return len(head) == len(_MAGIC[".bag"]) and sum(a != b for a, b in zip(head, _MAGIC[".bag"], strict=True)) <= 2


class RosbagAdapter:
    """ROS1/ROS2 bags → tracks (see the module docstring).

    Args:
        mapping: which topics are the ego and the other agents (a ``Mapping`` or a TOML/YAML file path);
            None = detect from the topic types.
        hz: output rate (Hz); 0/None keeps the source timestamps (``frame_rate_hz`` is then 0).
        allow_empty: a bag that yields no track rows is returned empty instead of an error.
        gap_periods: source gaps longer than this many output periods are not interpolated across.
        typestore: rosbags store for bags without embedded definitions (``ros2_humble``, ``ros1_noetic``...).
        mapping_overrides: CLI ``key=value`` overrides merged over the mapping file (see ``mapping.py``).
        with_mcap: also find and read standalone ``.mcap`` files (through ``McapAdapter``, same options): what
            ``logpipe.formats.choose_format`` asks for a folder holding both bags and MCAP files, one dataset.
    """

    name: ClassVar[str] = "rosbag"
    default_protocol: ClassVar[SampleProtocol] = ROSBAG_PROTOCOL
    batch_files: ClassVar[int] = 1
    hashes_while_reading: ClassVar[bool] = False

    def __init__(
        self,
        mapping: Mapping | str | Path | None = None,
        hz: float | None = 10.0,
        allow_empty: bool = False,
        gap_periods: float = 2.0,
        typestore: str = "ros2_humble",
        mapping_overrides: Sequence[str] = (),
        with_mcap: bool = False,
    ) -> None:
        self.options = ExtractOptions.from_settings(mapping, mapping_overrides, hz, gap_periods, allow_empty)
        self.with_mcap = with_mcap
        if typestore.upper() not in Stores.__members__:
            raise ValueError(f"unknown typestore {typestore!r}; one of {[s.name.lower() for s in Stores]}")
        self.typestore_name = typestore  # built on first read: detect() constructs adapters just to sniff

    # --- finding inputs

    def sniff(self, path: Path) -> bool:
        """A ``.bag`` with the ROS1 magic, a folder with metadata.yaml or split storage, a ``.db3``, or a file of
        a rosbag2 folder (``metadata.yaml`` or storage beside one)."""
        if path.is_dir():
            return (path / "metadata.yaml").exists() or bool(split_parts(path))
        if path.parent.joinpath("metadata.yaml").exists() and (
            path.name == "metadata.yaml" or path.suffix in _STORAGE_SUFFIXES
        ):
            return True
        magic = _MAGIC.get(path.suffix)
        if magic is None:
            return False
        return read_head(path, len(magic)) == magic

    def discover(self, root: Path) -> list[Path]:
        """Bags under ``root``: ``.bag`` files, rosbag2 folders (with metadata.yaml, or split parts), bare
        ``.db3`` files. Standalone ``.mcap`` files are left to the MCAP adapter, unless ``with_mcap``."""
        bags = self._discover_bags(root)
        if not self.with_mcap:
            return bags
        folders = [b for b in bags if b.is_dir()]
        mcaps = [m for m in McapAdapter().discover(root) if not any(m.is_relative_to(f) for f in folders)]
        return sorted([*bags, *mcaps])

    def _discover_bags(self, root: Path) -> list[Path]:
        if root.is_file():
            if root.suffix in (*_STORAGE_SUFFIXES, ".yaml") and (root.parent / "metadata.yaml").exists():
                return [root.parent]  # a file of a rosbag2 folder stands for the folder
            return [root] if self.sniff(root) else []
        if not root.is_dir():
            return []
        if self.sniff(root):
            return [root]
        found: list[Path] = []
        for child in sorted(root.iterdir()):
            if child.is_dir():
                found += self._discover_bags(child)
            elif child.suffix in (".bag", ".db3") and self.sniff(child):
                found.append(child)
            elif child.suffix == ".bag" and _damaged_bag(child):
                found.append(child)  # quarantined saying what is wrong, not skipped as "no bag"
        return sorted(found)

    # --- reading

    def read(self, sources: Sequence[SourceFile], *, keep_going: bool) -> ParsedLogs:
        """Parse bags into track rows (see ``FormatAdapter.read``)."""
        return read_each(sources, lambda src: self.read_one(src, keep_going=keep_going), keep_going=keep_going,
                         empty=empty_tracks())

    def read_one(self, src: SourceFile, *, keep_going: bool) -> tuple[pa.Table, LogMeta, list[SourceError]]:
        """One bag → (rows, LogMeta, per-topic problems kept when ``keep_going``)."""
        path = Path(src.path)
        if self.with_mcap and path.is_file() and path.suffix == ".mcap" and McapAdapter().sniff(path):
            opts = self.options  # a standalone MCAP of a folder mixing formats: the MCAP adapter reads it
            return McapAdapter(mapping=opts.mapping, hz=opts.hz, allow_empty=opts.allow_empty,
                               gap_periods=opts.gap_periods).read_one(src, keep_going=keep_going)
        rel = src.relpath
        paths = storage_paths(path)
        if not paths:
            raise SourceError(rel, "folder holds no metadata.yaml and no .db3/.mcap storage file")
        if path.is_dir():
            require_regular_tree(path, rel)  # a FIFO among a bag's files would block the reader forever
        try:
            check_ros1_bags(paths)  # before rosbags decompresses any chunk, unbounded
        except InflationError as err:
            raise SourceError(rel, f"refused: {err}") from None
        try:
            reader = AnyReader(paths, default_typestore=_typestore(self.typestore_name))
            reader.open()
        except Exception as err:  # rosbags raises many kinds; every one is a bad input here
            reason, topic = explain_open_error(path, err)
            mcaps = sorted(path.glob("*.mcap")) if path.is_dir() else [path] if path.suffix == ".mcap" else []
            if str(err).startswith("Could not parse") and len(mcaps) == 1:
                # rosbags refuses the whole bag for one schema it cannot parse (a .srv service event);
                # the mcap reader decodes channel by channel, so the other topics stay usable
                return self._read_with_mcap(mcaps[0], path, src, keep_going=keep_going, why=reason)
            raise SourceError(rel, reason, field=topic) from None
        try:
            return self._read_open(reader, path, src, keep_going=keep_going)
        finally:
            reader.close()

    def _read_with_mcap(
        self, file: Path, path: Path, src: SourceFile, *, keep_going: bool, why: str
    ) -> tuple[pa.Table, LogMeta, list[SourceError]]:
        opts = self.options
        mcap = McapAdapter(mapping=opts.mapping, hz=opts.hz, allow_empty=opts.allow_empty, gap_periods=opts.gap_periods)
        inner = SourceFile(str(file), src.relpath, src.sha256, src.size, src.memberships)
        table, meta, problems = mcap.read_one(inner, keep_going=keep_going, log_id=log_id_of(path))
        meta.source_format = self.name
        meta.attributes["storage"] = "rosbag2 (read with the mcap reader)"
        meta.attributes["rosbags_refused"] = why
        return table, meta, problems

    @staticmethod
    def _probe(reader: AnyReader, rel: str, topics: list[TopicSummary], conns: dict[str, list[Any]]) -> None:
        """Fail a ROS2 bag whose metadata declares messages that the reader cannot find (rosbags matches
        metadata.yaml topics to storage connections by type and QoS and silently yields nothing on a mismatch)."""
        declared = [t for t in topics if t.count and t.topic in conns]
        for t in declared:
            if next(iter(reader.messages(connections=conns[t.topic])), None) is not None:
                return
        if declared:
            t = declared[0]
            raise SourceError(
                rel,
                f"metadata.yaml declares {sum(x.count or 0 for x in declared)} messages "
                f"({t.count} on this topic) but rosbags reads none from the storage files: the topics in "
                "metadata.yaml do not match the storage's connections (offered QoS or type differ)",
                field=t.topic,
            )

    def _read_open(
        self, reader: AnyReader, path: Path, src: SourceFile, *, keep_going: bool
    ) -> tuple[pa.Table, LogMeta, list[SourceError]]:
        rel = src.relpath
        topics = [TopicSummary(name, info.msgtype or "?", info.msgcount) for name, info in reader.topics.items()]
        if reader.message_count == 0 and not self.options.allow_empty:
            names = ", ".join(sorted(t.topic for t in topics)) or "none"
            raise SourceError(rel, f"the bag holds no messages (topics: {names})")
        log_id = log_id_of(path)
        conns_by_topic: dict[str, list[Any]] = {}
        for conn in reader.connections:
            conns_by_topic.setdefault(conn.topic, []).append(conn)
        if reader.is2:
            self._probe(reader, rel, topics, conns_by_topic)

        def read(wanted: Collection[str]) -> Iterator[tuple[str, int, Any]]:
            # topic by topic: extraction needs no cross-topic order, and rosbags' merge of several connections
            # is slow on bags whose chunks interleave them (evo/ROS_example: 2 topics merged take 17x longer)
            for topic in wanted:
                conns = conns_by_topic.get(topic, [])
                try:
                    for conn, t, raw in reader.messages(connections=conns):
                        try:
                            msg = reader.deserialize(raw, conn.msgtype)
                        except Exception as err:  # reported per topic by extract_log
                            yield topic, t, err
                            continue
                        yield topic, t, msg
                except Exception as err:  # a damaged chunk ends the topic
                    yield topic, 0, ReadStopped(f"{type(err).__name__}: {err}")

        result = extract_log(rel, topics, read, self.options, log_id, keep_going=keep_going)
        attributes = {
            **({} if reader.is2 else {"unchecked": "a ROS 1 bag carries no checksums: corruption inside it cannot be "
                                      "detected"}),
            "storage": "rosbag2" if reader.is2 else "rosbag1",
            "files": [p.name for p in paths] if (paths := storage_paths(path)) and path.is_dir() else [path.name],
            "start_ns": reader.start_time if reader.message_count else None,
            "end_ns": reader.end_time - 1 if reader.message_count else None,  # rosbags' end is last stamp + 1
            **result.attributes,
        }
        attributes["message_types"] = {t.topic: normalize_type(t.msgtype) for t in topics}
        meta = LogMeta(
            log_id=log_id,
            source_format=self.name,
            source_file=rel,
            source_sha256=src.sha256,
            map_id=result.map_id,
            frame_rate_hz=float(self.options.hz or 0.0),
            memberships=src.memberships,
            attributes=attributes,
        )
        return result.tracks, meta, result.failures
