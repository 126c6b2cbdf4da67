"""The lite renderer's static scene as numpy meshes, checked without GL: counts, surfaces, tiling, LOD."""

from __future__ import annotations

import math

import numpy as np
import pytest

from genesis_rl.sim.lite.maps import load_map
from genesis_rl.sim.lite.maps.lane_graph import LANE_WIDTH
from genesis_rl.sim.lite.render import labels as L
from genesis_rl.sim.lite.render.mesh import Mesh
from genesis_rl.sim.lite.render.static_scene import (
    FAR_KINDS,
    STATIC_BLOCK_TILES,
    STATIC_LOD_M,
    STATIC_TILE_M,
    build_static_scene,
    layout,
    static_meshes,
)

MAPS = ("urban", "highway")


@pytest.fixture(scope="module")
def built() -> dict:
    """Per map: (road map, whole-map meshes, tiled scene); the highway map takes some seconds to build."""
    out = {}
    for name in MAPS:
        rm = load_map(name)
        meshes = static_meshes(rm)
        out[name] = (rm, meshes, layout(rm, meshes))
    return out


def _count(parts: list[tuple[str, Mesh]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for kind, m in parts:
        out[kind] = out.get(kind, 0) + m.triangle_count
    return out


def _level_counts(scene, level: str) -> dict[str, int]:
    return _count([p for t in scene.tiles.values() for p in getattr(t, level)])


def _rows(meshes: list[Mesh]) -> np.ndarray:
    """One row per triangle (its three vertices' position, normal and colour), sorted: a multiset of triangles."""
    rows = []
    for m in meshes:
        pos, nrm, col, tri = m.arrays()
        rows.append(np.concatenate([pos[tri].reshape(-1, 9), nrm[tri].reshape(-1, 9),
                                    col[tri].reshape(-1, 12).astype(np.float32)], axis=1))
    a = np.concatenate(rows) if rows else np.zeros((0, 30), np.float32)
    return a[np.lexsort(a.T[::-1])]


def _areas(pos: np.ndarray, tri: np.ndarray) -> np.ndarray:
    p = pos[tri].astype(np.float64)
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def _ground_area_2d(m: Mesh) -> float:
    pos, _, _, tri = m.arrays()
    p = pos[tri].astype(np.float64)
    a, b, c = p[:, 0, :2], p[:, 1, :2], p[:, 2, :2]
    return float(0.5 * np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]).sum())


