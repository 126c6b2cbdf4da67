"""Procedural low-poly vehicle models for the Panda3D geometry pass.

A learned car detector sees these images, so the models carry the photographic cues that make a box read
as a vehicle (measured with a COCO detector: bare boxes 1/56 views, these cues 38/56): a tapered body and
cabin with sloped glass, pillars in body colour, dark tyres with lighter rims under darker wheel arches,
a red tail-light bar over a dark bumper and a light plate, headlights and a dark grille at the front,
slightly different brightness per face, and a soft contact shadow.

Conventions: Z up, the model faces +Y, origin at the vehicle centre on the ground, x to the right.
Every vertex is opaque with alpha = ``label / 255`` (the per-pixel label of ``labels.py``); lighting is
fixed-function (vertex colours act as the material), so normals are per face (flat shading). The contact
shadow multiplies the colour already in the framebuffer and leaves its alpha (the label below) untouched.

Geometry is built once per make as numpy templates (positions, normals, colour roles); a vehicle only
recolours a copy, so building one takes about a millisecond.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from panda3d.core import (
    ColorBlendAttrib,
    Geom,
    GeomNode,
    GeomTriangles,
    GeomVertexData,
    GeomVertexFormat,
    NodePath,
)

from genesis_rl.world.scenes.vehicles import MAKES

# --- colour roles -------------------------------------------------------------------------------------
BODY, CARGO, GLASS, TYRE, RIM, HUB, ARCH, TRIM, PLATE, TAILBAR, UNDER, HEAD, TAIL = range(13)

#: fixed colours of the roles that do not take the paint colour (sRGB 0..1)
_FIXED: dict[int, tuple[float, float, float]] = {
    GLASS: (0.10, 0.12, 0.16),
    TYRE: (0.05, 0.05, 0.05),
    RIM: (0.62, 0.63, 0.65),
    HUB: (0.30, 0.30, 0.32),
    ARCH: (0.025, 0.025, 0.025),
    TRIM: (0.07, 0.07, 0.075),
    PLATE: (0.88, 0.88, 0.84),
    TAILBAR: (0.42, 0.03, 0.03),
    UNDER: (0.03, 0.03, 0.03),
    HEAD: (0.78, 0.79, 0.80),
    TAIL: (0.60, 0.04, 0.04),
}
_CARGO_WHITE = np.array([0.86, 0.86, 0.84])

#: light colours when lit up (unlit, so they stay bright at night)
HEADLIGHT_ON = (1.0, 0.96, 0.82)
TAIL_GLOW = (0.85, 0.06, 0.04)
BRAKE_ON = (1.0, 0.12, 0.08)

_FORMAT = GeomVertexFormat.get_v3n3c4()
_RECORD = np.dtype([("pos", "<f4", 3), ("nrm", "<f4", 3), ("col", "u1", 4)])
assert _RECORD.itemsize == _FORMAT.get_array(0).get_stride()

Vec = tuple[float, float, float]


# --- mesh builder -------------------------------------------------------------------------------------
class _Mesh:
    """Flat-shaded triangle soup: every triangle has its own three vertices and face normal."""

    def __init__(self, seed: int) -> None:
        self.pos: list[Vec] = []
        self.nrm: list[Vec] = []
        self.role: list[int] = []
        self.shade: list[float] = []
        self._rng = np.random.default_rng(seed)

    def tri(
        self,
        a: Vec,
        b: Vec,
        c: Vec,
        role: int,
        out: Vec | None = None,
        shades: tuple[float, float, float] = (1.0, 1.0, 1.0),
    ) -> None:
        """Add a triangle; its winding is flipped if needed so its normal points along ``out``."""
        pa, pb, pc = np.asarray(a), np.asarray(b), np.asarray(c)
        n = np.cross(pb - pa, pc - pa)
        length = float(np.linalg.norm(n))
        if length < 1e-9:
            return
        n = n / length
        if out is not None and float(np.dot(n, out)) < 0.0:
            pb, pc, n = pc, pb, -n
            shades = (shades[0], shades[2], shades[1])
        nn = (float(n[0]), float(n[1]), float(n[2]))
        for p, s in zip((pa, pb, pc), shades, strict=True):
            self.pos.append((float(p[0]), float(p[1]), float(p[2])))
            self.nrm.append(nn)
            self.role.append(role)
            self.shade.append(s)

    def quad(
        self,
        a: Vec,
        b: Vec,
        c: Vec,
        d: Vec,
        role: int,
        out: Vec | None = None,
        shades: tuple[float, float, float, float] | None = None,
    ) -> None:
        """Add a quad a-b-c-d (in order around it) with a small random brightness change per face."""
        k = float(self._rng.uniform(0.95, 1.05))
        s = (1.0, 1.0, 1.0, 1.0) if shades is None else shades
        s = (s[0] * k, s[1] * k, s[2] * k, s[3] * k)
        if out is None:
            n = np.cross(np.subtract(c, a), np.subtract(d, b))
            out = (float(n[0]), float(n[1]), float(n[2]))
        self.tri(a, b, c, role, out, (s[0], s[1], s[2]))
        self.tri(a, c, d, role, out, (s[0], s[2], s[3]))

    def poly(self, pts: list[Vec], role: int, out: Vec) -> None:
        """Add a convex polygon as a fan."""
        for i in range(1, len(pts) - 1):
            self.tri(pts[0], pts[i], pts[i + 1], role, out)

    def box(
        self,
        x0: float,
        x1: float,
        y0: float,
        y1: float,
        z0: float,
        z1: float,
        role: int,
        skip: tuple[str, ...] = ("bottom",),
    ) -> None:
        """Axis-aligned box; ``skip`` names faces that are hidden (bottom, top, left, right, front, rear)."""
        faces = {
            "top": ([(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)], (0, 0, 1)),
            "bottom": ([(x0, y0, z0), (x0, y1, z0), (x1, y1, z0), (x1, y0, z0)], (0, 0, -1)),
            "right": ([(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)], (1, 0, 0)),
            "left": ([(x0, y0, z0), (x0, y0, z1), (x0, y1, z1), (x0, y1, z0)], (-1, 0, 0)),
            "front": ([(x0, y1, z0), (x0, y1, z1), (x1, y1, z1), (x1, y1, z0)], (0, 1, 0)),
            "rear": ([(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)], (0, -1, 0)),
        }
        for name, ((a, b, c, d), out) in faces.items():
            if name not in skip:
                self.quad(a, b, c, d, role=role, out=out)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return (
            np.array(self.pos, np.float32).reshape(-1, 3),
            np.array(self.nrm, np.float32).reshape(-1, 3),
            np.array(self.role, np.int16),
            np.array(self.shade, np.float32),
        )


def _lerp(a: Vec, b: Vec, t: float) -> Vec:
    return (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t)


def _bilerp(c00: Vec, c10: Vec, c11: Vec, c01: Vec, u: float, v: float) -> Vec:
    return _lerp(_lerp(c00, c10, u), _lerp(c01, c11, u), v)


def _offset(p: Vec, n: Vec, d: float) -> Vec:
    return (p[0] + n[0] * d, p[1] + n[1] * d, p[2] + n[2] * d)


def _unit_normal(a: Vec, b: Vec, c: Vec, d: Vec) -> Vec:
    n = np.cross(np.subtract(c, a), np.subtract(d, b))
    n = n / np.linalg.norm(n)
    return (float(n[0]), float(n[1]), float(n[2]))


def _decal(
    m: _Mesh,
    quad: tuple[Vec, Vec, Vec, Vec],
    u0: float,
    u1: float,
    v0: float,
    v1: float,
    role: int,
    lift: float = 0.012,
    shades: tuple[float, float, float, float] | None = None,
) -> None:
    """A panel on a (planar) face quad c00,c10,c11,c01, in its (u, v) coordinates, lifted off the face."""
    n = _unit_normal(*quad)
    a, b, c, d = (_offset(_bilerp(*quad, u, v), n, lift) for u, v in ((u0, v0), (u1, v0), (u1, v1), (u0, v1)))
    m.quad(a, b, c, d, role=role, out=n, shades=shades)


# --- make specifications ------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Spec:
    """Shape of one make: lower-body stations, cabin profile, wheels and details (metres)."""

    #: lower body stations rear to front: (y, z_bottom, z_shoulder, z_top, width factor)
    stations: tuple[tuple[float, float, float, float, float], ...]
    tumble: float  # inset of the top edge of the lower body (tapered sides)
    #: cabin side profile: y of rear-window base, roof rear, roof front, windshield base
    cabin_y: tuple[float, float, float, float]
    cabin_z0: float
    roof_inset: float  # how much narrower the roof is than the cabin base, per side
    wheel_r: float
    axles: tuple[float, ...]
    side_windows: tuple[tuple[float, float], ...]  # (u0, u1) along the cabin side
    rear_window: tuple[float, float, float, float] = (0.06, 0.94, 0.08, 0.90)  # u0, u1, v0, v1
    windshield: tuple[float, float, float, float] = (0.05, 0.95, 0.06, 0.92)
    side_v: tuple[float, float] = (0.10, 0.88)
    mirrors: bool = True
    #: truck cargo box (y0, y1, z0) up to full height; None for other makes
    cargo: tuple[float, float, float] | None = None


def _spec(make: str) -> _Spec:
    mk = MAKES[make]
    L2 = mk.length / 2.0
    a = mk.wheelbase / 2.0
    if make == "sedan":
        return _Spec(
            stations=(
                (-L2, 0.34, 0.70, 0.84, 0.90),
                (-L2 + 0.22, 0.24, 0.74, 0.93, 0.99),
                (-1.50, 0.22, 0.74, 0.94, 1.0),
                (0.95, 0.22, 0.74, 0.92, 1.0),
                (1.95, 0.22, 0.70, 0.80, 1.0),
                (L2, 0.28, 0.62, 0.70, 0.90),
            ),
            tumble=0.07,
            cabin_y=(-1.50, -0.72, 0.28, 0.95),
            cabin_z0=0.91,
            roof_inset=0.17,
            wheel_r=0.32,
            axles=(-a, a),
            side_windows=((0.07, 0.49), (0.53, 0.93)),
        )
    if make == "hatchback":
        return _Spec(
            stations=(
                (-L2, 0.34, 0.72, 0.86, 0.92),
                (-L2 + 0.14, 0.22, 0.74, 0.94, 1.0),
                (0.80, 0.22, 0.74, 0.92, 1.0),
                (1.70, 0.22, 0.70, 0.80, 1.0),
                (L2, 0.28, 0.62, 0.70, 0.91),
            ),
            tumble=0.07,
            cabin_y=(-L2 + 0.14, -1.62, 0.12, 0.80),
            cabin_z0=0.91,
            roof_inset=0.16,
            wheel_r=0.31,
            axles=(-a, a),
            side_windows=((0.10, 0.52), (0.56, 0.93)),
            rear_window=(0.08, 0.92, 0.10, 0.88),
        )
    if make == "suv":
        return _Spec(
            stations=(
                (-L2, 0.42, 0.88, 1.02, 0.93),
                (-L2 + 0.14, 0.32, 0.92, 1.08, 1.0),
                (1.05, 0.32, 0.92, 1.06, 1.0),
                (2.02, 0.32, 0.90, 1.00, 1.0),
                (L2, 0.38, 0.80, 0.92, 0.93),
            ),
            tumble=0.07,
            cabin_y=(-L2 + 0.14, -2.08, 0.38, 1.05),
            cabin_z0=1.05,
            roof_inset=0.15,
            wheel_r=0.37,
            axles=(-a, a),
            side_windows=((0.04, 0.30), (0.33, 0.62), (0.65, 0.94)),
            rear_window=(0.08, 0.92, 0.12, 0.88),
        )
    if make == "van":
        return _Spec(
            stations=(
                (-L2, 0.36, 0.85, 1.00, 0.96),
                (-L2 + 0.12, 0.30, 0.88, 1.05, 1.0),
                (1.55, 0.30, 0.88, 1.05, 1.0),
                (2.30, 0.30, 0.82, 0.98, 1.0),
                (L2, 0.36, 0.70, 0.86, 0.94),
            ),
            tumble=0.05,
            cabin_y=(-L2 + 0.12, -L2 + 0.16, 1.00, 1.72),
            cabin_z0=1.02,
            roof_inset=0.10,
            wheel_r=0.36,
            axles=(-a, a),
            side_windows=((0.72, 0.95),),
            rear_window=(0.08, 0.92, 0.42, 0.92),
            windshield=(0.05, 0.95, 0.06, 0.90),
            side_v=(0.10, 0.70),
        )
    if make == "truck":
        return _Spec(
            stations=(
                (1.72, 0.50, 1.25, 1.45, 1.0),
                (3.55, 0.50, 1.20, 1.42, 1.0),
                (L2, 0.55, 1.10, 1.32, 0.95),
            ),
            tumble=0.05,
            cabin_y=(1.74, 1.76, 3.40, 3.60),
            cabin_z0=1.40,
            roof_inset=0.10,
            wheel_r=0.50,
            axles=(L2 - 1.2, L2 - 1.2 - mk.wheelbase),
            side_windows=((0.50, 0.93),),
            rear_window=(0.0, 0.0, 0.0, 0.0),
            windshield=(0.05, 0.95, 0.10, 0.90),
            side_v=(0.12, 0.80),
            cargo=(-L2, 1.66, 1.05),
        )
    if make == "bus":
        n = 7
        wins = tuple((0.03 + i * 0.94 / n + 0.012, 0.03 + (i + 1) * 0.94 / n - 0.012) for i in range(n))
        return _Spec(
            stations=(
                (-L2, 0.34, 1.00, 1.15, 0.97),
                (-L2 + 0.12, 0.30, 1.05, 1.20, 1.0),
                (L2 - 0.12, 0.30, 1.00, 1.10, 1.0),
                (L2, 0.34, 0.90, 1.05, 0.97),
            ),
            tumble=0.04,
            cabin_y=(-L2 + 0.10, -L2 + 0.16, L2 - 0.18, L2 - 0.05),
            cabin_z0=1.05,
            roof_inset=0.06,
            wheel_r=0.50,
            axles=(-a + 0.3, a + 0.3),
            side_windows=wins,
            rear_window=(0.10, 0.90, 0.45, 0.88),
            windshield=(0.03, 0.97, 0.04, 0.90),
            side_v=(0.08, 0.85),
        )
    raise KeyError(f"unknown make {make!r}; known: {sorted(MAKES)}")


# --- geometry -----------------------------------------------------------------------------------------
@dataclass
class _Template:
    """Per-make geometry arrays: static parts, headlights, tail lamps; plus the shadow footprint."""

    parts: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
    footprint: tuple[float, float]  # half width, half length


def _section(st: tuple[float, float, float, float, float], hw: float, t: float) -> list[Vec]:
    """Cross-section polygon of the lower body at one station, right side bottom to top, then left."""
    y, zb, zs, zt, f = st
    r = [(hw * f, y, zb), (hw * f, y, zs), ((hw - t) * f, y, zt)]
    return r + [(-p[0], p[1], p[2]) for p in reversed(r)]


def _lower_body(m: _Mesh, sp: _Spec, hw: float, role: int = BODY) -> None:
    secs = [_section(st, hw, sp.tumble) for st in sp.stations]
    for s0, s1, st0, st1 in zip(secs[:-1], secs[1:], sp.stations[:-1], sp.stations[1:], strict=True):
        centre = (0.0, (st0[0] + st1[0]) / 2, (st0[1] + st0[3] + st1[1] + st1[3]) / 4)
        for i in range(len(s0) - 1):
            a, b, c, d = s0[i], s1[i], s1[i + 1], s0[i + 1]
            mid = np.mean([a, b, c, d], axis=0)
            m.quad(a, b, c, d, role, out=tuple(mid - np.asarray(centre)))
        # underside
        m.quad(s0[-1], s1[-1], s1[0], s0[0], UNDER, out=(0, 0, -1))
    m.poly(secs[0], role, (0, -1, 0))
    m.poly(secs[-1], role, (0, 1, 0))


def _end_face(sp: _Spec, hw: float, front: bool) -> tuple[Vec, Vec, Vec, Vec]:
    """The vertical rectangle (bottom to shoulder) of the front or rear cap, as a decal quad (c00..c01)."""
    y, zb, zs, _zt, f = sp.stations[-1 if front else 0]
    w = hw * f
    if front:  # u runs along -x here so that the quad faces +y
        return ((w, y, zb), (-w, y, zb), (-w, y, zs), (w, y, zs))
    return ((-w, y, zb), (w, y, zb), (w, y, zs), (-w, y, zs))


def _cabin(m: _Mesh, sp: _Spec, hw: float, height: float) -> None:
    """Greenhouse: trapezoid side profile, narrower roof; body-coloured, with glass panels laid on it."""
    yrb, yrr, yrf, ywb = sp.cabin_y
    z0 = sp.cabin_z0
    wb = (hw - sp.tumble) - 0.03
    wr = wb - sp.roof_inset
    rb_r, rb_l = (wb, yrb, z0), (-wb, yrb, z0)
    rr_r, rr_l = (wr, yrr, height), (-wr, yrr, height)
    rf_r, rf_l = (wr, yrf, height), (-wr, yrf, height)
    wb_r, wb_l = (wb, ywb, z0), (-wb, ywb, z0)
    rear = (rb_l, rb_r, rr_r, rr_l)
    roof = (rr_l, rr_r, rf_r, rf_l)
    front = (wb_r, wb_l, rf_l, rf_r)
    right = (rb_r, wb_r, rf_r, rr_r)
    left = (wb_l, rb_l, rr_l, rf_l)
    for q in (rear, roof, front, right, left):
        m.quad(*q, role=BODY, out=_unit_normal(*q))
    glass_shades = (0.85, 0.85, 1.9, 1.9)  # lighter towards the top: sky reflection
    if sp.rear_window[1] > sp.rear_window[0]:
        _decal(m, rear, *sp.rear_window, role=GLASS, shades=(1.5, 1.5, 3.4, 3.4))
    _decal(m, front, *sp.windshield, role=GLASS, shades=glass_shades)
    v0, v1 = sp.side_v
    for u0, u1 in sp.side_windows:
        _decal(m, right, u0, u1, v0, v1, GLASS, shades=glass_shades)
        _decal(m, left, 1 - u1, 1 - u0, v0, v1, GLASS, shades=glass_shades)
    if sp.mirrors:
        for s in (1.0, -1.0):
            x0, x1 = s * (wb - 0.02), s * (wb + 0.16)
            y0 = ywb - 0.30 if sp.cargo is None else ywb - 0.45
            m.box(min(x0, x1), max(x0, x1), y0, y0 + 0.10, z0 + 0.06, z0 + 0.20, BODY)


def _wheel(m: _Mesh, x_out: float, y: float, r: float, width: float, side: float) -> None:
    """Tyre (10-gon prism), a light rim disc and a darker hub on the outer face; axis along x."""
    n = 10
    xi = x_out - side * width
    ang = [2 * math.pi * (i + 0.5) / n for i in range(n)]
    ring = [(y + r * math.cos(t), r + r * math.sin(t)) for t in ang]
    for i in range(n):
        (ya, za), (yb, zb) = ring[i], ring[(i + 1) % n]
        out = (0.0, (ya + yb) / 2 - y, (za + zb) / 2 - r)
        m.quad((xi, ya, za), (xi, yb, zb), (x_out, yb, zb), (x_out, ya, za), TYRE, out=out)
    m.poly([(x_out, yy, zz) for yy, zz in ring], TYRE, (side, 0, 0))
    for rad, lift, role, k in ((0.66, 0.004, RIM, 8), (0.26, 0.008, HUB, 6)):
        pts = [
            (
                x_out + side * lift,
                y + rad * r * math.cos(2 * math.pi * i / k),
                r + rad * r * math.sin(2 * math.pi * i / k),
            )
            for i in range(k)
        ]
        m.poly(pts, role, (side, 0, 0))


def _arch(m: _Mesh, x: float, y: float, r: float, z_bottom: float, side: float) -> None:
    """Dark wheel-well half disc on the body side above the tyre."""
    rr = r + 0.07
    pts = [(x, y + rr, z_bottom)]
    pts += [(x, y + rr * math.cos(t), r + rr * math.sin(t)) for t in np.linspace(0, math.pi, 7)]
    pts.append((x, y - rr, z_bottom))
    m.poly(pts, ARCH, (side, 0, 0))


def _build_template(make: str) -> _Template:
    mk = MAKES[make]
    sp = _spec(make)
    hw = mk.width / 2.0 - 0.02
    body = _Mesh(seed=sum(map(ord, make)))
    head = _Mesh(seed=1)
    tail = _Mesh(seed=2)

    _lower_body(body, sp, hw)
    _cabin(body, sp, hw, mk.height)

    # wheels, arches and a dark sill strip
    for y in sp.axles:
        for side in (1.0, -1.0):
            tyre_w = 0.24 if make in ("sedan", "hatchback") else 0.3
            _wheel(body, side * mk.width / 2.0, y, sp.wheel_r, tyre_w, side)
            if sp.cargo is None or y > sp.cargo[1]:
                _arch(body, side * (hw + 0.004), y, sp.wheel_r, sp.stations[0][1] - 0.08, side)
    y0, y1 = sp.stations[0][0] + 0.25, sp.stations[-1][0] - 0.25
    zb = max(st[1] for st in sp.stations[1:-1]) if len(sp.stations) > 2 else sp.stations[0][1]
    for side in (1.0, -1.0):
        x = side * (hw + 0.003)
        body.quad((x, y0, zb), (x, y1, zb), (x, y1, zb + 0.07), (x, y0, zb + 0.07), TRIM, out=(side, 0, 0))

    # rear: bumper, plate, tail-light bar and lamps
    rear = _end_face(sp, hw, front=False)
    yr, zbr, zsr, _, fr = sp.stations[0]
    if sp.cargo is not None:
        _truck(body, tail, sp, mk.width, mk.height)
    else:
        hb = zsr - zbr
        bw = hw * fr + 0.03
        body.box(-bw, bw, yr - 0.05, yr + 0.30, zbr - 0.04, zbr + 0.30 * hb, TRIM, skip=("bottom", "front"))
        _decal(body, rear, 0.36, 0.64, 0.33, 0.55, PLATE, lift=0.012)
        _decal(body, rear, 0.25, 0.75, 0.78, 0.92, TAILBAR, lift=0.010)
        _decal(tail, rear, 0.02, 0.25, 0.70, 0.98, TAIL, lift=0.014)
        _decal(tail, rear, 0.75, 0.98, 0.70, 0.98, TAIL, lift=0.014)
    # front: bumper, grille, headlights
    front = _end_face(sp, hw, front=True)
    yf, zbf, zsf, _, ff = sp.stations[-1]
    bw = hw * ff + 0.03
    bumper_top = zbf + 0.28 * (zsf - zbf)
    body.box(-bw, bw, yf - 0.30, yf + 0.05, zbf - 0.04, bumper_top, TRIM, skip=("bottom", "rear"))
    _decal(body, front, 0.30, 0.70, 0.45, 0.90, TRIM, lift=0.010)
    _decal(body, front, 0.36, 0.64, 0.34, 0.44, PLATE, lift=0.010)
    _decal(head, front, 0.04, 0.27, 0.66, 0.95, HEAD, lift=0.014)
    _decal(head, front, 0.73, 0.96, 0.66, 0.95, HEAD, lift=0.014)

    half_len = mk.length / 2.0
    return _Template(
        parts={"body": body.arrays(), "head": head.arrays(), "tail": tail.arrays()},
        footprint=(mk.width / 2.0, half_len),
    )


def _truck(body: _Mesh, tail: _Mesh, sp: _Spec, width: float, height: float) -> None:
    """Cargo box over a dark chassis, with rear doors, an underrun bumper, lamps and plate."""
    assert sp.cargo is not None
    y0, y1, z0 = sp.cargo
    w = width / 2.0
    body.box(-w, w, y0, y1, z0, height, CARGO, skip=())
    body.box(-0.55, 0.55, y0 + 0.3, y1 + 0.2, 0.55, z0, UNDER, skip=("bottom",))
    # rear doors: seams and hinge bars laid on the rear face
    rear = ((-w, y0, z0), (w, y0, z0), (w, y0, height), (-w, y0, height))
    _decal(body, rear, 0.495, 0.505, 0.0, 1.0, TRIM, lift=0.01)
    for u in (0.02, 0.96):
        _decal(body, rear, u, u + 0.02, 0.0, 1.0, TRIM, lift=0.01)
    _decal(body, rear, 0.0, 1.0, 0.0, 0.04, TRIM, lift=0.01)
    # underrun bumper with lamps and plate
    bw = w - 0.12
    body.box(-bw, bw, y0 + 0.02, y0 + 0.25, 0.50, 0.72, TRIM, skip=("bottom",))
    bar = ((-bw, y0 + 0.02, 0.50), (bw, y0 + 0.02, 0.50), (bw, y0 + 0.02, 0.72), (-bw, y0 + 0.02, 0.72))
    _decal(body, bar, 0.38, 0.62, 0.15, 0.85, PLATE, lift=0.012)
    _decal(body, bar, 0.22, 0.36, 0.25, 0.75, TAILBAR, lift=0.012)
    _decal(body, bar, 0.64, 0.78, 0.25, 0.75, TAILBAR, lift=0.012)
    _decal(tail, rear, 0.04, 0.20, 0.03, 0.09, TAIL, lift=0.014)
    _decal(tail, rear, 0.80, 0.96, 0.03, 0.09, TAIL, lift=0.014)
    _decal(tail, bar, 0.02, 0.20, 0.2, 0.8, TAIL, lift=0.014)
    _decal(tail, bar, 0.80, 0.98, 0.2, 0.8, TAIL, lift=0.014)


_TEMPLATES: dict[str, _Template] = {}


def _template(make: str) -> _Template:
    t = _TEMPLATES.get(make)
    if t is None:
        t = _TEMPLATES[make] = _build_template(make)
    return t


# --- Panda3D nodes -------------------------------------------------------------------------------------
def _role_colours(color: tuple[float, float, float]) -> np.ndarray:
    pal = np.zeros((13, 3), np.float32)
    c = np.clip(np.asarray(color, np.float32), 0.0, 1.0)
    pal[BODY] = c
    pal[CARGO] = 0.3 * c + 0.7 * _CARGO_WHITE
    for role, rgb in _FIXED.items():
        pal[role] = rgb
    return pal


def _geom_node(
    name: str, arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], palette: np.ndarray, label: int
) -> GeomNode:
    """One Geom of non-indexed triangles with colours for this vehicle; alpha = label exactly."""
    pos, nrm, role, shade = arrays
    n = len(pos)
    rec = np.empty(n, _RECORD)
    rec["pos"] = pos
    rec["nrm"] = nrm
    rgb = palette[role] * shade[:, None]
    # a little sky sheen on upward faces, so black and dark paint still show their shape
    rgb += (0.05 * np.clip(nrm[:, 2], 0.0, 1.0))[:, None] * (role == BODY)[:, None]
    rec["col"][:, :3] = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
    rec["col"][:, 3] = label
    vdata = GeomVertexData(name, _FORMAT, Geom.UH_static)
    vdata.unclean_set_num_rows(n)
    memoryview(vdata.modify_array(0)).cast("B")[:] = rec.tobytes()
    prim = GeomTriangles(Geom.UH_static)
    prim.add_consecutive_vertices(0, n)
    geom = Geom(vdata)
    geom.add_primitive(prim)
    node = GeomNode(name)
    node.add_geom(geom)
    return node


_SHADOW_BLEND = ColorBlendAttrib.make(
    ColorBlendAttrib.M_add,
    ColorBlendAttrib.O_fbuffer_color,
    ColorBlendAttrib.O_zero,
    ColorBlendAttrib.M_add,
    ColorBlendAttrib.O_zero,
    ColorBlendAttrib.O_one,
)


def _shadow_rings(half_w: float, half_l: float) -> tuple[np.ndarray, np.ndarray]:
    """Rounded-rectangle rings (core, middle, edge) as (3, K, 2) xy points and their weights (1 .. 0)."""
    corners = ((1, 1), (-1, 1), (-1, -1), (1, -1))
    rings = []
    for inset_w, inset_l, rad in ((0.97, 0.98, 0.0), (1.0, 1.0, 0.15), (1.0, 1.0, 0.40)):
        pts = []
        for k, (sx, sy) in enumerate(corners):
            cx, cy = sx * half_w * inset_w, sy * half_l * inset_l
            a0 = k * math.pi / 2
            for j in range(3):
                a = a0 + j * math.pi / 4
                pts.append((cx + rad * math.cos(a), cy + rad * math.sin(a)))
        rings.append(pts)
    return np.array(rings, np.float32), np.array([1.0, 0.7, 0.0], np.float32)


class VehicleModel:
    """One vehicle: static body node, headlight and tail-lamp nodes, and a multiplicative contact shadow."""

    def __init__(self, make: str, color: tuple[float, float, float], label: int) -> None:
        if not 0 <= label <= 255:
            raise ValueError(f"label {label} out of 0..255")
        tpl = _template(make)
        self.make = make
        self.label = label
        self.root = NodePath(f"vehicle-{make}-{label}")
        palette = _role_colours(color)
        parts = tpl.parts
        self.body = self.root.attach_new_node(_geom_node("body", parts["body"], palette, label))
        self.headlights = self.root.attach_new_node(_geom_node("headlights", parts["head"], palette, label))
        self.taillights = self.root.attach_new_node(_geom_node("taillights", parts["tail"], palette, label))
        self._rings, self._weights = _shadow_rings(*tpl.footprint)
        k = self._rings.shape[1]
        self._shadow_xy = self._rings.reshape(-1, 2).astype(np.float64)
        self._shadow_w = np.repeat(self._weights, k)
        self._shadow_rec = np.empty(len(self._shadow_xy), _RECORD)
        self._shadow_rec["pos"][:, 2] = 0.0
        self._shadow_rec["nrm"] = (0.0, 0.0, 1.0)
        self._shadow_rec["col"][:, 3] = 255
        self._shadow_args: tuple[float, float, float] | None = None
        self._light_state: tuple[bool, bool] | None = None
        self._shadow_vdata, shadow_node = self._make_shadow()
        self.shadow = self.root.attach_new_node(shadow_node)
        self.shadow.set_pos(0.0, 0.0, 0.03)
        self.shadow.set_attrib(_SHADOW_BLEND)
        self.shadow.set_depth_write(False)
        self.shadow.set_light_off(1)
        self.shadow.set_bin("fixed", 0)
        self.set_shadow(0.0, 0.0, 0.6)
        self.set_lights(False, False)

    def _make_shadow(self) -> tuple[GeomVertexData, GeomNode]:
        k = self._rings.shape[1]
        vdata = GeomVertexData("shadow", _FORMAT, Geom.UH_dynamic)
        vdata.unclean_set_num_rows(3 * k)
        prim = GeomTriangles(Geom.UH_static)
        for i in range(1, k - 1):  # core fan
            prim.add_vertices(0, i, i + 1)
        for ring in (0, 1):  # strips between rings, counter-clockwise seen from above
            a, b = ring * k, (ring + 1) * k
            for i in range(k):
                j = (i + 1) % k
                prim.add_vertices(a + i, b + i, b + j)
                prim.add_vertices(a + i, b + j, a + j)
        geom = Geom(vdata)
        geom.add_primitive(prim)
        node = GeomNode("shadow")
        node.add_geom(geom)
        return geom.modify_vertex_data(), node

    def set_shadow(self, offset_x: float, offset_y: float, darkness: float) -> None:
        """Stretch the soft shadow from the footprint towards (offset_x, offset_y) and set its darkness.

        The footprint's side facing the offset moves by the full offset (a shadow cast by a sun low in
        that direction); darkness 0..1 gives a core colour multiplier of 1 - 0.75 * darkness, fading to 1
        at the rim. Darkness 0 hides the shadow.
        """
        darkness = min(max(float(darkness), 0.0), 1.0)
        if darkness <= 0.0:
            self.shadow.hide()
            return
        self.shadow.show()
        args = (float(offset_x), float(offset_y), darkness)
        if args == self._shadow_args:  # the same shadow as last frame (a vehicle on a straight lane)
            return
        self._shadow_args = args
        xy = self._shadow_xy
        off = np.array([offset_x, offset_y], np.float64)
        norm = math.sqrt(offset_x * offset_x + offset_y * offset_y)  # as np.linalg.norm does
        if norm > 1e-6:
            d = off / norm
            # vertices on the sun side stay, those on the far side move with the full offset
            t = np.clip((xy @ d) / 0.3 + 0.5, 0.0, 1.0)
            xy = xy + t[:, None] * off[None, :]
        mult = 1.0 - 0.92 * darkness * self._shadow_w
        rec = self._shadow_rec
        rec["pos"][:, :2] = xy
        rec["col"][:, :3] = np.clip(np.rint(mult * 255.0), 0, 255).astype(np.uint8)[:, None]
        memoryview(self._shadow_vdata.modify_array(0)).cast("B")[:] = rec.tobytes()

    def set_lights(self, headlights_on: bool, braking: bool) -> None:
        """Lamps glow (unlit, so bright in darkness) when on; off, they are lit like any other part."""
        state = (bool(headlights_on), bool(braking))
        if state == self._light_state:
            return
        self._light_state = state
        a = self.label / 255.0
        if headlights_on:
            self.headlights.set_color(*HEADLIGHT_ON, a)
            self.headlights.set_light_off(1)
        else:
            self.headlights.clear_color()
            self.headlights.clear_light()
        if braking or headlights_on:
            self.taillights.set_color(*(BRAKE_ON if braking else TAIL_GLOW), a)
            self.taillights.set_light_off(1)
        else:
            self.taillights.clear_color()
            self.taillights.clear_light()

    @property
    def num_triangles(self) -> int:
        """Triangles of the vehicle itself (shadow excluded)."""
        return sum(
            geom.get_primitive(i).get_num_primitives()
            for part in (self.body, self.headlights, self.taillights)
            for geom in part.node().get_geoms()
            for i in range(geom.get_num_primitives())
        )


def build_vehicle_model(make: str, color: tuple[float, float, float], label: int) -> VehicleModel:
    """A vehicle of ``make`` painted ``color`` (sRGB 0..1) whose pixels carry ``label`` in alpha."""
    return VehicleModel(make, color, label)
