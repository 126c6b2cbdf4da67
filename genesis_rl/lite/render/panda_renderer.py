"""Offscreen Panda3D renderer of the lite backend: RGB, metric depth, per-pixel labels and GT boxes.

One geometry pass draws the static scene (built once, flattened per kind) and the vehicles; every surface
is opaque with alpha = label / 255 (see ``labels.py``), so the framebuffer's alpha channel is the label
image. The colour then goes through :class:`WeatherCompositor` (fog, rain, wet roads, sky, noise).

No ShowBase: a module-level headless GL pipe and the global GraphicsEngine are shared by every renderer;
each renderer owns its own offscreen buffer, scene root and camera, so several can live in one process.
"""

from __future__ import annotations

import math
import zlib

import cv2
import numpy as np
from panda3d.core import (
    AmbientLight,
    DirectionalLight,
    FrameBufferProperties,
    Geom,
    GeomNode,
    GeomTriangles,
    GeomVertexData,
    GeomVertexFormat,
    GraphicsEngine,
    GraphicsOutput,
    GraphicsPipe,
    GraphicsPipeSelection,
    LODNode,
    NodePath,
    PerspectiveLens,
    Point3,
    Spotlight,
    Texture,
    WindowProperties,
    loadPrcFileData,
)

from genesis_rl.knobs import Weather
from genesis_rl.lite.maps.lane_graph import LANE_WIDTH, RoadMap
from genesis_rl.lite.render import labels as L
from genesis_rl.lite.render.ground import FAR_GROUND_STEP, cell_triangles, coarse_blocks, ground_grid
from genesis_rl.lite.render.lighting import lighting_for
from genesis_rl.lite.render.polyline import simplify_indices
from genesis_rl.lite.render.vehicle_models import VehicleModel, build_vehicle_model
from genesis_rl.lite.render.weather_effects import WeatherCompositor
from genesis_rl.sim.interface import CameraConfig, GroundTruthBox

NEAR = 0.3
MAX_BOX_RANGE = 150.0
MIN_BOX_PIXELS = 12
#: edge of the square tiles the static scene is cut into for frustum culling (metres)
STATIC_TILE_M = 64.0
#: distance from the camera to a tile's centre beyond which the tile is drawn at its far level of detail
STATIC_LOD_M = 180.0
#: tiles per side of the blocks whose far level is drawn as one mesh
STATIC_BLOCK_TILES = 4
#: share of a vehicle's projected 3D-box rectangle that its silhouette covers (for visible_fraction)
_SILHOUETTE_FILL = 0.72

_FORMAT = GeomVertexFormat.get_v3n3c4()
_RECORD = np.dtype([("pos", "<f4", 3), ("nrm", "<f4", 3), ("col", "u1", 4)])

_PIPE: GraphicsPipe | None = None


_CORNER_A = np.array([-1, -1, -1, -1, 1, 1, 1, 1], np.float64)[:, None]  # along the vehicle's length
_CORNER_B = np.array([-1, -1, 1, 1, -1, -1, 1, 1], np.float64)[:, None]  # along its width


