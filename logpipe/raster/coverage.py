"""Which logs of a rasterise run have a map, and what a run with blank rasters must say: ``rasterise`` refuses
maps that cover none of the dataset's logs and lists in its summary what made rasters blank."""

from __future__ import annotations

from pathlib import Path

from logpipe.errors import DatasetError
from logpipe.maps import MapSource
from logpipe.summaries import RasteriseSummary


def check_map_coverage(root: Path, maps: MapSource, log_map: dict[str, str | None],
                       map_files: dict[str, Path | None]) -> None:
    """Refuse a run that could only draw blank rasters: a ``--maps`` folder that does not exist, or maps that
    cover none of the dataset's logs (a typo in a path must not pass as a finished run of empty images)."""
    for folder in maps.roots:
        if not folder.is_dir():
            raise DatasetError(f"--maps {folder}: no such folder")
    if not log_map or any(p is not None for p in map_files.values()):
        return
    logs = sorted(log_map)
    ids = sorted({m for m in log_map.values() if m})
    where = (f"under --maps {', '.join(map(str, maps.roots))}" if maps.roots else "(no --maps folder given)")
    given = f"; --map given for {', '.join(sorted(maps.files))}" if maps.files else ""
    raise DatasetError(
        f"{root}: no map found for any of its {len(logs)} logs ({', '.join(logs[:5])}{', ...' if len(logs) > 5 else ''}"
        f"; map ids looked for: {', '.join(ids) or 'none, the logs name no map'}) {where}{given}; "
        "give --maps FOLDER or --map MAP_ID=FILE")


def blank_warnings(summary: RasteriseSummary, n: int, out: Path) -> list[str]:
    """Record in ``warnings`` (and return) what makes rasters blank: logs without a map, and samples of logs with one
    whose raster shows nothing of it (the centre off the map)."""
    if summary["logs_without_map"]:
        examples = summary["logs_without_map_examples"]
        summary["warnings"].append(f"{summary['logs_without_map']} logs have no map, their rasters are blank "
                                   f"(e.g. {', '.join(examples[:3])})")
    if summary["blank_with_map"]:
        summary["warnings"].append(f"{summary['blank_with_map']} of {n} rasters are blank although their log has a "
                                   f"map (centre off the map); `empty` in {out / 'index-*.parquet'} marks them")
    return summary["warnings"]
