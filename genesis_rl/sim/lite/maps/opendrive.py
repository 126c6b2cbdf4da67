"""Lite maps as OpenDRIVE 1.4: the one map format that lite, Scenic and CARLA all read.

``genesis-rl map export --map urban --format xodr`` writes it. CARLA's client builds a ``carla.Map`` from the
text without a server (so the CARLA route planner is tested on our own maps), a CARLA server drives it with
``client.generate_opendrive_world`` (the same scenes on both backends), and Scenic's driving domain loads it
as its road network.

What maps to what:

- a lite road -> an OpenDRIVE road whose reference line is the lite centre line; its forward lanes (node a to
  node b) are the right lanes -1..-n, its backward lanes the left lanes 1..n, all 3.5 m wide, so every lane
  centre lies where the lite lane lies;
- a lite junction connector -> a connecting road (one lane, -1) inside an OpenDRIVE junction whose reference
  line is the connector shifted half a lane to the left, with the lane links of the lite successor lists;
- the light at the end of a signalised lane -> a dynamic signal of type 1000001 ("OpenDRIVE" country, as
  CARLA's towns) at the stop line, named ``junction<J>_group<G>`` after the lite phase group, valid for the
  road's lanes in that direction, and one controller per (junction, group); a light has no ``unit`` (ASAM's
  schema allows only real units there, and CARLA reads a missing unit as the empty one);
- the planView is a chain of arcs through the centre line every :data:`ARC_STEP` metres, each starting with
  the centre line's tangent (exact at the joints, heading steps of ~1e-5 rad between arcs);
- the elevation is the lite terrain along the centre line, linear between the same points;
- the speed limit is the lite lane's (12 m/s in town, 25 m/s on the highway), written in km/h.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from genesis_rl import __version__
from genesis_rl.sim.lite.maps.lane_graph import DS, LANE_WIDTH, Lane, RoadMap

ARC_STEP = 2.0  # [m] spacing of the planView's arc joints along a reference line
#: arcs flatter than this are written as lines: their sagitta over ARC_STEP is under 0.05 mm, and CARLA's
#: client evaluates an arc of radius 6.6e5 km 25 m off its line (measured on the highway loop)
MIN_CURVATURE = 1e-4  # [1/m]
SIGNAL_TYPE = "1000001"  # OpenDRIVE's dynamic traffic light, as CARLA's towns name theirs
SIGNAL_SETBACK = 0.1  # [m] the signal stands this far before the road's end (inside its s range)


@dataclass(frozen=True)
class Piece:
    """One planView element: start (s, x, y, heading), length and constant curvature (0: a line)."""

    s: float
    x: float
    y: float
    hdg: float
    length: float
    curvature: float


def wrap_angle(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _tangent_headings(xy: np.ndarray) -> np.ndarray:
    d = np.gradient(xy, axis=0)
    return np.arctan2(d[:, 1], d[:, 0])


def piece_chain(xy: np.ndarray, step: float = ARC_STEP) -> list[Piece]:
    """Arcs through every ``step``-th metre of the polyline ``xy`` (sampled every DS). Each starts on the
    polyline with its tangent and ends exactly at the next joint, where its heading differs from the
    polyline's tangent by a third-order term (1e-5 rad on our bends). A chain that carried each arc's end
    heading into the next instead drifted by degrees on the highway loop (0.4 m at the outer lanes)."""
    every = max(int(round(step / DS)), 1)
    idx = list(range(0, len(xy), every))
    if idx[-1] != len(xy) - 1:
        if len(xy) - 1 - idx[-1] < every // 2 and len(idx) > 1:
            idx[-1] = len(xy) - 1  # no sliver at the end: stretch the last arc
        else:
            idx.append(len(xy) - 1)
    heads = _tangent_headings(xy)[idx]
    joints = xy[idx]
    pieces, s = [], 0.0
    for k in range(len(idx) - 1):
        (px, py), (qx, qy), hdg = joints[k], joints[k + 1], float(heads[k])
        dx, dy = float(qx - px), float(qy - py)
        chord = math.hypot(dx, dy)
        phi = wrap_angle(math.atan2(dy, dx) - hdg)  # half the heading change of the arc from p through q
        if abs(2.0 * math.sin(phi) / chord) < MIN_CURVATURE:
            length, curvature = chord, 0.0
        else:
            length, curvature = chord * phi / math.sin(phi), 2.0 * math.sin(phi) / chord
        pieces.append(Piece(s, float(px), float(py), hdg, length, curvature))
        s += length
    return pieces


def chain_length(pieces: list[Piece]) -> float:
    return pieces[-1].s + pieces[-1].length


def _left_normals(xy: np.ndarray) -> np.ndarray:
    d = np.gradient(xy, axis=0)
    h = np.arctan2(d[:, 1], d[:, 0])
    return np.column_stack([-np.sin(h), np.cos(h)])


def _f(v: float) -> str:
    return f"{v:.9g}"


class _Writer:
    """Builds the OpenDRIVE element tree of one lite map."""

    def __init__(self, road_map: RoadMap) -> None:
        self.map = road_map
        self.root = ET.Element("OpenDRIVE")
        xmin, ymin, xmax, ymax = road_map.bounds
        ET.SubElement(self.root, "header", revMajor="1", revMinor="4", name=road_map.name, version="1.00",
                      date="", north=_f(ymax), south=_f(ymin), east=_f(xmax), west=_f(xmin),
                      vendor=f"genesis-rl {__version__}")
        geo = ET.SubElement(self.root[0], "geoReference")  # a local flat frame: x east, y north, metres
        geo.text = "+proj=tmerc +lat_0=0 +lon_0=0 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs"
        # lite lane id -> (OpenDRIVE road id, OpenDRIVE lane id); connectors are roads after the lite roads
        self.odr_lane: dict[int, tuple[int, int]] = {}
        for road in road_map.roads:
            for k, lid in enumerate(road.forward_lanes):
                self.odr_lane[lid] = (road.id, -(k + 1))
            for k, lid in enumerate(road.backward_lanes):
                self.odr_lane[lid] = (road.id, k + 1)
        self.connectors = [ln for ln in road_map.lanes if ln.road < 0]
        self.connector_road = {ln.id: len(road_map.roads) + k for k, ln in enumerate(self.connectors)}
        for ln in self.connectors:
            self.odr_lane[ln.id] = (self.connector_road[ln.id], -1)
        self.predecessor = {s: ln.id for ln in road_map.lanes for s in ln.successors}
        # CARLA's parser takes a road link to an id that no road has as a link to a junction: junction ids
        # must not collide with road ids, so they start at the next thousand above the last road
        self.junction_base = 1000 * (1 + (len(road_map.roads) + len(self.connectors)) // 1000)
        self.signal_ids: dict[tuple[int, int], list[int]] = {}  # (junction, group) -> signal ids

    # -- pieces --------------------------------------------------------------------------------------------
    def _plan_view(self, road: ET.Element, pieces: list[Piece]) -> None:
        pv = ET.SubElement(road, "planView")
        for a in pieces:
            g = ET.SubElement(pv, "geometry", s=_f(a.s), x=_f(a.x), y=_f(a.y), hdg=_f(a.hdg), length=_f(a.length))
            if a.curvature == 0.0:
                ET.SubElement(g, "line")
            else:
                ET.SubElement(g, "arc", curvature=_f(a.curvature))

    def _elevation(self, road: ET.Element, arcs: list[Piece], end_xy: np.ndarray) -> None:
        prof = ET.SubElement(road, "elevationProfile")
        xs = np.array([a.x for a in arcs] + [float(end_xy[0])])
        ys = np.array([a.y for a in arcs] + [float(end_xy[1])])
        z = np.asarray(self.map.elevation(xs, ys), dtype=np.float64)
        if not np.any(z):
            ET.SubElement(prof, "elevation", s="0", a="0", b="0", c="0", d="0")
            return
        for i, a in enumerate(arcs):
            slope = (z[i + 1] - z[i]) / a.length
            ET.SubElement(prof, "elevation", s=_f(a.s), a=_f(z[i]), b=_f(slope), c="0", d="0")

    @staticmethod
    def _lane(parent: ET.Element, lane_id: int, n: int, pred: int | None = None, succ: int | None = None) -> None:
        """Lane ``lane_id`` of ``n`` on its side. Its road mark is on its outer border: broken between lanes,
        solid at the road's edge, each with an explicit ``laneChange`` (CARLA reads a mark without one as
        allowing changes both ways, solid or not)."""
        ln = ET.SubElement(parent, "lane", id=str(lane_id), type="driving", level="false")
        link = ET.SubElement(ln, "link")
        if pred is not None:
            ET.SubElement(link, "predecessor", id=str(pred))
        if succ is not None:
            ET.SubElement(link, "successor", id=str(succ))
        ET.SubElement(ln, "width", sOffset="0", a=_f(LANE_WIDTH), b="0", c="0", d="0")
        edge = abs(lane_id) == n
        ET.SubElement(ln, "roadMark", sOffset="0", type="solid" if edge else "broken", weight="standard",
                      color="standard", width="0.15", laneChange="none" if edge else "both")

    def _speed(self, road: ET.Element, lane: int) -> None:
        kind = "motorway" if self.map.speed_limit(lane) > 20.0 else "town"
        t = ET.SubElement(road, "type", s="0", type=kind)
        ET.SubElement(t, "speed", max=_f(self.map.speed_limit(lane) * 3.6), unit="km/h")

    # -- roads -----------------------------------------------------------------------------------------------
    def road(self, rid: int) -> None:
        r = self.map.roads[rid]
        arcs = piece_chain(r.centerline)
        length = chain_length(arcs)
        el = ET.SubElement(self.root, "road", name=f"road {rid}", length=_f(length), id=str(rid), junction="-1")
        link = ET.SubElement(el, "link")
        ja, jb = self._junction_at(r.node_a), self._junction_at(r.node_b)
        ET.SubElement(link, "predecessor", elementType="junction", elementId=str(ja))
        ET.SubElement(link, "successor", elementType="junction", elementId=str(jb))
        self._speed(el, r.forward_lanes[0])
        self._plan_view(el, arcs)
        self._elevation(el, arcs, r.centerline[-1])
        ET.SubElement(el, "lateralProfile")
        lanes = ET.SubElement(el, "lanes")
        sec = ET.SubElement(lanes, "laneSection", s="0")
        left = ET.SubElement(sec, "left")
        for k in reversed(range(r.lanes_each_way)):
            self._lane(left, k + 1, r.lanes_each_way)
        center = ET.SubElement(sec, "center")
        c = ET.SubElement(center, "lane", id="0", type="none", level="false")
        ET.SubElement(c, "link")
        ET.SubElement(c, "roadMark", sOffset="0", type="solid solid", weight="standard", color="yellow",
                      width="0.15", laneChange="none")
        right = ET.SubElement(sec, "right")
        for k in range(r.lanes_each_way):
            self._lane(right, -(k + 1), r.lanes_each_way)
        ET.SubElement(el, "objects")
        signals = ET.SubElement(el, "signals")
        n = r.lanes_each_way
        for lanes_of, sign in ((r.forward_lanes, -1), (r.backward_lanes, 1)):
            sig = self.map.lanes[lanes_of[0]].signal
            if sig is None:
                continue
            junction, group = sig
            sid = len(self.map.roads) + len(self.connectors) + sum(len(v) for v in self.signal_ids.values())
            self.signal_ids.setdefault(sig, []).append(sid)
            s = length - SIGNAL_SETBACK if sign < 0 else SIGNAL_SETBACK
            t = sign * (n * LANE_WIDTH + 1.2)
            name = f"junction{junction}_group{group}"
            se = ET.SubElement(signals, "signal", s=_f(s), t=_f(t), id=str(sid), name=name,
                               dynamic="yes", orientation="+" if sign < 0 else "-", zOffset="0", country="OpenDRIVE",
                               type=SIGNAL_TYPE, subtype="-1", value="-1", height="1.0", width="0.3",
                               text="", hOffset="0", pitch="0", roll="0")
            ET.SubElement(se, "validity", fromLane=str(sign), toLane=str(sign * n))

    def _junction_at(self, node: int) -> int:
        return self.junction_base + next(j.id for j in self.map.junctions if j.node == node)

    def connector(self, ln: Lane) -> None:
        """A connecting road whose lane -1 runs along the lite connector ``ln``."""
        cid = self.connector_road[ln.id]
        ref = ln.xy + _left_normals(ln.xy) * (LANE_WIDTH / 2.0)
        arcs = piece_chain(ref)
        el = ET.SubElement(self.root, "road", name=f"connector {ln.id}", length=_f(chain_length(arcs)), id=str(cid),
                           junction=str(self.junction_base + ln.junction))
        src = self.map.lanes[self.predecessor[ln.id]]
        dst = self.map.lanes[ln.successors[0]]
        (src_road, src_lane), (dst_road, dst_lane) = self.odr_lane[src.id], self.odr_lane[dst.id]
        link = ET.SubElement(el, "link")
        ET.SubElement(link, "predecessor", elementType="road", elementId=str(src_road),
                      contactPoint="end" if src_lane < 0 else "start")
        ET.SubElement(link, "successor", elementType="road", elementId=str(dst_road),
                      contactPoint="start" if dst_lane < 0 else "end")
        self._speed(el, ln.id)
        self._plan_view(el, arcs)
        self._elevation(el, arcs, ref[-1])
        ET.SubElement(el, "lateralProfile")
        lanes = ET.SubElement(el, "lanes")
        sec = ET.SubElement(lanes, "laneSection", s="0")
        center = ET.SubElement(sec, "center")
        c = ET.SubElement(center, "lane", id="0", type="none", level="false")
        ET.SubElement(c, "link")
        right = ET.SubElement(sec, "right")
        self._lane(right, -1, 1, pred=src_lane, succ=dst_lane)
        ET.SubElement(el, "objects")
        ET.SubElement(el, "signals")

    def junctions(self) -> None:
        for (junction, group), sids in sorted(self.signal_ids.items()):
            ctrl = ET.SubElement(self.root, "controller", name=f"junction{junction}_group{group}",
                                 id=f"{junction * 2 + group}")
            for sid in sids:
                ET.SubElement(ctrl, "control", signalId=str(sid), type="0")
        for j in self.map.junctions:
            el = ET.SubElement(self.root, "junction", id=str(self.junction_base + j.id), name=f"junction {j.id}")
            conns = [ln for ln in self.connectors if ln.junction == j.id]
            for k, ln in enumerate(conns):
                src_road, src_lane = self.odr_lane[self.predecessor[ln.id]]
                c = ET.SubElement(el, "connection", id=str(k), incomingRoad=str(src_road),
                                  connectingRoad=str(self.connector_road[ln.id]), contactPoint="start")
                ET.SubElement(c, "laneLink", attrib={"from": str(src_lane), "to": "-1"})
            for group in (0, 1):
                if (j.id, group) in self.signal_ids:
                    ET.SubElement(el, "controller", id=f"{j.id * 2 + group}", type="0", sequence=str(group))

    def text(self) -> str:
        for rid in range(len(self.map.roads)):
            self.road(rid)
        for ln in self.connectors:
            self.connector(ln)
        self.junctions()
        ET.indent(self.root)
        return '<?xml version="1.0" standalone="yes"?>\n' + ET.tostring(self.root, encoding="unicode") + "\n"


def to_opendrive(road_map: RoadMap) -> str:
    """The map as OpenDRIVE 1.4 text (deterministic: the same map gives the same bytes)."""
    return _Writer(road_map).text()


def odr_lane_ids(road_map: RoadMap) -> dict[int, tuple[int, int]]:
    """Lite lane id -> (OpenDRIVE road id, lane id) in :func:`to_opendrive`'s output."""
    return dict(_Writer(road_map).odr_lane)


def signal_of(name: str) -> tuple[int, int] | None:
    """(junction, group) of a signal this exporter named, else None (e.g. a CARLA town's light)."""
    if not name.startswith("junction") or "_group" not in name:
        return None
    j, g = name[len("junction"):].split("_group", 1)
    return (int(j), int(g)) if j.isdigit() and g.isdigit() else None


def signal_plan(road_map: RoadMap) -> Callable[[Any, float], str]:
    """The lite map's fixed-time light plan for the exported signals: (landmark or signal with a ``name``,
    time [s]) -> 'green', 'yellow', 'red'. What a CARLA route on the exported map reads offline, so the
    built-in controller meets the same lights on both backends."""

    def state(landmark: Any, time_s: float) -> str:
        ref = signal_of(str(landmark.name))
        return "green" if ref is None else road_map.signal_state(ref[0], ref[1], time_s)

    return state
