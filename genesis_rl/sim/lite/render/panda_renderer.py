"""Offscreen Panda3D renderer of the lite backend: RGB, metric depth, per-pixel labels and GT boxes.

This module is the GL shell: the offscreen buffer, camera and lights, the upload of the static scene that
``static_scene.py`` builds as numpy meshes, the per-frame vehicle poses, lamps and lights, and the read-back
of colour, labels and depth. The ground-truth boxes come from ``gt_boxes.py``, the camera geometry from
``view.py``.

One geometry pass draws the static scene and the vehicles; every surface is opaque with alpha = label / 255
(see ``labels.py``), so the framebuffer's alpha channel is the label image. The colour then goes through
:class:`WeatherCompositor` (fog, rain, wet roads, sky, noise).

No ShowBase: a module-level headless GL pipe and the global GraphicsEngine are shared by every renderer;
each renderer owns its own offscreen buffer, scene root and camera, so several can live in one process.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from panda3d.core import (
    AmbientLight,
    Camera,
    CullBinManager,
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

from genesis_rl.sim.interface import CameraConfig, GroundTruthBox
from genesis_rl.sim.lite.maps.lane_graph import RoadMap
from genesis_rl.sim.lite.render import labels as L
from genesis_rl.sim.lite.render.gt_boxes import ground_truth_boxes
from genesis_rl.sim.lite.render.lighting import lighting_for
from genesis_rl.sim.lite.render.mesh import Mesh
from genesis_rl.sim.lite.render.static_scene import StaticScene, build_static_scene
from genesis_rl.sim.lite.render.vehicle_models import VehicleModel, build_vehicle_model
from genesis_rl.sim.lite.render.view import camera_pose, outside_view
from genesis_rl.sim.lite.render.weather_effects import WeatherCompositor
from genesis_rl.world.knobs import Weather

NEAR = 0.3

_FORMAT = GeomVertexFormat.get_v3n3c4()
#: one vertex as _FORMAT lays it out (position, normal, RGBA)
_RECORD = np.dtype([("pos", "<f4", 3), ("nrm", "<f4", 3), ("col", "u1", 4)])

_PIPE: GraphicsPipe | None = None


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
        # Draw opaque geometry in scene-graph order. Panda3D's default opaque bin sorts by render state, and
        # states compare by their addresses in memory, so the draw order (and with it which of two surfaces
        # at the same depth wins, e.g. a far car's shadow on the road) depended on what the process had drawn
        # before: one frame in ~2,000 differed by a few pixels between one campaign worker and two.
        bins = CullBinManager.get_global_ptr()
        bins.set_bin_type(bins.find_bin("opaque"), CullBinManager.BT_unsorted)
        _PIPE = pipe
    return _PIPE


# --- upload -------------------------------------------------------------------------------------------
def _geom_node(m: Mesh, name: str) -> GeomNode | None:
    """A static GeomNode holding ``m`` (vertex bytes and uint32 indices copied in whole), None if empty."""
    if not m.n:
        return None
    pos, nrm, col, tri = m.arrays()
    rec = np.empty(m.n, _RECORD)
    rec["pos"] = pos
    rec["nrm"] = nrm
    rec["col"] = col
    vdata = GeomVertexData(name, _FORMAT, Geom.UH_static)
    vdata.unclean_set_num_rows(m.n)
    memoryview(vdata.modify_array(0)).cast("B")[:] = rec.tobytes()
    prim = GeomTriangles(Geom.UH_static)
    prim.set_index_type(Geom.NT_uint32)
    idx = tri.reshape(-1).astype(np.uint32)
    handle = prim.modify_vertices()
    handle.unclean_set_num_rows(len(idx))
    memoryview(handle).cast("B")[:] = idx.tobytes()
    geom = Geom(vdata)
    geom.add_primitive(prim)
    node = GeomNode(name)
    node.add_geom(geom)
    return node


def _lod_node(name: str, centre: tuple[float, float, float]) -> LODNode:
    node = LODNode(name)
    node.set_center(Point3(*centre))
    return node


def _level(parent: NodePath, name: str, parts: list[tuple[str, Mesh]]) -> None:
    """One level of detail of a tile or block: its meshes, flattened into as few geoms as their states allow."""
    child = parent.attach_new_node(name)
    for kind, part in parts:
        node = _geom_node(part, kind)
        if node is not None:
            child.attach_new_node(node)
    child.flatten_strong()


def _upload_static(parent: NodePath, scene: StaticScene) -> None:
    """Blocks (LOD: their tiles near, the merged mesh far), and under each its tiles (LOD: near, far)."""
    blocks: dict[tuple[int, int], NodePath] = {}
    for (bx, by), b in scene.blocks.items():
        node = _lod_node(f"block_{bx}_{by}", b.centre)
        block = parent.attach_new_node(node)
        blocks[(bx, by)] = block.attach_new_node("tiles")
        _level(block, "merged", b.merged)
        node.add_switch(scene.block_lod_m, 0.0)
        node.add_switch(1.0e7, scene.block_lod_m)
    for (kx, ky), t in scene.tiles.items():
        node = _lod_node(f"tile_{kx}_{ky}", t.centre)
        tile = blocks[scene.block_of((kx, ky))].attach_new_node(node)
        _level(tile, "near", t.near)
        _level(tile, "far", t.far)
        node.add_switch(scene.tile_lod_m, 0.0)
        node.add_switch(1.0e7, scene.tile_lod_m)


#: the static scene of each map this process built, by the map object (``load_map`` keeps one per name; the map
#: is held here so that its id is not reused): the highway's takes seconds to build, and each camera size, each
#: episode running beside another and each oracle replay needs a renderer of its own. The upload only reads it.
_STATIC_SCENES: dict[int, tuple[RoadMap, StaticScene]] = {}
_STATIC_SCENES_KEPT = 4


def _static_scene(road_map: RoadMap) -> StaticScene:
    hit = _STATIC_SCENES.get(id(road_map))
    if hit is None or hit[0] is not road_map:
        hit = _STATIC_SCENES[id(road_map)] = (road_map, build_static_scene(road_map))
        while len(_STATIC_SCENES) > _STATIC_SCENES_KEPT:
            del _STATIC_SCENES[next(iter(_STATIC_SCENES))]
    return hit[1]


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

        self._compositor = WeatherCompositor(self.width, self.height, hfov, self.seed,
                                             exposure_jitter=camera.exposure_jitter)
        self._vehicles: dict[int, VehicleModel] = {}
        self._depth_u32: np.ndarray | None = None  # reused buffers of _read_depth
        self._depth_f64: np.ndarray | None = None
        self._build_static()
        self._closed = False

    # -- static scene ----------------------------------------------------------------------------------
    def _build_static(self) -> None:
        scene = _static_scene(self.map)
        _upload_static(self.root.attach_new_node("static"), scene)
        lamps = scene.lamps
        self._lamps = lamps.keys
        self._lamp_vdata = None
        if lamps.keys:
            n = 4 * len(lamps.keys)
            rec = np.zeros(n, _RECORD)
            rec["pos"] = lamps.quads.reshape(-1, 3)
            rec["nrm"] = (0.0, 0.0, 1.0)
            rec["col"][:, 3] = L.POLE
            self._lamp_rec = rec
            vdata = GeomVertexData("lamps", _FORMAT, Geom.UH_dynamic)
            vdata.unclean_set_num_rows(n)
            memoryview(vdata.modify_array(0)).cast("B")[:] = rec.tobytes()
            prim = GeomTriangles(Geom.UH_static)
            prim.set_index_type(Geom.NT_uint32)
            for q in range(len(lamps.keys)):
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
            r, g, b = color
            vm = build_vehicle_model(make, (r, g, b), L.vehicle_label(idx))
            vm.root.reparent_to(self.root)
            vm.root.hide()
            self._vehicles[int(idx)] = vm

    def clear_vehicles(self) -> None:
        for vm in self._vehicles.values():
            vm.root.remove_node()
        self._vehicles.clear()

    # -- frame -----------------------------------------------------------------------------------------
    def _camera_pose(self, pose: np.ndarray) -> tuple[np.ndarray, float, float]:
        return camera_pose(pose, self.camera)

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
        """Vehicles wholly out of view (see ``view.outside_view``). They are hidden without updating their
        pose, lamps and shadow: Panda3D would cull them anyway, but not before the Python work of updating
        them, which took some 3 ms a frame for 29 vehicles."""
        return outside_view(poses, dims, self.camera.fov_deg, cpos, cyaw, cpitch, shadow_len)

    def _read_depth(self) -> np.ndarray:
        """The depth buffer in 0..1 as float64, bottom row first; the usual 24-bit format goes through a
        reused buffer (fresh 600 kB arrays per step cost page faults)."""
        tex = self._depth_tex
        h, w = self.height, self.width
        data = memoryview(tex.get_ram_image())
        ct = tex.get_component_type()
        d: np.ndarray
        if ct == Texture.T_float:
            d = np.frombuffer(data, np.float32).reshape(h, w)
        elif ct == Texture.T_unsigned_int_24_8:
            u32, f64 = self._depth_u32, self._depth_f64
            if u32 is None or f64 is None:  # both are made together, on the first read
                u32, f64 = np.empty((h, w), np.uint32), np.empty((h, w), np.float64)
                self._depth_u32, self._depth_f64 = u32, f64
            np.right_shift(np.frombuffer(data, np.uint32).reshape(h, w), 8, out=u32)
            np.copyto(f64, u32)
            return np.divide(f64, float(2**24 - 1), out=f64)
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
        """Ground-truth boxes of the drawn vehicles (``hidden``: those wholly out of view, skipped)."""
        ids = [i for i in self._vehicles if i < len(poses) and not hidden[i]]
        vehicle_labels = [self._vehicles[i].label for i in ids]
        return ground_truth_boxes(
            self.camera, self.near, poses, dims, ids, vehicle_labels, cpos, cyaw, cpitch, labels, depth
        )

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