def _camera_axes(cyaw: float, cpitch: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The camera's forward, right and up unit vectors in the world (yaw CCW from +x, pitch up)."""
    cy_, sy_ = math.cos(cyaw), math.sin(cyaw)
    cp, sp = math.cos(cpitch), math.sin(cpitch)
    fwd = np.array([cp * cy_, cp * sy_, sp])
    right = np.array([sy_, -cy_, 0.0])
    up = np.array([-sp * cy_, -sp * sy_, cp])
    return fwd, right, up


def gl_pipe_created() -> bool:
    """Whether this process has created the renderer's OpenGL pipe, and so loaded the GL driver (Mesa)."""
    return _PIPE is not None


def _pipe() -> GraphicsPipe:
    global _PIPE
    if _PIPE is None:
        loadPrcFileData(
            "genesis-lite-renderer",
            "window-type offscreen\nload-display p3headlessgl\naudio-library-name null\n"
            "framebuffer-multisample 0\nmulti-samples 0\nsync-video 0\nframebuffer-srgb 0\n"
            "notify-level-display error\nnotify-level-glgsg error\n",
        )
        sel = GraphicsPipeSelection.get_global_ptr()
        pipe = sel.make_module_pipe("p3headlessgl")
        if pipe is None:
            pipe = sel.make_default_pipe()
        if pipe is None:
            raise RuntimeError("no Panda3D graphics pipe (p3headlessgl) available for offscreen rendering")
        _PIPE = pipe
    return _PIPE


# --- mesh building ------------------------------------------------------------------------------------
class _Mesh:
    """Accumulates indexed triangles (numpy chunks) with per-vertex colour; alpha = label."""

    def __init__(self) -> None:
        self.pos: list[np.ndarray] = []
        self.nrm: list[np.ndarray] = []
        self.col: list[np.ndarray] = []
        self.idx: list[np.ndarray] = []
        self.n = 0

    def add(self, pos: np.ndarray, nrm: np.ndarray, col: np.ndarray, idx: np.ndarray, label: int) -> None:
        pos = np.asarray(pos, np.float32).reshape(-1, 3)
        k = len(pos)
        nrm = np.broadcast_to(np.asarray(nrm, np.float32), (k, 3))
        rgb = np.broadcast_to(np.asarray(col, np.float64), (k, 3))
        c = np.empty((k, 4), np.uint8)
        c[:, :3] = np.clip(np.rint(rgb * 255.0), 0, 255)
        c[:, 3] = label
        self.pos.append(pos)
        self.nrm.append(np.array(nrm))
        self.col.append(c)
        self.idx.append(np.asarray(idx, np.int64).reshape(-1) + self.n)
        self.n += k

    def quad(self, a, b, c, d, col, label: int) -> None:  # noqa: ANN001 - counter-clockwise seen from outside
        p = np.array([a, b, c, d], np.float64)
        nrm = np.cross(p[1] - p[0], p[2] - p[0])
        nrm /= max(1e-9, float(np.linalg.norm(nrm)))
        self.add(p, nrm, col, np.array([0, 1, 2, 0, 2, 3]), label)

    def strip(self, left: np.ndarray, right: np.ndarray, col, label: int) -> None:  # noqa: ANN001
        """Quads between two (N, 3) polylines, facing up (left is to the left of the direction of travel)."""
        n = len(left)
        if n < 2:
            return
        pos = np.concatenate([right, left])
        i = np.arange(n - 1)
        tri = np.stack([i, i + 1, n + i + 1, i, n + i + 1, n + i], axis=1)
        self.add(pos, (0.0, 0.0, 1.0), col, tri, label)

    def tiles(self, size: float) -> dict[tuple[int, int], _Mesh]:
        """Split into square ground tiles of ``size`` metres by triangle centroid, so that the renderer can
        cull what the camera does not see (one flattened mesh for a whole map made llvmpipe transform
        every tree on the map each frame). Triangle order within a tile is kept."""
        if not self.n:
            return {}
        pos, nrm, col = np.concatenate(self.pos), np.concatenate(self.nrm), np.concatenate(self.col)
        tri = np.concatenate(self.idx).reshape(-1, 3)
        key = np.floor(pos[tri].mean(axis=1)[:, :2] / size).astype(np.int64)
        out: dict[tuple[int, int], _Mesh] = {}
        for kx, ky in np.unique(key, axis=0):
            t = tri[(key[:, 0] == kx) & (key[:, 1] == ky)]
            used, local = np.unique(t.ravel(), return_inverse=True)
            m = _Mesh()
            m.pos, m.nrm, m.col = [pos[used]], [nrm[used]], [col[used]]
            m.idx = [local.astype(np.int64)]
            m.n = len(used)
            out[(int(kx), int(ky))] = m
        return out

    def node(self, name: str) -> GeomNode | None:
        if not self.n:
            return None
        rec = np.empty(self.n, _RECORD)
        rec["pos"] = np.concatenate(self.pos)
        rec["nrm"] = np.concatenate(self.nrm)
        rec["col"] = np.concatenate(self.col)
        vdata = GeomVertexData(name, _FORMAT, Geom.UH_static)
        vdata.unclean_set_num_rows(self.n)
        memoryview(vdata.modify_array(0)).cast("B")[:] = rec.tobytes()
        prim = GeomTriangles(Geom.UH_static)
        prim.set_index_type(Geom.NT_uint32)
        idx = np.concatenate(self.idx).astype(np.uint32)
        handle = prim.modify_vertices()
        handle.unclean_set_num_rows(len(idx))
        memoryview(handle).cast("B")[:] = idx.tobytes()
        geom = Geom(vdata)
        geom.add_primitive(prim)
        node = GeomNode(name)
        node.add_geom(geom)
        return node


def _box(
    m: _Mesh,
    cx: float,
    cy: float,
    z0: float,
    yaw: float,
    w: float,
    d: float,
    h: float,
    col,  # noqa: ANN001
    label: int,
    top: bool = True,
) -> None:
    """Box with footprint w (along yaw) x d, from z0 to z0 + h."""
    c, s = math.cos(yaw), math.sin(yaw)
    ax = np.array([c, s, 0.0]) * w / 2
    ay = np.array([-s, c, 0.0]) * d / 2
    base = np.array([cx, cy, z0])
    up = np.array([0.0, 0.0, h])
    corners = [base + ax + ay, base - ax + ay, base - ax - ay, base + ax - ay]  # counter-clockwise
    col = np.asarray(col, np.float64)
    for k in range(4):
        p, q = corners[k], corners[(k + 1) % 4]
        shade = 0.85 + 0.15 * ((k % 2) == 0)
        m.quad(q, p, p + up, q + up, col * shade, label)
    if top:
        m.quad(*(cr + up for cr in corners), col * 0.95, label)


def _normals2(poly: np.ndarray) -> np.ndarray:
    t = np.gradient(poly, axis=0)
    t /= np.maximum(1e-9, np.linalg.norm(t, axis=1, keepdims=True))
    return np.stack([-t[:, 1], t[:, 0]], axis=1)  # left normal


def _elev(rm: RoadMap, xy: np.ndarray) -> np.ndarray:
    return np.asarray(rm.elevation(xy[:, 0], xy[:, 1]), np.float64) * np.ones(len(xy))


def _offset_line(rm: RoadMap, cl: np.ndarray, nrm: np.ndarray, off: float, dz: float) -> np.ndarray:
    xy = cl + nrm * off
    return np.column_stack([xy, _elev(rm, xy) + dz])


# --- the renderer -------------------------------------------------------------------------------------
class LiteRenderer:
    """Renders a :class:`RoadMap` and its vehicles from the ego's camera."""

    _count = 0

    def __init__(self, road_map: RoadMap, camera: CameraConfig, seed: int = 0) -> None:
        self.map = road_map
        self.camera = camera
        self.seed = int(seed)
        self.width, self.height = int(camera.width), int(camera.height)
        self.near = NEAR
        self.far = float(max(1000.0, camera.max_range * 5.0))
        pipe = _pipe()
        self._engine = GraphicsEngine.get_global_ptr()
        LiteRenderer._count += 1
        fb = FrameBufferProperties()
        fb.set_rgb_color(True)
        fb.set_rgba_bits(8, 8, 8, 8)
        fb.set_depth_bits(24)
        fb.set_multisamples(0)
        fb.set_srgb_color(False)
        props = WindowProperties.size(self.width, self.height)
        self._buffer = self._engine.make_output(
            pipe,
            f"lite-renderer-{LiteRenderer._count}",
            -2,
            fb,
            props,
            GraphicsPipe.BF_refuse_window,
            None,
            None,
        )
        if self._buffer is None:
            raise RuntimeError("could not create the Panda3D offscreen buffer")
        self._color_tex = Texture("color")
        self._depth_tex = Texture("depth")
        self._depth_tex.set_format(Texture.F_depth_component)
        self._buffer.add_render_texture(
            self._color_tex, GraphicsOutput.RTM_copy_ram, GraphicsOutput.RTP_color
        )
        self._buffer.add_render_texture(
            self._depth_tex, GraphicsOutput.RTM_copy_ram, GraphicsOutput.RTP_depth
        )
        self._buffer.set_clear_color_active(True)
        self._buffer.set_clear_color((0.0, 0.0, 0.0, 0.0))
        self._buffer.set_clear_depth_active(True)
        self._buffer.set_clear_depth(1.0)
        # GraphicsEngine.render_frame() draws every active buffer of the process; a buffer is active only
        # inside its own render() (see there)
        self._buffer.set_active(False)

        self.root = NodePath("lite-render-root")
        self.lens = PerspectiveLens()
        hfov = float(camera.fov_deg)
        vfov = math.degrees(2 * math.atan(math.tan(math.radians(hfov) / 2) * self.height / self.width))
        self.lens.set_fov(hfov, vfov)
        self.lens.set_near_far(self.near, self.far)
        from panda3d.core import Camera

        cam_node = Camera("lite-camera", self.lens)
        self.cam = self.root.attach_new_node(cam_node)
        dr = self._buffer.make_display_region()
        dr.set_camera(self.cam)
        dr.set_clear_color_active(False)
        self._dr = dr

        # lights
        self._sun = DirectionalLight("sun")
        self._sun_np = self.root.attach_new_node(self._sun)
        self._amb = AmbientLight("ambient")
        self._amb_np = self.root.attach_new_node(self._amb)
        self._head = Spotlight("ego-headlights")
        hl = PerspectiveLens()
        hl.set_fov(70.0, 40.0)
        hl.set_near_far(0.5, 120.0)
        self._head.set_lens(hl)
        self._head.set_exponent(6.0)
        self._head.set_attenuation((1.0, 0.0, 0.0012))
        self._head_np = self.cam.attach_new_node(self._head)
        self._head_np.set_pos(0.0, 0.0, -0.6)
        self._head_np.set_p(-2.0)
        self.root.set_light(self._sun_np)
        self.root.set_light(self._amb_np)

        self._compositor = WeatherCompositor(self.width, self.height, hfov, self.seed)
        self._vehicles: dict[int, VehicleModel] = {}
        self._depth_u32: np.ndarray | None = None  # reused buffers of _read_depth
        self._depth_f64: np.ndarray | None = None
        self._build_static()
        self._closed = False

    # -- static scene ----------------------------------------------------------------------------------
    def _build_static(self) -> None:
        rm = self.map
        highway = rm.name == "highway"
        static = self.root.attach_new_node("static")
        rng = np.random.default_rng(zlib.crc32(rm.name.encode()))

        # ground
        grid = ground_grid(rm, rng, 0.3 if highway else 0.05)
        m = _Mesh()
        flat = (grid.pos.reshape(-1, 3), grid.nrm.reshape(-1, 3), grid.col.reshape(-1, 3))
        m.add(*flat, cell_triangles(grid.shape[1], grid.shape[0]), L.GROUND)
        meshes: list[tuple[str, _Mesh]] = [("ground", m)]

        # roads, junctions, markings, sidewalks, puddles
        road, mark, side, puddle = _Mesh(), _Mesh(), _Mesh(), _Mesh()
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
                self._line(mark, rm, cl, nv, off, 0.12, yellow, None, s, keep)
            for k in range(1, r.lanes_each_way):  # dashed white between same-direction lanes
                for sign in (1, -1):
                    self._line(mark, rm, cl, nv, sign * k * LANE_WIDTH, 0.15, white, (3.0, 9.0), s, keep)
            for sign in (1, -1):  # solid edge lines
                self._line(mark, rm, cl, nv, sign * (hw - 0.25), 0.15, white, None, s, keep)
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
        meshes += [("roads", road), ("markings", mark), ("sidewalks", side), ("puddles", puddle)]

        # buildings
        bm = _Mesh()
        for b in rm.buildings:
            z0 = float(_elev(rm, np.array([[b.x, b.y]]))[0]) - 0.5
            col = np.asarray(b.color, np.float64)
            _box(bm, b.x, b.y, z0, b.yaw, b.width, b.depth, b.height + 0.5, col, L.BUILDING)
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
                    bm.quad(
                        centre + u + lo, centre - u + lo, centre - u + hi, centre + u + hi, win, L.BUILDING
                    )
                    zz0 += 3.2
        meshes.append(("buildings", bm))

        # trees, with a few-triangle twin of each for the far level of detail
        tm, tm_far = _Mesh(), _Mesh()
        if rm.trees:
            txy = np.array([[t.x, t.y] for t in rm.trees])
            tz = _elev(rm, txy) - (0.3 if highway else 0.0)
            for t, z in zip(rm.trees, tz, strict=True):
                self._tree(tm, tm_far, t.x, t.y, float(z), t.height, t.kind, rng)
        meshes.append(("trees", tm))

        # traffic lights: poles static, lamps one dynamic geom
        pm = _Mesh()
        lamps: list[tuple[int, int, int]] = []  # (junction, group, lamp 0 red 1 yellow 2 green)
        lamp_pos: list[np.ndarray] = []
        for jn in rm.junctions:
            for xy, heading, group in jn.signal_heads:
                x, y = float(xy[0]), float(xy[1])
                z = float(_elev(rm, np.array([[x, y]]))[0])
                _box(pm, x, y, z, heading, 0.16, 0.16, 4.6, (0.22, 0.23, 0.24), L.POLE)
                _box(pm, x, y, z + 3.2, heading, 0.32, 0.36, 1.1, (0.08, 0.08, 0.07), L.POLE)
                f = np.array([math.cos(heading), math.sin(heading), 0.0])
                rgt = np.array([math.sin(heading), -math.cos(heading), 0.0])
                for li in range(3):
                    cz = z + 4.05 - li * 0.33
                    ctr = np.array([x, y, cz]) + f * 0.17
                    h = 0.12
                    lamp_pos.append(
                        np.array(
                            [
                                ctr - rgt * h - [0, 0, h],
                                ctr + rgt * h - [0, 0, h],
                                ctr + rgt * h + [0, 0, h],
                                ctr - rgt * h + [0, 0, h],
                            ]
                        )
                    )
                    lamps.append((jn.id, int(group), li))
        meshes.append(("poles", pm))
        # The static scene is cut into ground tiles so that Panda3D's cull skips those outside the frustum,
        # and each tile has two levels of detail: beyond STATIC_LOD_M the lane markings and poles (under
        # a pixel wide there) are left out and trees are drawn as a few triangles. Tiles are grouped in
        # blocks of STATIC_BLOCK_TILES x STATIC_BLOCK_TILES; a block far enough for all its tiles to be at
        # the far level is drawn as one mesh, because llvmpipe spends some 15 us on each draw call. On the
        # highway map the full-detail scene was 214k triangles, most of them far away, in one mesh, and
        # llvmpipe spent 12 of 13 ms per frame transforming them.
        far_kinds = {"ground", "roads", "sidewalks", "puddles", "buildings"}
        far_meshes = [(n, m_) for n, m_ in meshes if n in far_kinds] + [("trees", tm_far)]
        block_m = STATIC_TILE_M * STATIC_BLOCK_TILES
        tiled: dict[tuple[int, int], list[list[tuple[str, _Mesh]]]] = {}
        for level, group in enumerate((meshes, far_meshes)):
            for name, mesh in group:
                for key, part in mesh.tiles(STATIC_TILE_M).items():
                    tiled.setdefault(key, [[], []])[level].append((name, part))
        # merged blocks draw the ground on a coarser grid (see ground.py)
        merged: dict[tuple[int, int], list[tuple[str, _Mesh]]] = {}
        for key, (gpos, gnrm, gcol, gtri) in coarse_blocks(grid, FAR_GROUND_STEP, block_m).items():
            part = _Mesh()
            part.add(gpos, gnrm, gcol, gtri, L.GROUND)
            merged.setdefault(key, []).append(("ground", part))
        for name, mesh in far_meshes:
            if name == "ground":
                continue
            for key, part in mesh.tiles(block_m).items():
                merged.setdefault(key, []).append((name, part))

        def lod_node(name: str, kx: int, ky: int, size: float) -> tuple[LODNode, Point3]:
            cx, cy = (kx + 0.5) * size, (ky + 0.5) * size
            centre = Point3(cx, cy, float(_elev(rm, np.array([[cx, cy]]))[0]))
            node = LODNode(name)
            node.set_center(centre)
            return node, centre

        def level(parent: NodePath, name: str, parts: list[tuple[str, _Mesh]]) -> None:
            child = parent.attach_new_node(name)
            for kind, part in parts:
                self._attach(child, part, kind)
            child.flatten_strong()

        blocks: dict[tuple[int, int], tuple[NodePath, NodePath, Point3]] = {}
        block_keys = set(merged) | {(kx // STATIC_BLOCK_TILES, ky // STATIC_BLOCK_TILES) for kx, ky in tiled}
        for bx, by in sorted(block_keys):
            node, centre = lod_node(f"block_{bx}_{by}", bx, by, block_m)
            block = static.attach_new_node(node)
            blocks[(bx, by)] = (block, block.attach_new_node("tiles"), centre)
            level(block, "merged", merged.get((bx, by), []))
        reach = 0.0  # farthest tile centre from its block's centre, in 3D
        for (kx, ky), levels in sorted(tiled.items()):
            block, tiles, bcentre = blocks[(kx // STATIC_BLOCK_TILES, ky // STATIC_BLOCK_TILES)]
            node, centre = lod_node(f"tile_{kx}_{ky}", kx, ky, STATIC_TILE_M)
            reach = max(reach, (centre - bcentre).length())
            tile = tiles.attach_new_node(node)
            level(tile, "near", levels[0])
            level(tile, "far", levels[1])
            node.add_switch(STATIC_LOD_M, 0.0)
            node.add_switch(1.0e7, STATIC_LOD_M)
        # a block merges only where each of its tiles is at least STATIC_LOD_M away (triangle inequality)
        block_lod = STATIC_LOD_M + reach + 1.0
        for block, _, _ in blocks.values():
            block.node().add_switch(block_lod, 0.0)
            block.node().add_switch(1.0e7, block_lod)
        self._lamps = lamps
        self._lamp_vdata = None
        if lamps:
            n = 4 * len(lamps)
            rec = np.zeros(n, _RECORD)
            rec["pos"] = np.concatenate(lamp_pos)
            rec["nrm"] = (0.0, 0.0, 1.0)
            rec["col"][:, 3] = L.POLE
            self._lamp_rec = rec
            vdata = GeomVertexData("lamps", _FORMAT, Geom.UH_dynamic)
            vdata.unclean_set_num_rows(n)
            memoryview(vdata.modify_array(0)).cast("B")[:] = rec.tobytes()
            prim = GeomTriangles(Geom.UH_static)
            prim.set_index_type(Geom.NT_uint32)
            for q in range(len(lamps)):
                prim.add_vertices(4 * q, 4 * q + 1, 4 * q + 2)
                prim.add_vertices(4 * q, 4 * q + 2, 4 * q + 3)
            geom = Geom(vdata)
            geom.add_primitive(prim)
            node = GeomNode("lamps")
            node.add_geom(geom)
            self._lamps_np = self.root.attach_new_node(node)
            self._lamps_np.set_light_off(1)
            self._lamp_vdata = geom.modify_vertex_data()
            self._lamp_state: list[str] | None = None

    @staticmethod
    def _attach(parent: NodePath, m: _Mesh, name: str) -> None:
        node = m.node(name)
        if node is not None:
            parent.attach_new_node(node)

    @staticmethod
    def _line(
        m: _Mesh,
        rm: RoadMap,
        cl: np.ndarray,
        nv: np.ndarray,
        off: float,
        w: float,
        col,  # noqa: ANN001
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

    @staticmethod
    def _tree(
        m: _Mesh,
        m_far: _Mesh,
        x: float,
        y: float,
        z: float,
        height: float,
        kind: str,
        rng: np.random.Generator,
    ) -> None:
        """A tree into ``m`` and its far twin (a 3-sided cone, no trunk, same colour) into ``m_far``."""
        trunk_h = height * (0.25 if kind == "pine" else 0.4)
        _box(m, x, y, z, 0.0, 0.3, 0.3, trunk_h + 0.3, (0.30, 0.22, 0.14), L.VEGETATION, top=False)
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
                np.column_stack(
                    [np.cos(a) * np.cos(ang), np.cos(a) * np.sin(ang), np.full(sides, math.sin(a))]
                )
                for a in lat
            ]
            unit = np.vstack([[[0, 0, -1.0]], *rings, [[0, 0, 1.0]]])
            pts = unit * np.array([rad, rad, rad * 0.85]) + np.array([x, y, cz])
            tri = []
            for q in range(sides):
                qn = (q + 1) % sides
                tri.append([0, 1 + qn, 1 + q])
                for rix in range(len(rings) - 1):
                    a0, b0 = 1 + rix * sides, 1 + (rix + 1) * sides
                    tri.append([a0 + q, a0 + qn, b0 + qn])
                    tri.append([a0 + q, b0 + qn, b0 + q])
                top = 1 + len(rings) * sides
                last = 1 + (len(rings) - 1) * sides
                tri.append([last + q, last + qn, top])
            m.add(pts, unit, col, np.array(tri), L.VEGETATION)
            far_lo, far_rad = cz - 0.6 * rad, rad
        a3 = ang[::2]
        ring = np.column_stack([x + far_rad * np.cos(a3), y + far_rad * np.sin(a3), np.full(3, far_lo)])
        nrm = np.vstack([np.column_stack([np.cos(a3), np.sin(a3), np.full(3, 0.5)]), [[0.0, 0.0, 1.0]]])
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        pts = np.vstack([ring, [[x, y, z + height]]])
        m_far.add(pts, nrm, col, np.array([[0, 1, 3], [1, 2, 3], [2, 0, 3]]), L.VEGETATION)

    def set_episode_seed(self, seed: int) -> None:
        """Seed of the per-frame sensor noise for the episode now using this renderer."""
        self._compositor.episode_seed = int(seed)

    # -- vehicles --------------------------------------------------------------------------------------
    def set_vehicles(self, vehicles: list[tuple[int, str, tuple[float, float, float]]]) -> None:
        """(vehicle index, make, colour) per vehicle; index 0 (the ego) is not drawn."""
        self.clear_vehicles()
        for idx, make, color in vehicles:
            if idx == 0:
                continue
            vm = build_vehicle_model(make, tuple(color), L.vehicle_label(idx))
            vm.root.reparent_to(self.root)
            vm.root.hide()
            self._vehicles[int(idx)] = vm

    def clear_vehicles(self) -> None:
        for vm in self._vehicles.values():
            vm.root.remove_node()
        self._vehicles.clear()

    # -- frame -----------------------------------------------------------------------------------------
    def _camera_pose(self, pose: np.ndarray) -> tuple[np.ndarray, float, float]:
        x, y, z, yaw, pitch = (float(v) for v in pose[:5])
        cam = self.camera
        cy_, sy_ = math.cos(yaw), math.sin(yaw)
        cp = math.cos(pitch)
        f0, f1, f2 = cp * cy_, cp * sy_, math.sin(pitch)  # forward
        l0, l1, l2 = -sy_, cy_, 0.0  # left
        b0, b1, b2 = -l0, -l1, -l2
        # up = forward x (-left), as np.cross computes it, pointing up
        u0, u1, u2 = f1 * b2 - f2 * b1, f2 * b0 - f0 * b2, f0 * b1 - f1 * b0
        if u2 < 0:
            u0, u1, u2 = -u0, -u1, -u2
        mx, my, mz = cam.mount_x, cam.mount_y, cam.mount_z
        pos = np.array(
            [x + f0 * mx + l0 * my + u0 * mz, y + f1 * mx + l1 * my + u1 * mz, z + f2 * mx + l2 * my + u2 * mz]
        )
        return pos, yaw, pitch + math.radians(cam.pitch_deg)

    def _update_lamps(self, time_s: float) -> None:
        if self._lamp_vdata is None:
            return
        by_group = {jg: self.map.signal_state(*jg, time_s) for jg in dict.fromkeys((j, g) for j, g, _ in self._lamps)}
        states = [by_group[(j, g)] for j, g, _ in self._lamps]
        if states == self._lamp_state:
            return
        self._lamp_state = states
        on = {0: "red", 1: "yellow", 2: "green"}
        lit = {0: (1.0, 0.12, 0.08), 1: (1.0, 0.72, 0.05), 2: (0.15, 1.0, 0.45)}
        off = {0: (0.20, 0.04, 0.03), 1: (0.20, 0.15, 0.03), 2: (0.03, 0.16, 0.07)}
        col = np.array(
            [lit[li] if st == on[li] else off[li] for (_, _, li), st in zip(self._lamps, states, strict=True)]
        )
        self._lamp_rec["col"][:, :3] = np.repeat(np.rint(col * 255), 4, axis=0).astype(np.uint8)
        memoryview(self._lamp_vdata.modify_array(0)).cast("B")[:] = self._lamp_rec.tobytes()

    def render(
        self,
        poses: np.ndarray,
        braking: np.ndarray,
        dims: np.ndarray,
        weather: Weather,
        time_s: float,
        step: int,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[GroundTruthBox]]:
        if self._closed:
            raise RuntimeError("renderer is closed")
        poses = np.asarray(poses, np.float64)
        braking = np.asarray(braking, bool)
        dims = np.asarray(dims, np.float64)
        lighting = lighting_for(weather)

        # camera
        cpos, cyaw, cpitch = self._camera_pose(poses[0])
        self.cam.set_pos(*cpos)
        self.cam.set_hpr(math.degrees(cyaw) - 90.0, math.degrees(cpitch), 0.0)

        # lights
        sd = lighting.sun_direction
        self._sun.set_color((*lighting.sun_color, 1.0))
        self._sun_np.set_pos(0, 0, 0)
        self._sun_np.look_at(Point3(-sd[0], -sd[1], -sd[2]))
        self._amb.set_color((*lighting.ambient_color, 1.0))
        hs = float(lighting.headlight_strength)
        if hs > 0.01:
            self._head.set_color((1.6 * hs, 1.55 * hs, 1.35 * hs, 1.0))
            self.root.set_light(self._head_np)
        else:
            self.root.clear_light(self._head_np)

        # vehicles
        sz = max(0.25, sd[2])
        sh_len = min(4.0, 1.4 / sz) if sd[2] > 0 else 0.0
        hidden = self._outside_view(poses, dims, cpos, cyaw, cpitch, sh_len)
        pose_rows, brake_flags, hidden_flags = poses[:, :5].tolist(), braking.tolist(), hidden.tolist()
        for idx, vm in self._vehicles.items():
            if idx >= len(pose_rows) or hidden_flags[idx]:
                vm.root.hide()
                continue
            x, y, z, yaw, pitch = pose_rows[idx]
            vm.root.show()
            vm.root.set_pos_hpr(x, y, z, math.degrees(yaw) - 90.0, math.degrees(pitch), 0.0)
            vm.set_lights(hs > 0.3, bool(brake_flags[idx]) if idx < len(brake_flags) else False)
            # shadow offset in the model frame (x right, y forward), away from the sun
            ox, oy = -sd[0] * sh_len, -sd[1] * sh_len
            c, s = math.cos(yaw), math.sin(yaw)
            fwd_o = ox * c + oy * s
            right_o = ox * s - oy * c
            vm.set_shadow(right_o, fwd_o, float(lighting.shadow_darkness) if sh_len > 0 else 0.3)
        self._update_lamps(time_s)

        # Only this renderer's buffer is active while the engine renders: render_frame() draws all active
        # buffers, and a process often holds several renderers (the backend pools one per map and camera;
        # `detector eval` keeps both maps). Each was drawn on every frame of any of them: the bench's
        # 640x480 frames, timed after its 320x240 ones, took 24 ms instead of 19.
        self._buffer.set_active(True)
        try:
            self._engine.render_frame()  # single-threaded pipeline: RTM_copy_ram textures hold this frame
        finally:
            self._buffer.set_active(False)
        h, w = self.height, self.width
        # Panda3D keeps 8-bit colour RAM images as BGRA, bottom row first: one OpenCV flip and two channel
        # extractions instead of get_ram_image_as("RGBA") and strided numpy copies (same bytes, ~1 ms less)
        bgra = cv2.flip(np.frombuffer(self._color_tex.get_ram_image(), np.uint8).reshape(h, w, 4), 0)
        labels = cv2.extractChannel(bgra, 3)
        rgb0 = cv2.cvtColor(bgra, cv2.COLOR_BGRA2RGB)
        # metric depth near * far / (far - d (far - near)), in place (same operations as one expression)
        d = self._read_depth()  # float64, ours to overwrite
        np.multiply(d, self.far - self.near, out=d)
        np.subtract(self.far, d, out=d)
        np.divide(self.near * self.far, d, out=d)
        depth = cv2.flip(d.astype(np.float32), 0)
        depth[labels == L.SKY] = np.float32(self.far)
        rgb = self._compositor.apply(rgb0, depth, labels, weather, lighting, cyaw, cpitch, int(step))
        boxes = self._boxes(poses, dims, cpos, cyaw, cpitch, labels, depth, hidden)
        return rgb, depth, labels, boxes

    def _outside_view(
        self, poses: np.ndarray, dims: np.ndarray, cpos: np.ndarray, cyaw: float, cpitch: float, shadow_len: float
    ) -> np.ndarray:
        """Vehicles wholly behind the camera or beyond the side planes of its frustum (a sphere around
        each, its shadow included, against the camera's near and two side planes in 3D). They are hidden
        without updating their pose, lamps and shadow: Panda3D would cull them anyway, but not before the
        Python work of updating them, which took some 3 ms a frame for 29 vehicles."""
        fwd, right, _ = _camera_axes(cyaw, cpitch)
        centre = poses[:, :3] + np.column_stack([np.zeros((len(poses), 2)), dims[:, 2] / 2])
        rel = centre - cpos[None, :]
        radius = 0.5 * np.sqrt((dims[:, :3] ** 2).sum(axis=1)) + shadow_len + 1.0
        half = math.radians(self.camera.fov_deg) / 2.0
        sh, ch = math.sin(half), math.cos(half)
        out = np.zeros(len(poses), bool)
        for normal in (fwd, fwd * sh + right * ch, fwd * sh - right * ch):  # inward normals of the planes
            out |= rel @ normal < -radius
        return out

    def _read_depth(self) -> np.ndarray:
        """The depth buffer in 0..1 as float64, bottom row first; the usual 24-bit format goes through a
        reused buffer (fresh 600 kB arrays per step cost page faults)."""
        tex = self._depth_tex
        h, w = self.height, self.width
        data = memoryview(tex.get_ram_image())
        ct = tex.get_component_type()
        if ct == Texture.T_float:
            d = np.frombuffer(data, np.float32).reshape(h, w)
        elif ct == Texture.T_unsigned_int_24_8:
            if self._depth_u32 is None:
                self._depth_u32, self._depth_f64 = np.empty((h, w), np.uint32), np.empty((h, w), np.float64)
            np.right_shift(np.frombuffer(data, np.uint32).reshape(h, w), 8, out=self._depth_u32)
            np.copyto(self._depth_f64, self._depth_u32)
            return np.divide(self._depth_f64, float(2**24 - 1), out=self._depth_f64)
        elif ct == Texture.T_unsigned_int:
            d = np.frombuffer(data, np.uint32).reshape(h, w).astype(np.float64) / float(2**32 - 1)
        elif ct == Texture.T_unsigned_short:
            d = np.frombuffer(data, np.uint16).reshape(h, w).astype(np.float64) / 65535.0
        else:
            raise RuntimeError(f"unsupported depth texture component type {ct}")
        return np.asarray(d, np.float64)  # bottom row first, as in the texture

    def _boxes(
        self,
        poses: np.ndarray,
        dims: np.ndarray,
        cpos: np.ndarray,
        cyaw: float,
        cpitch: float,
        labels: np.ndarray,
        depth: np.ndarray,
        hidden: np.ndarray,
    ) -> list[GroundTruthBox]:
        """Ground-truth boxes of the drawn vehicles (``hidden``: those wholly out of view, skipped).

        Each vehicle's 3D box is projected to find the window in which its label pixels are searched; the
        box is then the extent of those pixels. The projection is done for all vehicles at once (one
        numpy expression instead of some forty small ones per vehicle: 80 us per vehicle before, 25 now)."""
        h, w = self.height, self.width
        ids = [i for i in self._vehicles if i < len(poses) and not hidden[i]]
        if not ids:
            return []
        f = self.camera.focal_px
        fwd, right, up = _camera_axes(cyaw, cpitch)
        sel = np.asarray(ids)
        x, y, z = poses[sel, 0], poses[sel, 1], poses[sel, 2]
        ln, wd, ht = (dims[sel, k][:, None, None] for k in range(3))
        yaw = poses[sel, 3]
        c = np.array([math.cos(float(a)) for a in yaw])
        s = np.array([math.sin(float(a)) for a in yaw])
        zero = np.zeros(len(ids))
        ex = np.stack([c, s, zero], axis=1)[:, None, :]  # (N, 1, 3)
        ey = np.stack([-s, c, zero], axis=1)[:, None, :]
        zz = np.zeros((len(ids), 8, 3))
        zz[:, 1::2, 2] = ht[:, :, 0]
        base = np.stack([x, y, z], axis=1)[:, None, :]
        # the 8 corners, ordered a, b, z as (-1|1) x (-1|1) x (0|ht), relative to the camera
        corners = (base + ex * _CORNER_A * ln / 2 + ey * _CORNER_B * wd / 2 + zz) - cpos
        zc = corners @ fwd  # (N, 8)
        front = zc > self.near
        with np.errstate(divide="ignore", invalid="ignore"):
            u_all = w / 2 + f * (corners @ right) / zc
            v_all = h / 2 - f * (corners @ up) / zc
        u_min = np.where(front, u_all, np.inf).min(axis=1)
        u_max = np.where(front, u_all, -np.inf).max(axis=1)
        v_min = np.where(front, v_all, np.inf).min(axis=1)
        v_max = np.where(front, v_all, -np.inf).max(axis=1)
        all_front = front.all(axis=1)
        seen = (np.hypot(x - cpos[0], y - cpos[1]) <= MAX_BOX_RANGE) & front.any(axis=1)
        out: list[GroundTruthBox] = []
        for k in np.flatnonzero(seen):
            idx = ids[k]
            u0, u1, v0, v1 = float(u_min[k]), float(u_max[k]), float(v_min[k]), float(v_max[k])
            if not all_front[k]:  # partly behind the camera: the box reaches the border it crosses
                u0 = 0.0 if u0 <= w / 2 else u0
                u1 = float(w) if u1 >= w / 2 else u1
                v0, v1 = max(0.0, v0), min(float(h), v1)
            truncated = bool(u0 < 0 or v0 < 0 or u1 > w or v1 > h or not all_front[k])
            ix0, iy0 = max(0, math.floor(u0) - 1), max(0, math.floor(v0) - 1)
            ix1, iy1 = min(w, math.ceil(u1) + 1), min(h, math.ceil(v1) + 1)
            if ix1 <= ix0 or iy1 <= iy0:
                continue
            # its label's pixels in the window (OpenCV: four calls instead of eight numpy ones)
            mask = cv2.compare(labels[iy0:iy1, ix0:ix1], self._vehicles[idx].label, cv2.CMP_EQ)
            count = cv2.countNonZero(mask)
            if count < MIN_BOX_PIXELS:
                continue
            bx, by, bw, bh = cv2.boundingRect(mask)
            dist = float(cv2.minMaxLoc(depth[iy0:iy1, ix0:ix1], mask)[0])
            area = max(1.0, (min(u1, w) - max(u0, 0)) * (min(v1, h) - max(v0, 0)))
            frac = float(min(1.0, count / (_SILHOUETTE_FILL * area)))
            out.append(
                GroundTruthBox(
                    vehicle_id=int(idx),
                    x0=int(ix0 + bx),
                    y0=int(iy0 + by),
                    x1=int(ix0 + bx + bw),
                    y1=int(iy0 + by + bh),
                    distance=dist,
                    visible_fraction=frac,
                    truncated=truncated,
                )
            )
        return out

    def close(self) -> None:
        if getattr(self, "_closed", True):
            return
        self._closed = True
        self.clear_vehicles()
        self._engine.remove_window(self._buffer)
        self._buffer = None
        self.root.remove_node()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass
