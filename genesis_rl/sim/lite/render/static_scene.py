"""The static scene of a lite map as numpy meshes, cut into level-of-detail tiles; no GL involved.

What the camera sees besides the vehicles: terrain, roads and junctions, lane markings, kerbs and
sidewalks, puddles, buildings, trees, traffic-light poles, and the traffic-light lamps (whose colours the
renderer changes per frame). :func:`build_static_scene` returns it laid out for culling; the Panda3D shell
(``panda_renderer.py``) only uploads it, so the geometry can be built and tested without a GL context.

The scene is cut into ground tiles so that Panda3D's cull skips those outside the frustum, and each tile has
two levels of detail: beyond STATIC_LOD_M the lane markings and poles (under a pixel wide there) are left out
and trees are drawn as a few triangles. Tiles are grouped in blocks of STATIC_BLOCK_TILES x
STATIC_BLOCK_TILES; a block far enough for all its tiles to be at the far level is drawn as one mesh, because
llvmpipe spends some 15 us on each draw call. On the highway map the full-detail scene was 214k triangles,
most of them far away, in one mesh, and llvmpipe spent 12 of 13 ms per frame transforming them.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from genesis_rl.sim.lite.maps.lane_graph import LANE_WIDTH, RoadMap
from genesis_rl.sim.lite.render import labels as L
from genesis_rl.sim.lite.render.ground import FAR_GROUND_STEP, GroundGrid, cell_triangles, coarse_blocks, ground_grid
from genesis_rl.sim.lite.render.mesh import Mesh, box
from genesis_rl.sim.lite.render.polyline import simplify_indices

#: edge of the square tiles the static scene is cut into for frustum culling (metres)
STATIC_TILE_M = 64.0
#: distance from the camera to a tile's centre beyond which the tile is drawn at its far level of detail
STATIC_LOD_M = 180.0
#: tiles per side of the blocks whose far level is drawn as one mesh
STATIC_BLOCK_TILES = 4
#: the kinds of surface a tile keeps at its far level (trees there are their few-triangle twins)
FAR_KINDS = ("ground", "roads", "sidewalks", "puddles", "buildings")

#: a mesh of one kind of surface ("ground", "roads", "markings", ...) within a tile or block
Part = tuple[str, Mesh]


@dataclass(frozen=True)
class Tile:
    """One STATIC_TILE_M square: its centre on the terrain (the LOD reference) and its two levels."""

    centre: tuple[float, float, float]
    near: list[Part]
    far: list[Part]


@dataclass(frozen=True)
class Block:
    """STATIC_BLOCK_TILES x STATIC_BLOCK_TILES tiles; ``merged`` is their far level as one mesh per kind,
    the ground on the coarse grid (see ``ground.py``)."""

    centre: tuple[float, float, float]
    merged: list[Part]


@dataclass(frozen=True)
class Lamps:
    """The traffic-light lamps: one upward-facing quad each (``quads`` (n, 4, 3), counter-clockwise), and
    which junction, signal group and lamp (0 red, 1 yellow, 2 green) each one is."""

    quads: np.ndarray
    keys: list[tuple[int, int, int]]


@dataclass(frozen=True)
class SceneMeshes:
    """The whole map's static meshes before tiling: ``near`` every kind at full detail, ``far`` the kinds
    kept far away (FAR_KINDS, trees as their few-triangle twins), the terrain grid they were made from."""

    near: list[Part]
    far: list[Part]
    grid: GroundGrid
    lamps: Lamps


@dataclass(frozen=True)
class StaticScene:
    """The static scene laid out for culling: blocks and tiles keyed by (x, y) index on their grid, in
    sorted key order; a tile (kx, ky) lies in block (kx // STATIC_BLOCK_TILES, ky // STATIC_BLOCK_TILES)."""

    tiles: dict[tuple[int, int], Tile]
    blocks: dict[tuple[int, int], Block]
    tile_size_m: float
    block_tiles: int
    #: a tile is drawn at its near level while the camera is within this distance of its centre
    tile_lod_m: float
    #: a block's tiles are drawn (each at its own level) within this distance of the block's centre; beyond
    #: it the merged block, which is only right where each of its tiles is at least tile_lod_m away
    block_lod_m: float
    lamps: Lamps

    @property
    def block_size_m(self) -> float:
        return self.tile_size_m * self.block_tiles

    def block_of(self, tile: tuple[int, int]) -> tuple[int, int]:
        """The key of the block that holds tile ``tile``."""
        return tile[0] // self.block_tiles, tile[1] // self.block_tiles


def _normals2(poly: np.ndarray) -> np.ndarray:
    t = np.gradient(poly, axis=0)
    t /= np.maximum(1e-9, np.linalg.norm(t, axis=1, keepdims=True))
    return np.stack([-t[:, 1], t[:, 0]], axis=1)  # left normal


def _elev(rm: RoadMap, xy: np.ndarray) -> np.ndarray:
    return np.asarray(rm.elevation(xy[:, 0], xy[:, 1]), np.float64) * np.ones(len(xy))


def _offset_line(rm: RoadMap, cl: np.ndarray, nrm: np.ndarray, off: float, dz: float) -> np.ndarray:
    xy = cl + nrm * off
    return np.column_stack([xy, _elev(rm, xy) + dz])


def _line(
    m: Mesh,
    rm: RoadMap,
    cl: np.ndarray,
    nv: np.ndarray,
    off: float,
    w: float,
    col: ArrayLike,
    dash: tuple[float, float] | None,
    s: np.ndarray,
    keep: np.ndarray,
) -> None:
    """A painted line ``w`` wide at lateral offset ``off``: solid on the road's kept vertices, or dashes
    (``dash`` = (on, period) metres of arc length), each dash simplified on its own so that it keeps
    its exact ends."""
    left = _offset_line(rm, cl, nv, off + w / 2, 0.045)
    right = _offset_line(rm, cl, nv, off - w / 2, 0.045)
    if dash is None:
        m.strip(left[keep], right[keep], col, L.LANE_MARKING)
        return
    on_len, period = dash
    mid = 0.5 * (s[:-1] + s[1:])
    on = np.concatenate([[False], (mid % period) < on_len, [False]])
    starts = np.flatnonzero(on[1:] & ~on[:-1])  # first segment of each dash
    ends = np.flatnonzero(on[:-1] & ~on[1:])  # one past its last segment = its last vertex
    for a, b in zip(starts, ends, strict=True):
        k = a + simplify_indices(np.stack([left[a : b + 1], right[a : b + 1]]))
        m.strip(left[k], right[k], col, L.LANE_MARKING)


def _road_meshes(rm: RoadMap, rng: np.random.Generator) -> tuple[Mesh, Mesh, Mesh, Mesh]:
    """Roads and junctions, markings, sidewalks (urban only) and puddles (drawing from ``rng``)."""
    highway = rm.name == "highway"
    road, mark, side, puddle = Mesh(), Mesh(), Mesh(), Mesh()
    asphalt = (0.28, 0.28, 0.29)
    white, yellow = (0.85, 0.85, 0.82), (0.85, 0.68, 0.12)
    for r in rm.roads:
        cl = np.asarray(r.centerline, np.float64)
        if len(cl) < 2:
            continue
        nv = _normals2(cl)
        hw = r.width / 2
        # the vertices the drawn lines need (the centreline is sampled every 0.5 m for lane keeping);
        # every line between the outermost two stays within tolerance when they and the centre do
        span = hw if highway else hw + 2.5  # to the road's edge, or the sidewalk's
        keep = simplify_indices(np.stack([_offset_line(rm, cl, nv, o, 0.02) for o in (span, 0.0, -span)]))
        road.strip(
            _offset_line(rm, cl, nv, hw, 0.02)[keep],
            _offset_line(rm, cl, nv, -hw, 0.02)[keep],
            asphalt,
            L.ROAD,
        )
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(cl, axis=0), axis=1))])
        for off in (0.12, -0.12):  # double yellow centre line
            _line(mark, rm, cl, nv, off, 0.12, yellow, None, s, keep)
        for k in range(1, r.lanes_each_way):  # dashed white between same-direction lanes
            for sign in (1, -1):
                _line(mark, rm, cl, nv, sign * k * LANE_WIDTH, 0.15, white, (3.0, 9.0), s, keep)
        for sign in (1, -1):  # solid edge lines
            _line(mark, rm, cl, nv, sign * (hw - 0.25), 0.15, white, None, s, keep)
        if not highway:
            for sign in (1, -1):
                inner = _offset_line(rm, cl, nv, sign * hw, 0.15)[keep]
                outer = _offset_line(rm, cl, nv, sign * (hw + 2.5), 0.15)[keep]
                lo = _offset_line(rm, cl, nv, sign * hw, 0.0)[keep]
                if sign > 0:
                    side.strip(outer, inner, (0.56, 0.55, 0.53), L.SIDEWALK)
                    side.strip(inner, lo, (0.45, 0.45, 0.44), L.SIDEWALK)
                else:
                    side.strip(inner, outer, (0.56, 0.55, 0.53), L.SIDEWALK)
                    side.strip(lo, inner, (0.45, 0.45, 0.44), L.SIDEWALK)
        # puddles at deterministic places
        n_p = int(rng.integers(1, 4))
        for _ in range(n_p):
            k = int(rng.integers(0, len(cl)))
            lat = float(rng.uniform(-hw + 1.0, hw - 1.0))
            rad = float(rng.uniform(0.8, 2.2))
            cxy = cl[k] + nv[k] * lat
            ang = np.linspace(0, 2 * math.pi, 10, endpoint=False)
            ell = np.column_stack([cxy[0] + rad * 1.6 * np.cos(ang), cxy[1] + rad * np.sin(ang)])
            pts = np.column_stack([np.vstack([cxy, ell]), _elev(rm, np.vstack([cxy, ell])) + 0.03])
            fan = np.array([[0, 1 + q, 1 + (q + 1) % 10] for q in range(10)])
            puddle.add(pts, (0.0, 0.0, 1.0), (0.22, 0.22, 0.23), fan, L.PUDDLE)
    for jn in rm.junctions:
        c = np.asarray(jn.center, np.float64)
        ang = np.linspace(0, 2 * math.pi, 28, endpoint=False)
        ring = np.column_stack([c[0] + jn.radius * np.cos(ang), c[1] + jn.radius * np.sin(ang)])
        pts = np.vstack([c, ring])
        fan = np.array([[0, 1 + q, 1 + (q + 1) % 28] for q in range(28)])
        road.add(np.column_stack([pts, _elev(rm, pts) + 0.025]), (0.0, 0.0, 1.0), asphalt, fan, L.ROAD)
    return road, mark, side, puddle


def _building_mesh(rm: RoadMap) -> Mesh:
    """Boxes sunk 0.5 m into the terrain, with a dark window band every 3.2 m up each facade."""
    bm = Mesh()
    for b in rm.buildings:
        z0 = float(_elev(rm, np.array([[b.x, b.y]]))[0]) - 0.5
        col = np.asarray(b.color, np.float64)
        box(bm, b.x, b.y, z0, b.yaw, b.width, b.depth, b.height + 0.5, col, L.BUILDING)
        win = col * 0.35 + np.array([0.02, 0.03, 0.05])
        c, s_ = math.cos(b.yaw), math.sin(b.yaw)
        ex, ey = np.array([c, s_, 0.0]), np.array([-s_, c, 0.0])
        for fx, fy, half_len, half_out in (
            (ex, ey, b.width, b.depth),
            (ey, -ex, b.depth, b.width),
            (-ex, -ey, b.width, b.depth),
            (-ey, ex, b.depth, b.width),
        ):
            # facade with outward normal fy, running along fx
            centre = np.array([b.x, b.y, z0 + 0.5]) + fy * (half_out / 2 + 0.05)
            u = fx * max(0.0, half_len / 2 - 0.8)
            zz0 = 1.6
            while zz0 + 1.3 < b.height - 0.6:
                lo, hi = np.array([0, 0, zz0]), np.array([0, 0, zz0 + 1.3])
                bm.quad(centre + u + lo, centre - u + lo, centre - u + hi, centre + u + hi, win, L.BUILDING)
                zz0 += 3.2
    return bm


