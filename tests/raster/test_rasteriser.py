"""Rasteriser correctness: known pixels with and without rotation, real AGENT tracks on drawn lanes,
off-map and city-edge windows, agreement with the straightforward reference renderer."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pyarrow.csv as pacsv
import pytest

from logpipe.maps import FeatureKind, MapBuilder, MapStore, load_map
from logpipe.raster.rasteriser import (
    DEFAULT_CHANNELS,
    QUADRANT_CHANNELS,
    OffMapWarning,
    Rasteriser,
    RasterSpec,
    decode_direction,
    heading_from_motion,
    world_to_pixel,
)
from logpipe.raster.reference import render_baseline

DATA = Path(__file__).parents[1] / "data" / "maps"
SHARED = (Path(__file__).parents[2] / ".." / "shared" / "data").resolve()
LEGACY = ("drivable_area", "lane_centerline", "lane_direction", "lane_boundary", "crossing")
CL = 1  # channel indices in LEGACY
DIR = 2
CX, CY = 1000.0, 2000.0


def _one_lane(start: tuple[float, float], end: tuple[float, float]) -> MapStore:
    b = MapBuilder("synthetic", "test")
    pts = np.linspace(start, end, 9)
    b.add(FeatureKind.LANE_CENTERLINE, "1", pts, direction="forward")
    return b.build()


def _av1_csv(path: Path) -> dict[str, np.ndarray]:
    t = pacsv.read_csv(path).to_pydict()
    ts = np.array(t["TIMESTAMP"])
    steps = np.searchsorted(np.unique(ts), ts)
    kind = np.array(t["OBJECT_TYPE"])
    xy = np.stack([np.array(t["X"]), np.array(t["Y"])], axis=1)
    out: dict[str, np.ndarray] = {"city": np.array(t["CITY_NAME"][:1])}
    for name in ("AV", "AGENT"):
        sel = np.flatnonzero(kind == name)
        out[name] = xy[sel[np.argsort(steps[sel])]]
    return out


def S(**kw: object) -> RasterSpec:  # noqa: N802 - reads like the class it builds
    """A spec with the plain centerline + direction-sector channels (LEGACY order)."""
    return RasterSpec(channels=LEGACY, **kw)  # type: ignore[arg-type]


def spec_res() -> float:
    return RasterSpec().resolution_m


def test_affine_conventions() -> None:
    spec = S()
    a = world_to_pixel(spec, CX, CY)
    assert np.allclose(a @ [CX, CY, 1], [111.5, 111.5])  # exact middle of a 224 px image
    assert np.allclose(a @ [CX + 10, CY, 1], [111.5 + 22.4, 111.5])  # +x right, 0.4464 m/px
    assert np.allclose(a @ [CX, CY + 10, 1], [111.5, 111.5 - 22.4])  # +y up
    rot = world_to_pixel(S(rotate=True), CX, CY, heading=math.radians(30))
    fwd = [CX + 10 * math.cos(math.radians(30)), CY + 10 * math.sin(math.radians(30)), 1]
    assert np.allclose(rot @ fwd, [111.5, 111.5 - 22.4])  # heading points up
    left = [CX - 10 * math.sin(math.radians(30)), CY + 10 * math.cos(math.radians(30)), 1]
    assert np.allclose(rot @ left, [111.5 - 22.4, 111.5])  # the agent's left is image left


def test_lane_lands_on_expected_pixel_north_up() -> None:
    # A north-going lane 10 m east of the centre: column 111.5 + 10 / 0.4464 = 133.9.
    store = _one_lane((CX + 10, CY - 30), (CX + 10, CY + 30))
    res = Rasteriser(store, S()).render(CX, CY)
    cl = res.image[CL]
    rows = slice(60, 160)
    # Anti-aliased across columns 133/134; the intensity centroid is at the sub-pixel position.
    band = cl[rows, 130:138].astype(float)
    centroid = (band * np.arange(130, 138)).sum(axis=1) / band.sum(axis=1)
    assert np.allclose(centroid, 111.5 + 10 / spec_res(), atol=0.25)
    assert cl[rows, :131].max() == 0 and cl[rows, 137:].max() == 0
    # Ends at y = +-30 m -> rows 111.5 -+ 67.2.
    assert cl[46:177, 134].min() > 0 and cl[:43, 134].max() == 0 and cl[181:, 134].max() == 0
    # Direction: north = image up = pi/2.
    vals = set(np.unique(res.image[DIR])) - {0}
    assert len(vals) == 1
    assert decode_direction(int(vals.pop()), 16) == pytest.approx(math.pi / 2)
    assert res.image[0].max() == 0 and res.image[3].max() == 0 and res.image[4].max() == 0


def test_lane_lands_on_expected_pixel_rotated() -> None:
    # Heading east: the same north-going lane 10 m ahead appears as a horizontal line 22.4 px above the
    # centre (row 89.1) running towards image left (the agent's left, north).
    store = _one_lane((CX + 10, CY - 30), (CX + 10, CY + 30))
    res = Rasteriser(store, S(rotate=True)).render(CX, CY, heading=0.0)
    cl = res.image[CL]
    cols = slice(60, 160)
    band = cl[85:94, cols].astype(float)
    centroid = (band * np.arange(85, 94)[:, None]).sum(axis=0) / band.sum(axis=0)
    assert np.allclose(centroid, 111.5 - 10 / spec_res(), atol=0.25)
    assert cl[:86, cols].max() == 0 and cl[93:, cols].max() == 0
    vals = set(np.unique(res.image[DIR])) - {0}
    assert decode_direction(int(vals.pop()), 16) == pytest.approx(math.pi)  # pointing image left
    # Any heading: the pixel the affine gives for a lane point is on the drawn line.
    for deg in (0, 37, 90, 145, 211, 300):
        r = Rasteriser(store, S(rotate=True)).render(CX, CY, heading=math.radians(deg))
        u, v = r.affine @ [CX + 10, CY + 5, 1]
        assert r.image[CL][round(v), round(u)] > 0


def test_off_map_gives_empty_raster_and_warning() -> None:
    store = load_map(DATA / "MIA_lane_centerlines_crop_2645.npz")
    ras = Rasteriser(store, S(rotate=True))
    with pytest.warns(OffMapWarning, match="no map feature"):
        res = ras.render(-5000.0, -5000.0, heading=1.0)
    assert res.empty and res.image.max() == 0
    assert res.image.shape == (5, 224, 224) and res.image.dtype == np.uint8
    assert Rasteriser(store, RasterSpec()).render(-5000.0, 0.0, warn=False).image.shape == (7, 224, 224)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Rasteriser(None, S()).render(0.0, 0.0, warn=False)  # no map, no warning when asked


def test_city_edge_windows_match_reference() -> None:
    store = load_map(DATA / "PIT_lane_centerlines_crop_3861.npz")
    xmin, ymin, xmax, ymax = store.bounds
    for rotate in (False, True):
        spec = S(rotate=rotate)
        ras = Rasteriser(store, spec)
        for cx, cy in ((xmin, ymin), (xmax, ymax), (xmin - 40, (ymin + ymax) / 2), (xmax + 10, ymin + 5)):
            res = ras.render(cx, cy, heading=0.7, warn=False)
            ref = render_baseline(store, spec, cx, cy, 0.7)
            assert np.array_equal(res.image[CL], ref[CL])
            assert (res.image[CL] > 0).mean() < 0.5  # only part of the window has map
        assert ras.render(xmin + 30, ymin + 30, heading=0.7).image[CL].max() == 255


def test_matches_reference_on_av2_map_all_channels() -> None:
    store = load_map(DATA / "log_map_archive_0a1e6f0a-1817-4a98-b02e-db8c9327d151.json")
    for rotate in (False, True):
        spec = S(rotate=rotate)
        res = Rasteriser(store, spec).render(-423.5, 1430.0, heading=1.6)
        ref = render_baseline(store, spec, -423.5, 1430.0, 1.6)
        for c in (0, 1, 3, 4):  # area, centerline, boundary, crossing: identical
            assert np.array_equal(res.image[c], ref[c]), spec.channels[c]
        # Direction: the same pixels are lit; values differ only where lanes of different directions
        # overlap (the reference keeps the last-drawn lane, ours the highest sector).
        lit = ref[DIR] > 0
        assert np.array_equal(res.image[DIR] > 0, lit)
        assert (res.image[DIR] != ref[DIR]).sum() < 0.1 * lit.sum()
        # The focal track's position is on drivable area; every channel has content here.
        assert res.image[0][111, 111] == 255
        assert all(res.image[c].max() > 0 for c in range(5))


@pytest.mark.parametrize("channels", [DEFAULT_CHANNELS, ("lane_centerline", "lane_up", "lane_down")])
def test_reused_rasteriser_matches_reference_on_random_windows(channels: tuple[str, ...]) -> None:
    # One rasteriser for many windows: its per-layer scratch buffers are rewritten by every render, so
    # windows in, at the edge of and off the map, in any order and heading, must each match the reference.
    store = load_map(DATA / "MIA_lane_centerlines_crop_2645.npz")
    xmin, ymin, xmax, ymax = store.bounds
    rng = np.random.default_rng(3)
    for rotate in (False, True):
        spec = RasterSpec(rotate=rotate, channels=channels)
        ras = Rasteriser(store, spec)
        out = np.zeros(spec.shape, np.uint8)
        for _ in range(40):
            cx, cy = rng.uniform(xmin - 60, xmax + 60), rng.uniform(ymin - 60, ymax + 60)
            h = float(rng.uniform(-math.pi, math.pi))
            res = ras.render(cx, cy, h, warn=False)
            assert np.array_equal(res.image, render_baseline(store, spec, cx, cy, h))
            out[:] = 0
            into = ras.render(cx, cy, h, warn=False, out=out)
            assert into.image is out and np.array_equal(out, res.image)
            assert into.n_features == res.n_features and np.array_equal(into.affine, res.affine)
    with pytest.raises(ValueError, match="out must be"):
        ras.render(0.0, 0.0, out=np.zeros((1, 224, 224), np.uint8))


def test_rendering_is_deterministic_and_spec_fingerprinted() -> None:
    store = load_map(DATA / "MIA_lane_centerlines_crop_2645.npz")
    a = Rasteriser(store, S(rotate=True)).render(419.35, 1125.93, 0.3).image
    b = Rasteriser(store, S(rotate=True)).render(419.35, 1125.93, 0.3).image
    assert np.array_equal(a, b)
    assert RasterSpec(rotate=True).fingerprint() != RasterSpec().fingerprint()
    assert RasterSpec().fingerprint() != S().fingerprint()
    assert RasterSpec.from_dict(S(rotate=True).to_dict()) == S(rotate=True)
    with pytest.raises(ValueError, match="unknown raster channels"):
        RasterSpec(channels=("lanes",))


def test_heading_from_motion() -> None:
    still = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01]])
    assert heading_from_motion(still) is None
    move = np.array([[0.0, 0.0], [1.0, 1.0], [1.01, 1.0], [1.02, 1.01]])
    assert heading_from_motion(move) == pytest.approx(math.atan2(1.01, 1.02), abs=1e-9)
    assert heading_from_motion(np.array([[0.0, 0.0], [np.nan, np.nan]])) is None


def _agent_on_drawn_lanes(store: MapStore, csv: Path) -> tuple[float, float]:
    """(max AGENT->centerline distance in m, fraction of in-window AGENT points with a lane pixel within
    2.3 m) for a raster centred on the AV at step 19, rotated to its motion."""
    tr = _av1_csv(csv)
    av, agent = tr["AV"], tr["AGENT"]
    dist = store.distance_to(FeatureKind.LANE_CENTERLINE, agent, max_dist=10.0)
    spec = S(rotate=True)
    res = Rasteriser(store, spec).render(*av[19], heading_from_motion(av[:20]))
    uv = agent @ res.affine[:, :2].T + res.affine[:, 2]
    inside = ((uv >= 5) & (uv <= 218)).all(axis=1)
    r = math.ceil(2.3 / spec.resolution_m)
    hits = [
        res.image[CL][max(round(v) - r, 0) : round(v) + r + 1, max(round(u) - r, 0) : round(u) + r + 1].max() > 0
        for u, v in uv[inside]
    ]
    return float(dist.max()), float(np.mean(hits)) if hits else 1.0


@pytest.mark.parametrize("name", ["MIA_lane_centerlines_crop_2645.npz", "PIT_lane_centerlines_crop_3861.npz"])
def test_fixture_agent_tracks_lie_on_drawn_lanes(name: str) -> None:
    store = load_map(DATA / name)
    csv = DATA / f"{name.split('_crop_')[1][:-4]}.csv"
    max_d, frac = _agent_on_drawn_lanes(store, csv)
    assert max_d < 2.3
    assert frac == 1.0


@pytest.mark.shared
def test_all_69_real_agent_tracks_lie_on_drawn_lanes() -> None:
    folder = SHARED / "argoverse1"
    csvs = sorted((folder / "data").glob("*.csv"))
    if len(csvs) < 69:
        pytest.skip(f"needs the 69 AV1 CSVs under {folder}")
    stores = {c: load_map(c, roots=[folder / "maps"]) for c in ("MIA", "PIT")}
    worst = 0.0
    for csv in csvs:
        city = str(_av1_csv(csv)["city"][0])
        max_d, frac = _agent_on_drawn_lanes(stores[city], csv)
        worst = max(worst, max_d)
        assert frac == 1.0, csv.name
    assert worst < 2.3  # the shared SOURCE.md measured a per-file maximum of 2.25 m


def test_quadrant_channels_sort_lanes_by_direction() -> None:
    # Two parallel lanes 10 m east (going north) and 10 m west (going south) of the centre.
    b = MapBuilder("synthetic", "test")
    b.add(FeatureKind.LANE_CENTERLINE, "n", np.linspace((CX + 10, CY - 30), (CX + 10, CY + 30), 9))
    b.add(FeatureKind.LANE_CENTERLINE, "s", np.linspace((CX - 10, CY + 30), (CX - 10, CY - 30), 9))
    store = b.build()
    spec = RasterSpec()
    assert spec.channels == DEFAULT_CHANNELS
    q = {name: spec.channels.index(name) for name in QUADRANT_CHANNELS}
    img = Rasteriser(store, spec).render(CX, CY).image  # north up
    assert img[q["lane_up"]][60:160, 133:135].max(axis=1).min() > 100  # east lane goes up
    assert img[q["lane_down"]][60:160, 88:91].max(axis=1).min() > 100  # west lane goes down
    assert img[q["lane_left"]].max() == 0 and img[q["lane_right"]].max() == 0
    # Heading east: the north-going lane (ahead, 10 m) runs towards image left; the other one right.
    rot = Rasteriser(store, RasterSpec(rotate=True)).render(CX, CY, heading=0.0).image
    assert rot[q["lane_left"]][85:94].max() > 200 and rot[q["lane_right"]][130:139].max() > 200
    assert rot[q["lane_up"]].max() == 0 and rot[q["lane_down"]].max() == 0


def test_quadrant_channels_match_reference_and_cover_centerlines() -> None:
    store = load_map(DATA / "log_map_archive_0a1e6f0a-1817-4a98-b02e-db8c9327d151.json")
    for rotate in (False, True):
        spec = RasterSpec(rotate=rotate)
        res = Rasteriser(store, spec).render(-423.5, 1430.0, heading=1.6)
        assert np.array_equal(res.image, render_baseline(store, spec, -423.5, 1430.0, 1.6))
        quads = np.stack([res.image[spec.channels.index(n)] for n in QUADRANT_CHANNELS])
        plain = Rasteriser(store, S(rotate=rotate)).render(-423.5, 1430.0, heading=1.6).image[CL]
        assert np.array_equal(quads.max(axis=0) > 0, plain > 0)
