"""HD maps: one canonical store (``store.MapStore``) and one adapter per source format.

``load_map(path_or_city, roots=...)`` is the single entry point: give it a file (AV1 ``.npz`` or vector-map
``.xml``, AV2 ``log_map_archive_*.json``, Lanelet2 ``.osm``, or a store ``.parquet``), a folder holding one
map, or a city/map name to look up under ``roots``. ``MapSource`` resolves the map of each log of a
dataset and caches the loaded stores.
"""

from __future__ import annotations

import re
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from logpipe.errors import DatasetError, LogpipeError, SourceError
from logpipe.maps import argoverse1, av2, commonroad, lanelet2
from logpipe.maps.feature_kinds import KINDS, POLYGON_KINDS, FeatureKind
from logpipe.maps.grid_index import Layer, Window
from logpipe.maps.store import MapBuilder, MapStore
from logpipe.storage.regular_files import irregular_kind

__all__ = [
    "ADAPTERS",
    "KINDS",
    "POLYGON_KINDS",
    "FeatureKind",
    "Layer",
    "MapAdapter",
    "MapBuilder",
    "MapSource",
    "MapStore",
    "Window",
    "find_map_files",
    "load_map",
]


@dataclass(frozen=True)
class MapAdapter:
    """A map file format.

    Attributes:
        name: short id (also written to the store's ``source`` column).
        sniff: cheap test whether a path is in this format.
        load: ``(path, map_id or None) -> MapStore``.
    """

    name: str
    sniff: Callable[[Path], bool]
    load: Callable[[Path, str | None], MapStore]


def _load_parquet(path: Path, map_id: str | None) -> MapStore:
    del map_id  # a store file carries its own map_id
    return MapStore.read(path)


def _load_lanelet2(path: Path, map_id: str | None) -> MapStore:
    return lanelet2.load(path, map_id)


ADAPTERS: tuple[MapAdapter, ...] = (
    MapAdapter("store_parquet", lambda p: p.suffix == ".parquet", _load_parquet),
    MapAdapter(argoverse1.NPZ_SOURCE, argoverse1.sniff_npz, argoverse1.load_npz),
    MapAdapter(commonroad.SOURCE, commonroad.sniff, commonroad.load),
    MapAdapter(lanelet2.SOURCE, lanelet2.sniff, _load_lanelet2),
    MapAdapter(argoverse1.XML_SOURCE, argoverse1.sniff_xml, argoverse1.load_xml),
    MapAdapter(av2.SOURCE, av2.sniff, av2.load),
)
"""Tried in order; CommonRoad and Lanelet2 before AV1 XML because all three are XML, and only CommonRoad opens a
``<commonRoad>`` element and only Lanelet2 has lanelet relations."""

_MAP_SUFFIXES = {".npz", ".xml", ".osm", ".json", ".parquet"}


def _adapter_for(path: Path) -> MapAdapter:
    for adapter in ADAPTERS:
        if adapter.sniff(path):
            return adapter
    raise DatasetError(f"{path}: not a map format logpipe reads ({', '.join(a.name for a in ADAPTERS)})")


_CITY_CODE = re.compile(r"^[A-Z]{3}$")


def map_names(path: Path) -> set[str]:
    """The names a map file answers to, lower-cased: its stem, an AV1 city code among its name's parts
    (``MIA`` of ``MIA_lane_centerlines.npz``, of ``pruned_argoverse_MIA_10316_vector_map.xml``), and an AV2
    archive's log id and city (``PIT_city_57819`` and ``PIT``). Matching is exact: a substring (``a``, ``.``,
    ``lane``) used to pick the first map whose file name contained it."""
    names = {path.stem, *(part for part in path.stem.split("_") if _CITY_CODE.match(part))}
    log, city = av2.names_from_path(path)
    names |= {n for n in (log, city, city.split("_")[0] if city else None) if n}
    return {n.lower() for n in names}


def find_map_files(name: str, roots: Iterable[Path]) -> list[Path]:
    """Map files under ``roots`` that answer to ``name`` (``map_names``, case-insensitive; "" lists all), best
    match first.

    Preference: a canonical store, then AV1 vector-map XML, AV1 npz, Lanelet2, AV2 JSON; shorter names
    first within a format so ``MIA_lane_centerlines.npz`` wins over unrelated longer names.
    """
    rank = {".parquet": 0, ".xml": 1, ".npz": 2, ".osm": 3, ".json": 4}
    needle = name.lower()
    hits: set[Path] = set()
    for root in roots:
        if root.is_file():
            if not needle or needle in map_names(root):
                hits.add(root)
            continue
        for p in root.rglob("*"):
            if p.suffix in _MAP_SUFFIXES and (not needle or needle in map_names(p)) and p.is_file():
                hits.add(p)
    return sorted(hits, key=lambda p: (rank.get(p.suffix, 9), len(p.name), str(p)))


def load_map(path_or_city: str | Path, roots: Sequence[Path] = (), map_id: str | None = None) -> MapStore:
    """Load one map into the canonical store.

    Args:
        path_or_city: a map file, a folder with exactly one map file (e.g. an AV2 ``map/`` folder), or a
            map name (``MIA``, ``PIT``, ``PIT_city_57819``, an AV2 log id) looked up under ``roots``.
        roots: folders searched when ``path_or_city`` is a name.
        map_id: override the map name written into the store.

    Raises:
        DatasetError: nothing matches, a folder holds several candidate maps, or the format is unknown.
        SourceError: the file is in a known format but broken.
    """
    path = Path(path_or_city)
    if path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.suffix in _MAP_SUFFIXES and _regular(p) and _sniffs(p))
        if len(files) != 1:
            raise DatasetError(f"{path}: expected one map file, found {[p.name for p in files]}")
        path = files[0]
    elif not _regular(path):
        files = [p for p in find_map_files(str(path_or_city), roots) if _sniffs(p)]
        if not files:
            raise DatasetError(f"no map named {path_or_city!r} under {[str(r) for r in roots]}")
        path = files[0]
    return _load(path, map_id)