def _tree(
    m: Mesh,
    m_far: Mesh,
    x: float,
    y: float,
    z: float,
    height: float,
    kind: str,
    rng: np.random.Generator,
) -> None:
    """A tree into ``m`` and its far twin (a 3-sided cone, no trunk, same colour) into ``m_far``."""
    trunk_h = height * (0.25 if kind == "pine" else 0.4)
    box(m, x, y, z, 0.0, 0.3, 0.3, trunk_h + 0.3, (0.30, 0.22, 0.14), L.VEGETATION, top=False)
    tint = 0.85 + 0.3 * float(rng.random())
    sides = 6
    ang = np.linspace(0, 2 * math.pi, sides, endpoint=False) + float(rng.random())
    if kind == "pine":
        col = np.array([0.10, 0.24, 0.12]) * tint
        rad = height * 0.22
        for lo, hi, rr in (
            (trunk_h, height, rad),
            (trunk_h + 0.35 * (height - trunk_h), height, rad * 0.7),
        ):
            ring = np.column_stack([x + rr * np.cos(ang), y + rr * np.sin(ang), np.full(sides, z + lo)])
            apex = np.array([[x, y, z + hi]])
            pts = np.vstack([ring, apex])
            nrm = np.column_stack([np.cos(ang), np.sin(ang), np.full(sides, 0.5)])
            nrm = np.vstack([nrm, [[0, 0, 1.0]]])
            nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
            tri = np.array([[q, (q + 1) % sides, sides] for q in range(sides)])
            m.add(pts, nrm, col, tri, L.VEGETATION)
        far_lo, far_rad = z + 0.3 * trunk_h, rad
    else:
        col = np.array([0.20, 0.36, 0.14]) * tint
        rad = height * 0.3
        cz = z + trunk_h + rad * 0.8
        lat = np.array([-0.6, 0.0, 0.6]) * math.pi / 2
        rings = [
            np.column_stack([np.cos(a) * np.cos(ang), np.cos(a) * np.sin(ang), np.full(sides, math.sin(a))])
            for a in lat
        ]
        unit = np.vstack([[[0, 0, -1.0]], *rings, [[0, 0, 1.0]]])
        pts = unit * np.array([rad, rad, rad * 0.85]) + np.array([x, y, cz])
        faces: list[list[int]] = []
        for q in range(sides):
            qn = (q + 1) % sides
            faces.append([0, 1 + qn, 1 + q])
            for rix in range(len(rings) - 1):
                a0, b0 = 1 + rix * sides, 1 + (rix + 1) * sides
                faces.append([a0 + q, a0 + qn, b0 + qn])
                faces.append([a0 + q, b0 + qn, b0 + q])
            top = 1 + len(rings) * sides
            last = 1 + (len(rings) - 1) * sides
            faces.append([last + q, last + qn, top])
        m.add(pts, unit, col, np.array(faces), L.VEGETATION)
        far_lo, far_rad = cz - 0.6 * rad, rad
    a3 = ang[::2]
    ring = np.column_stack([x + far_rad * np.cos(a3), y + far_rad * np.sin(a3), np.full(3, far_lo)])
    nrm = np.vstack([np.column_stack([np.cos(a3), np.sin(a3), np.full(3, 0.5)]), [[0.0, 0.0, 1.0]]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pts = np.vstack([ring, [[x, y, z + height]]])
    m_far.add(pts, nrm, col, np.array([[0, 1, 3], [1, 2, 3], [2, 0, 3]]), L.VEGETATION)


def _tree_meshes(rm: RoadMap, rng: np.random.Generator) -> tuple[Mesh, Mesh]:
    """Every tree at full detail, and a few-triangle twin of each for the far level of detail."""
    tm, tm_far = Mesh(), Mesh()
    if rm.trees:
        txy = np.array([[t.x, t.y] for t in rm.trees])
        tz = _elev(rm, txy) - (0.3 if rm.name == "highway" else 0.0)
        for t, z in zip(rm.trees, tz, strict=True):
            _tree(tm, tm_far, t.x, t.y, float(z), t.height, t.kind, rng)
    return tm, tm_far


def _signals(rm: RoadMap) -> tuple[Mesh, Lamps]:
    """Traffic-light poles and housings (static), and their lamps (recoloured per frame by the renderer)."""
    pm = Mesh()
    keys: list[tuple[int, int, int]] = []  # (junction, group, lamp 0 red 1 yellow 2 green)
    quads: list[np.ndarray] = []
    for jn in rm.junctions:
        for xy, heading, group in jn.signal_heads:
            x, y = float(xy[0]), float(xy[1])
            z = float(_elev(rm, np.array([[x, y]]))[0])
            box(pm, x, y, z, heading, 0.16, 0.16, 4.6, (0.22, 0.23, 0.24), L.POLE)
            box(pm, x, y, z + 3.2, heading, 0.32, 0.36, 1.1, (0.08, 0.08, 0.07), L.POLE)
            f = np.array([math.cos(heading), math.sin(heading), 0.0])
            rgt = np.array([math.sin(heading), -math.cos(heading), 0.0])
            for li in range(3):
                cz = z + 4.05 - li * 0.33
                ctr = np.array([x, y, cz]) + f * 0.17
                h = 0.12
                quads.append(
                    np.array(
                        [
                            ctr - rgt * h - [0, 0, h],
                            ctr + rgt * h - [0, 0, h],
                            ctr + rgt * h + [0, 0, h],
                            ctr - rgt * h + [0, 0, h],
                        ]
                    )
                )
                keys.append((jn.id, int(group), li))
    return pm, Lamps(np.array(quads, np.float64).reshape(-1, 4, 3), keys)


def _centre(rm: RoadMap, kx: int, ky: int, size: float) -> tuple[float, float, float]:
    cx, cy = (kx + 0.5) * size, (ky + 0.5) * size
    return cx, cy, float(_elev(rm, np.array([[cx, cy]]))[0])


def _reach(tile: tuple[float, float, float], block: tuple[float, float, float]) -> float:
    """Distance between two centres as the GL shell's float32 points give it (the LOD switch uses it)."""
    d = np.array(tile, np.float32) - np.array(block, np.float32)
    return float(np.sqrt(np.float32(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])))


def layout(rm: RoadMap, meshes: SceneMeshes) -> StaticScene:
    """Cut the near and far meshes into tiles, merge each block's far level, and set the LOD distances."""
    near, far = meshes.near, meshes.far
    block_m = STATIC_TILE_M * STATIC_BLOCK_TILES
    levels: dict[tuple[int, int], tuple[list[Part], list[Part]]] = {}
    for level, group in enumerate((near, far)):
        for name, mesh in group:
            for key, part in mesh.tiles(STATIC_TILE_M).items():
                levels.setdefault(key, ([], []))[level].append((name, part))
    # merged blocks draw the ground on a coarser grid (see ground.py)
    merged: dict[tuple[int, int], list[Part]] = {}
    for key, (gpos, gnrm, gcol, gtri) in coarse_blocks(meshes.grid, FAR_GROUND_STEP, block_m).items():
        part = Mesh()
        part.add(gpos, gnrm, gcol, gtri, L.GROUND)
        merged.setdefault(key, []).append(("ground", part))
    for name, mesh in far:
        if name == "ground":
            continue
        for key, part in mesh.tiles(block_m).items():
            merged.setdefault(key, []).append((name, part))

    block_keys = set(merged) | {(kx // STATIC_BLOCK_TILES, ky // STATIC_BLOCK_TILES) for kx, ky in levels}
    blocks = {k: Block(_centre(rm, *k, block_m), merged.get(k, [])) for k in sorted(block_keys)}
    tiles = {k: Tile(_centre(rm, *k, STATIC_TILE_M), *levels[k]) for k in sorted(levels)}
    reach = 0.0  # farthest tile centre from its block's centre, in 3D
    for (kx, ky), tile in tiles.items():
        reach = max(reach, _reach(tile.centre, blocks[(kx // STATIC_BLOCK_TILES, ky // STATIC_BLOCK_TILES)].centre))
    # a block merges only where each of its tiles is at least STATIC_LOD_M away (triangle inequality)
    return StaticScene(
        tiles, blocks, STATIC_TILE_M, STATIC_BLOCK_TILES, STATIC_LOD_M, STATIC_LOD_M + reach + 1.0, meshes.lamps
    )


def static_meshes(rm: RoadMap) -> SceneMeshes:
    """The map's static scene as whole-map meshes, deterministic per map (its random details are seeded by
    the map's name)."""
    rng = np.random.default_rng(zlib.crc32(rm.name.encode()))
    grid = ground_grid(rm, rng, 0.3 if rm.name == "highway" else 0.05)
    ground = Mesh()
    flat = (grid.pos.reshape(-1, 3), grid.nrm.reshape(-1, 3), grid.col.reshape(-1, 3))
    ground.add(*flat, cell_triangles(grid.shape[1], grid.shape[0]), L.GROUND)
    road, mark, side, puddle = _road_meshes(rm, rng)
    buildings = _building_mesh(rm)
    trees, trees_far = _tree_meshes(rm, rng)
    poles, lamps = _signals(rm)
    near: list[Part] = [
        ("ground", ground), ("roads", road), ("markings", mark), ("sidewalks", side), ("puddles", puddle),
        ("buildings", buildings), ("trees", trees), ("poles", poles),
    ]
    far = [(n, m) for n, m in near if n in FAR_KINDS] + [("trees", trees_far)]
    return SceneMeshes(near, far, grid, lamps)


def build_static_scene(rm: RoadMap) -> StaticScene:
    """The map's static scene, cut into tiles and blocks (see the module's docstring)."""
    return layout(rm, static_meshes(rm))