def _left_of(p0: np.ndarray, p1: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Positive where ``x`` lies left of the line p0 -> p1 (2D cross product), broadcast."""
    return (p1 - p0)[..., 0] * (x - p0)[..., 1] - (p1 - p0)[..., 1] * (x - p0)[..., 0]


# --- what the scene holds -------------------------------------------------------------------------------
@pytest.mark.parametrize("name", MAPS)
def test_triangle_counts_follow_the_map(built, name) -> None:
    """Each kind's triangle count is what the map's content makes (per tree, pole, puddle, terrain cell)."""
    rm, meshes, scene = built[name]
    near, far = _count(meshes.near), _count(meshes.far)
    ny, nx = meshes.grid.shape
    assert near["ground"] == 2 * (nx - 1) * (ny - 1)
    # a pine is a trunk (4 sides) and two 6-sided cones, a broadleaf a trunk and a 6 x 3-ring ball; far, 3 each
    assert near["trees"] == sum(20 if t.kind == "pine" else 44 for t in rm.trees) > 0
    assert far["trees"] == 3 * len(rm.trees)
    heads = sum(len(j.signal_heads) for j in rm.junctions)
    assert heads > 0
    assert near["poles"] == 20 * heads  # pole and housing, 5 faces each
    assert len(scene.lamps.keys) == 3 * heads and scene.lamps.quads.shape == (3 * heads, 4, 3)
    roads = [r for r in rm.roads if len(r.centerline) >= 2]
    assert 10 * len(roads) <= near["puddles"] <= 30 * len(roads)  # 1 to 3 ten-triangle puddles per road
    assert near["buildings"] >= 10 * len(rm.buildings)
    assert near["roads"] >= 28 * len(rm.junctions) + 2 * len(roads)
    assert ("sidewalks" in near and near["sidewalks"] > 0) == (name == "urban")  # no kerbs on the highway
    # far away: no markings or poles, the same ground, roads and buildings
    assert "markings" not in far and "poles" not in far
    for kind in FAR_KINDS:
        assert far.get(kind, 0) == near.get(kind, 0)


@pytest.mark.parametrize(("name", "near_total", "far_max", "merged_max"), [
    ("urban", (20_000, 25_000), 17_000, 12_000),
    ("highway", (100_000, 125_000), 38_000, 21_000),
])
def test_triangle_budget(built, name, near_total, far_max, merged_max) -> None:
    """What llvmpipe has to transform: the far level and the merged blocks are far lighter than full detail
    (the highway's full detail in one mesh cost 12 of 13 ms per frame)."""
    _, _, scene = built[name]
    near = sum(_level_counts(scene, "near").values())
    far = sum(_level_counts(scene, "far").values())
    merged = sum(sum(_count(b.merged).values()) for b in scene.blocks.values())
    assert near_total[0] <= near <= near_total[1]
    assert far <= far_max and merged <= merged_max
    if name == "highway":  # mostly trees: the far level is under a third of full detail
        assert far < near / 3


@pytest.mark.parametrize("name", MAPS)
def test_no_degenerate_triangles(built, name) -> None:
    """Every triangle at every level has three distinct in-range vertices and some area (1 cm2 at least)."""
    _, _, scene = built[name]
    parts = [p for t in scene.tiles.values() for p in (*t.near, *t.far)]
    parts += [p for b in scene.blocks.values() for p in b.merged]
    for kind, m in parts:
        pos, nrm, col, tri = m.arrays()
        assert tri.min() >= 0 and tri.max() < len(pos) == m.n
        assert np.all((tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])), kind
        assert _areas(pos, tri).min() > 1e-4, kind
        assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-5), kind
        assert np.isfinite(pos).all()


@pytest.mark.parametrize("name", MAPS)
def test_surfaces_lie_on_the_terrain(built, name) -> None:
    """Roads 2 cm (junctions 2.5 cm) above the terrain, markings 4.5, puddles 3, the ground under the road;
    all of them face up, with their label in the alpha channel."""
    rm, meshes, _ = built[name]
    below = 0.3 if name == "highway" else 0.05
    lift = {"roads": (0.02, 0.025), "markings": (0.045,), "puddles": (0.03,), "ground": (-below,)}
    label = {"roads": L.ROAD, "markings": L.LANE_MARKING, "puddles": L.PUDDLE, "ground": L.GROUND}
    for kind, m in meshes.near:
        if kind not in lift:
            continue
        pos, _, col, tri = m.arrays()
        dz = pos[:, 2].astype(np.float64) - np.asarray(rm.elevation(pos[:, 0], pos[:, 1]), np.float64)
        off = np.min([np.abs(dz - h) for h in lift[kind]], axis=0)
        assert off.max() < 1e-3, kind
        assert (col[:, 3] == label[kind]).all()
        p = pos[tri].astype(np.float64)
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        assert (n[:, 2] / np.linalg.norm(n, axis=1)).min() > 0.9, kind  # counter-clockwise from above


@pytest.mark.parametrize("name", MAPS)
def test_markings_lie_on_lanes(built, name) -> None:
    """Every painted line is within half a lane of a lane's centre (none off the road, none on the grass)."""
    rm, meshes, _ = built[name]
    pos, _, _, _ = dict(meshes.near)["markings"].arrays()
    pts = pos[::5, :2].astype(np.float64)
    d = [math.dist(p, rm.points[rm.nearest_lane_point(*p), :2]) for p in pts]
    assert max(d) < LANE_WIDTH / 2 + 0.3  # lane samples every 0.5 m
    assert len(pts) > 500


# --- tiles and levels of detail -----------------------------------------------------------------------------
@pytest.mark.parametrize("name", MAPS)
def test_tiles_hold_every_triangle_once(built, name) -> None:
    """Per kind and level, the tiles together hold exactly the whole-map mesh's triangles (none lost, none
    twice), each in the tile its centroid lies in; each block merges exactly its tiles' far level."""
    _, meshes, scene = built[name]
    for level, whole in (("near", meshes.near), ("far", meshes.far)):
        for kind, m in whole:
            parts = [p for t in scene.tiles.values() for k, p in getattr(t, level) if k == kind]
            assert np.array_equal(_rows([m]), _rows(parts)), (level, kind)
    for key, t in scene.tiles.items():
        for _, p in (*t.near, *t.far):
            pos, _, _, tri = p.arrays()
            assert np.all(np.floor(pos[tri].mean(axis=1)[:, :2] / STATIC_TILE_M) == key)
        assert scene.block_of(key) in scene.blocks
    for bkey, b in scene.blocks.items():
        mine = [t for k, t in scene.tiles.items() if scene.block_of(k) == bkey]
        kinds = {k for k, _ in b.merged if k != "ground"} | {k for t in mine for k, _ in t.far if k != "ground"}
        for kind in kinds:
            merged = [p for k, p in b.merged if k == kind]
            assert np.array_equal(_rows(merged), _rows([p for t in mine for k, p in t.far if k == kind]))


@pytest.mark.parametrize("name", MAPS)
def test_ground_covers_the_map_without_gaps(built, name) -> None:
    """The tiles' ground adds up to the map's area exactly (no gap, no overlap); each merged block's coarse
    ground covers all the ground its tiles cover (no sky through a seam), overlapping its neighbours little."""
    rm, _, scene = built[name]
    xmin, ymin, xmax, ymax = rm.bounds
    area = (xmax - xmin) * (ymax - ymin)
    tiles = sum(_ground_area_2d(p) for t in scene.tiles.values() for k, p in t.near if k == "ground")
    assert tiles == pytest.approx(area, rel=1e-6)
    coarse = 0.0
    for bkey, b in scene.blocks.items():
        ground = [p for k, p in b.merged if k == "ground"]
        assert len(ground) == 1
        coarse += _ground_area_2d(ground[0])
        cpos, _, _, ctri = ground[0].arrays()
        tri2 = cpos[ctri][:, :, :2].astype(np.float64)  # (M, 3, 2)
        fine = [p for k, t in scene.tiles.items() if scene.block_of(k) == bkey for kk, p in t.near if kk == "ground"]
        for p in fine:
            pos, _, _, tri = p.arrays()
            c = pos[tri].mean(axis=1)[:, :2].astype(np.float64)  # (N, 2) fine centroids
            a, b_, cc, x = tri2[None, :, 0], tri2[None, :, 1], tri2[None, :, 2], c[:, None]
            inside = (_left_of(a, b_, x) >= -1e-6) & (_left_of(b_, cc, x) >= -1e-6) & (_left_of(cc, a, x) >= -1e-6)
            assert inside.any(axis=1).all(), bkey
    assert area <= coarse <= 1.15 * area


@pytest.mark.parametrize("name", MAPS)
def test_lod_distances(built, name) -> None:
    """Tile and block centres sit on the terrain at their squares' centres; a block merges only where every
    one of its tiles is at its far level already (block distance >= tile LOD distance + tile offset)."""
    rm, _, scene = built[name]
    assert scene.tile_size_m == STATIC_TILE_M and scene.block_size_m == STATIC_TILE_M * STATIC_BLOCK_TILES
    assert scene.tile_lod_m == STATIC_LOD_M
    for keyed, size in ((scene.tiles, scene.tile_size_m), (scene.blocks, scene.block_size_m)):
        assert list(keyed) == sorted(keyed)
        for (kx, ky), item in keyed.items():
            cx, cy, cz = item.centre
            assert (cx, cy) == ((kx + 0.5) * size, (ky + 0.5) * size)
            assert cz == pytest.approx(float(np.asarray(rm.elevation(np.array([cx]), np.array([cy]))).ravel()[0]))
    reach = max(math.dist(t.centre, scene.blocks[scene.block_of(k)].centre) for k, t in scene.tiles.items())
    assert scene.block_lod_m >= scene.tile_lod_m + reach
    assert scene.block_lod_m < scene.tile_lod_m + reach + 1.01
    assert reach >= math.hypot(1.5, 1.5) * STATIC_TILE_M  # a corner tile's centre from its block's


def test_lamps_sit_on_their_heads(built) -> None:
    """Three 24 cm lamps per signal head, red above yellow above green, 17 cm in front of the pole."""
    rm, _, scene = built["urban"]
    quads, keys = scene.lamps.quads, scene.lamps.keys
    heads = [(j.id, xy, heading) for j in rm.junctions for xy, heading, _ in j.signal_heads]
    assert [k[2] for k in keys] == [0, 1, 2] * len(heads)
    assert np.allclose(np.linalg.norm(quads[:, 1] - quads[:, 0], axis=1), 0.24)
    assert np.allclose(quads[:, 2, 2] - quads[:, 1, 2], 0.24)
    centre = quads.mean(axis=1).reshape(len(heads), 3, 3)
    assert np.all(np.diff(centre[:, :, 2], axis=1) < 0)  # red on top
    for (jid, xy, heading), c, k in zip(heads, centre, keys[::3], strict=True):
        assert k[0] == jid
        ahead = (c[:, :2] - np.asarray(xy)) @ np.array([math.cos(heading), math.sin(heading)])
        assert np.allclose(ahead, 0.17)


def test_build_is_deterministic() -> None:
    """Two builds of a map give the same bytes (the random details are seeded by the map's name)."""
    rm = load_map("urban")
    a, b = build_static_scene(rm), build_static_scene(rm)
    assert list(a.tiles) == list(b.tiles) and list(a.blocks) == list(b.blocks)
    for key in a.tiles:
        for (ka, pa), (kb, pb) in zip(a.tiles[key].near, b.tiles[key].near, strict=True):
            assert ka == kb
            assert all(np.array_equal(x, y) for x, y in zip(pa.arrays(), pb.arrays(), strict=True))
    assert a.block_lod_m == b.block_lod_m and np.array_equal(a.lamps.quads, b.lamps.quads)


def test_static_tiles_keep_every_triangle() -> None:
    """Cutting the static scene into culling tiles neither drops nor duplicates a triangle or a vertex."""
    rng = np.random.default_rng(0)
    m = Mesh()
    for _ in range(50):
        p = rng.uniform(-200, 200, (3, 3))
        m.add(p, (0.0, 0.0, 1.0), rng.random(3), np.array([0, 1, 2]), 7)
    tiles = m.tiles(64.0)
    assert len(tiles) > 4
    tri_in = np.concatenate(m.pos)[np.concatenate(m.idx).reshape(-1, 3)]
    tri_out = np.concatenate([t.pos[0][t.idx[0].reshape(-1, 3)] for t in tiles.values()])
    key = lambda a: sorted(map(tuple, a.reshape(len(a), -1).round(4)))  # noqa: E731
    assert key(tri_in) == key(tri_out)
    for (kx, ky), t in tiles.items():  # each triangle's centroid lies in its tile
        c = t.pos[0][t.idx[0].reshape(-1, 3)].mean(axis=1)[:, :2]
        assert np.all(np.floor(c / 64.0) == (kx, ky))
