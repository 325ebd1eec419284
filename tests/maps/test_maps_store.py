"""Map store: schema contract, Parquet round trip, and the grid index against a brute-force scan."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from logpipe.contracts import arrow_schema
from logpipe.maps import FeatureKind, MapBuilder, MapStore, load_map
from logpipe.maps.grid_index import split_polyline

DATA = Path(__file__).parents[1] / "data" / "maps"
SHARED = (Path(__file__).parents[2] / ".." / "shared" / "data").resolve()


@pytest.fixture(scope="module")
def mia_crop() -> MapStore:
    return load_map(DATA / "MIA_lane_centerlines_crop_2645.npz")


def _brute(store: MapStore, kind: FeatureKind, box: tuple[float, float, float, float]) -> set[int]:
    xmin, ymin, xmax, ymax = box
    hits = set()
    for r in store.rows(kind).tolist():
        g = store.geometry(r)
        lo, hi = g.min(axis=0), g.max(axis=0)
        if hi[0] >= xmin and lo[0] <= xmax and hi[1] >= ymin and lo[1] <= ymax:
            hits.add(r)
    return hits


def _brute_chunks(store: MapStore, kind: FeatureKind, box: tuple[float, float, float, float]) -> set[int]:
    layer = store.layer(kind)
    xmin, ymin, xmax, ymax = box
    lo, hi = layer.lo, layer.hi
    hit = (hi[:, 0] >= xmin) & (lo[:, 0] <= xmax) & (hi[:, 1] >= ymin) & (lo[:, 1] <= ymax)
    return set(layer.features[hit].tolist())


def _random_boxes(bounds: tuple[float, float, float, float], seed: int,
                  n: int = 300) -> list[tuple[float, float, float, float]]:
    """Square query windows (half-size 1-120 m) centred anywhere up to 200 m outside ``bounds``."""
    rng = np.random.default_rng(seed)
    xmin, ymin, xmax, ymax = bounds
    boxes = []
    for _ in range(n):
        cx, cy = rng.uniform(xmin - 200, xmax + 200), rng.uniform(ymin - 200, ymax + 200)
        half = rng.uniform(1, 120)
        boxes.append((cx - half, cy - half, cx + half, cy + half))
    return boxes


def test_schema_matches_contract(mia_crop: MapStore) -> None:
    assert mia_crop.table.schema.equals(arrow_schema("map"), check_metadata=False)
    assert mia_crop.table.schema.metadata[b"logpipe.schema"] == b"map"


def test_parquet_round_trip_is_exact_and_reproducible(mia_crop: MapStore, tmp_path: Path) -> None:
    a, b = tmp_path / "a.parquet", tmp_path / "b.parquet"
    mia_crop.write(a)
    back = MapStore.read(a)
    back.write(b)
    assert a.read_bytes() == b.read_bytes()
    assert back.table.equals(mia_crop.table)
    assert pq.read_schema(a).field("xs").type == arrow_schema("map").field("xs").type
    loaded = load_map(a)  # the registry reads stores too
    assert loaded.counts() == mia_crop.counts()


def test_grid_query_equals_linear_scan(mia_crop: MapStore) -> None:
    rng = np.random.default_rng(0)
    xmin, ymin, xmax, ymax = mia_crop.bounds
    for _ in range(200):
        # Boxes anywhere, including partly and wholly outside the map (edges of the city).
        cx = rng.uniform(xmin - 150, xmax + 150)
        cy = rng.uniform(ymin - 150, ymax + 150)
        half = rng.uniform(1, 90)
        box = (cx - half, cy - half, cx + half, cy + half)
        got = set(mia_crop.query(FeatureKind.LANE_CENTERLINE, *box).tolist())
        # Chunk boxes are tighter than a whole lane's box (an L-shaped lane's box covers its corner).
        assert got <= _brute(mia_crop, FeatureKind.LANE_CENTERLINE, box)
        assert got == _brute_chunks(mia_crop, FeatureKind.LANE_CENTERLINE, box)


def test_dense_cell_table_equals_bisect_fallback(mia_crop: MapStore, monkeypatch: pytest.MonkeyPatch) -> None:
    import logpipe.maps.grid_index as grid_mod

    dense = mia_crop.render_layer(FeatureKind.LANE_CENTERLINE)
    assert dense.cell_start is not None
    monkeypatch.setattr(grid_mod, "MAX_DENSE_CELLS", 0)  # as for a huge, sparse map
    sparse = MapStore(mia_crop.table).render_layer(FeatureKind.LANE_CENTERLINE)
    assert sparse.cell_start is None
    for box in _random_boxes(mia_crop.bounds, seed=1):
        assert dense.candidate_ranges(*box) == sparse.candidate_ranges(*box)


@pytest.mark.parametrize("rows", [1, 3, 8])
def test_band_order_ranges_cover_every_overlapping_chunk(
    mia_crop: MapStore, monkeypatch: pytest.MonkeyPatch, rows: int
) -> None:
    import logpipe.maps.grid_index as grid_mod

    layer = mia_crop.render_layer(FeatureKind.LANE_CENTERLINE)
    dense = grid_mod.BandOrder(layer, rows)
    monkeypatch.setattr(grid_mod, "MAX_DENSE_CELLS", 0)
    sparse = grid_mod.BandOrder(layer, rows)
    assert dense.start is not None and sparse.start is None
    assert sorted(dense.order.tolist()) == list(range(len(layer)))
    assert (dense.order[dense.position] == np.arange(len(layer))).all()
    for box in _random_boxes(mia_crop.bounds, seed=2):
        ranges = dense.ranges(*box)
        assert ranges == sparse.ranges(*box)
        got = {int(dense.order[p]) for a, b in ranges for p in range(a, b)}
        assert set(layer.overlapping(*box).tolist()) <= got


def test_window_is_superset_and_preserves_segments(mia_crop: MapStore) -> None:
    layer = mia_crop.layer(FeatureKind.LANE_CENTERLINE)
    # Every chunk is at most one cell wide or listed as oversize.
    ext = (layer.hi - layer.lo).max(axis=1)
    assert (ext[: layer.n_regular] <= layer.cell).all()
    # The chunks together hold exactly the original segments.
    original = set()
    for r in mia_crop.rows(FeatureKind.LANE_CENTERLINE).tolist():
        g = mia_crop.geometry(r)
        original |= {tuple(np.round(np.r_[g[i], g[i + 1]], 6)) for i in range(len(g) - 1)}
    chunked = set()
    for i in range(len(layer)):
        g = layer.points[layer.offsets[i] : layer.offsets[i + 1]]
        chunked |= {tuple(np.round(np.r_[g[j], g[j + 1]], 6)) for j in range(len(g) - 1)}
    assert chunked == original
    w = layer.window(400.0, 1100.0, 450.0, 1150.0)
    exact = set(layer.features[layer.overlapping(400.0, 1100.0, 450.0, 1150.0)].tolist())
    assert exact <= set(layer.features[w.chunks].tolist())


def testsplit_polyline_limits_width_and_turn() -> None:
    t = np.linspace(0, np.pi, 40)
    arc = np.stack([30 * np.cos(t), 30 * np.sin(t)], axis=1)  # a half circle, 94 m long
    chunks = split_polyline(arc, 32.0, np.radians(20))
    assert len(chunks) > 3
    for c in chunks:
        d = np.diff(c, axis=0)
        a = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        assert (c.max(0) - c.min(0)).max() <= 32.0
        assert np.abs(a - a[0]).max() <= np.radians(20) + 1e-9
    assert np.array_equal(np.concatenate([chunks[0]] + [c[1:] for c in chunks[1:]]), arc)


def test_builder_drops_degenerate_and_closes_rings() -> None:
    b = MapBuilder("m", "test")
    b.add(FeatureKind.LANE_CENTERLINE, "one-point", [[0, 0]])
    with pytest.raises(ValueError, match="not finite"):  # issue 56: damage is an error, not a feature dropped
        b.add(FeatureKind.LANE_CENTERLINE, "nan", [[0, 0], [np.nan, 1]])
    b.add(FeatureKind.DRIVABLE_AREA, "sq", [[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]])
    store = b.build()
    assert store.counts() == {"lane_centerline": 0, "lane_boundary": 0, "drivable_area": 1, "crossing": 0}
    assert len(store.geometry(0)) == 4
    with pytest.raises(ValueError, match="unknown map attributes"):
        b.add(FeatureKind.CROSSING, "x", [[0, 0], [1, 0], [1, 1]], colour="red")


def test_distance_to_segments_not_vertices() -> None:
    b = MapBuilder("m", "test")
    b.add(FeatureKind.LANE_CENTERLINE, "1", [[0, 0], [100, 0]])
    store = b.build()
    d = store.distance_to(FeatureKind.LANE_CENTERLINE, [[50, 1.5], [50, -20], [130, 0]], max_dist=25)
    assert d[0] == pytest.approx(1.5)
    assert d[1] == pytest.approx(20.0)
    assert np.isinf(d[2])


@pytest.mark.shared
def test_whole_city_index_is_small_and_exact() -> None:
    npz = SHARED / "argoverse1/maps/lane_centerlines/derived/PIT_lane_centerlines.npz"
    if not npz.exists():
        pytest.skip(f"needs {npz}")
    store = load_map(npz)
    assert store.counts()["lane_centerline"] == 4952
    layer = store.layer(FeatureKind.LANE_CENTERLINE)
    # The index is a sorted key list and per-chunk boxes: memory is O(features), not O(city area).
    assert layer.points.nbytes < 2_000_000
    xmin, ymin, xmax, ymax = store.bounds
    for box in [
        (xmin - 60, ymin - 60, xmin + 40, ymin + 40),
        (xmax - 40, ymax - 40, xmax + 60, ymax + 60),
        (2600.0, 1100.0, 2700.0, 1200.0),
    ]:
        got = set(store.query(FeatureKind.LANE_CENTERLINE, *box).tolist())
        assert got == _brute_chunks(store, FeatureKind.LANE_CENTERLINE, box)
        assert got <= _brute(store, FeatureKind.LANE_CENTERLINE, box)