def _sniffs(path: Path) -> bool:
    """Whether ``path`` is a map file of a known format; a file that has a map's name and suffix but is damaged
    (a corrupt zip, an unreadable file) raises instead, so a damaged map is never taken for "no map".

    Raises:
        SourceError: naming the file.
    """
    try:
        if any(a.sniff(path) for a in ADAPTERS):
            return True
    except Exception as err:  # a sniff that cannot read the file at all
        raise _map_error(path, err) from None
    if path.suffix == ".npz":  # the npz sniff says False for a damaged archive: tell damage from "other npz"
        try:
            with zipfile.ZipFile(path) as z:
                broken = z.testzip()
        except Exception as err:
            raise _map_error(path, err) from None
        if broken is not None:
            raise SourceError(str(path), f"damaged map archive: member {broken!r} fails its CRC check")
    return False


def _map_error(path: Path, err: BaseException) -> SourceError:
    if isinstance(err, SourceError):
        return err
    text = str(err).strip().splitlines()[0][:200] if str(err).strip() else ""
    what = f"{type(err).__name__}: {text}" if text else type(err).__name__
    return SourceError(str(path), f"unreadable or damaged map file: {what}")


def _regular(path: Path) -> bool:
    """Whether ``path`` is a regular file; False when nothing is there. A FIFO, device or socket is refused: a
    map reader would block on it forever (or, for ``/dev/zero``, never finish).

    Raises:
        SourceError: naming the path and what it is.
    """
    try:
        kind = irregular_kind(path)
    except OSError:
        return False
    if kind in (None, "a folder"):
        return kind is None
    raise SourceError(str(path), f"not a regular file: {kind}; only regular files are read as maps")


def _load(path: Path, map_id: str | None) -> MapStore:
    """``_adapter_for(path).load`` with any failure of a damaged file as one ``SourceError`` naming it."""
    _regular(path)
    try:
        adapter = _adapter_for(path)
    except DatasetError:
        _sniffs(path)  # a damaged map file says so rather than "not a map format"
        raise
    except Exception as err:  # a sniff that cannot read the file
        raise _map_error(path, err) from None
    try:
        return adapter.load(path, map_id)
    except Exception as err:
        if isinstance(err, LogpipeError) and not isinstance(err, SourceError):
            raise
        raise _map_error(path, err) from None


@dataclass
class MapSource:
    """Finds and caches the map of each log of a dataset.

    Resolution for a log: an explicit ``files[map_id]``; then the log's own map (``own[log_id]``: the store ingest
    kept for a log whose input carries its map, CommonRoad); then an AV2 per-log archive
    ``log_map_archive_<log_id>*.json`` under ``roots``; then a file named after ``map_id`` (AV1 city
    ``MIA`` → ``MIA_lane_centerlines.npz``). Loaded stores are kept in an LRU of ``cache_size`` maps so a
    run over many per-log AV2 maps holds only a few in memory.

    Attributes:
        roots: folders searched for map files.
        files: explicit map file per ``map_id`` (takes precedence).
        own: the map store file of each log that has its own (``Dataset.own_maps()``), by log id.
        cache_size: how many loaded stores to keep.
    """

    roots: tuple[Path, ...] = ()
    files: dict[str, Path] = field(default_factory=dict)
    own: dict[str, Path] = field(default_factory=dict)
    cache_size: int = 4
    _cache: OrderedDict[Path, MapStore] = field(default_factory=OrderedDict, repr=False)
    _listing: list[Path] | None = field(default=None, repr=False)

    def _candidates(self, name: str) -> list[Path]:
        # List the roots once per source: resolving thousands of logs must not walk the tree each time.
        if self._listing is None:
            self._listing = find_map_files("", self.roots)  # already in preference order
        needle = name.lower()
        return [p for p in self._listing if needle in map_names(p)]

    def resolve(self, map_id: str | None, log_id: str | None = None) -> Path | None:
        """The map file for a log, or None when nothing matches."""
        if map_id is not None and map_id in self.files:
            given = self.files[map_id]
            if not _regular(given) and not given.is_dir():  # a FIFO is refused here, before anything hashes it
                raise SourceError(str(given), "map file not found")
            return given
        if log_id in self.own:
            return self.own[log_id]
        if log_id:
            tail = log_id.rsplit("/", 1)[-1]
            for cand in self._candidates(tail):
                # The archive must name exactly this log (AV1 log "1" must not pick up an AV2 uuid with a 1).
                if av2.names_from_path(cand)[0] == tail:
                    if _sniffs(cand):
                        return cand
                    # Named as this log's archive but not one: damage, which must not pass for "no map".
                    raise SourceError(str(cand), "named like this log's AV2 map archive but does not start like one "
                                      "(damaged or cut short?)")
        if map_id:
            for cand in self._candidates(map_id):
                if _sniffs(cand):
                    return cand
        return None

    def get(self, map_id: str | None, log_id: str | None = None) -> MapStore | None:
        """The loaded store for a log (cached), or None when no map is found."""
        path = self.resolve(map_id, log_id)
        if path is None:
            return None
        store = self._cache.get(path)
        if store is None:
            store = _load(path, None)
            self._cache[path] = store
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(path)
        return store
