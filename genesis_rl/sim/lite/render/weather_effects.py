"""The weather pass: turns a plainly lit Panda3D frame into the picture a camera takes in that weather.

Panda3D draws geometry with fixed-function lighting only; everything the weather does past that is done
here, on the frame's colour, metric depth and labels, with numpy/OpenCV, in a physically sensible order:

1. sky: a horizon-to-zenith gradient by each ray's true elevation, the sun's disk and aureole;
2. wet road: darker asphalt, a blurred mirror reflection about the horizon with a Fresnel weight,
   mirror puddles, and at night vertical streaks under bright vehicle lights;
3. fog (Koschmieder): I = I0 t + A (1 - t), t = exp(-beta_fog max(0, d - fog_distance) - beta_rain d);
4. rain: a grey veil (contrast loss), seeded animated streaks slanted by the wind, lens blur;
5. glare from a low sun: bloom around the sun's image position (also off-screen) and a veiling glare;
6. the camera: auto-exposure (partial), vignetting, gaussian blur, seeded sensor noise (more gain,
   more noise, in the dark), then its tone (saturation, contrast).

Steps 3-5 are all affine in the pixel value, so they are folded into one ``img * gain + offset``; the
smooth fields (sky, bloom) are computed on a coarse grid (a quarter of the resolution or less), the blurry
reflections and light glows at half resolution, and all work buffers are reused. That keeps one ``apply``
within a few milliseconds at 320x240 on two cores, which matters: the RL loop renders every step.

For the renderer: the sky is found by its label (SKY), never by its depth; a frame's sky colour is replaced.
Vehicle lights are pixels of a vehicle label with a channel above 204 at night; they glow and streak.
"""

from __future__ import annotations

import math
from typing import cast

import cv2
import numpy as np

from genesis_rl.sim.lite.render import labels as L
from genesis_rl.sim.lite.render.lighting import CLEAR_AIR_EXTINCTION, Lighting, luminance, smoothstep
from genesis_rl.world.knobs import Weather

#: Depth (m) the sky is fogged as if it were at; the frame's own sky depth is ignored (labels decide).
SKY_FOG_DEPTH_M = 1000.0
#: Path length (m) through fog used to dim the sun's disk and glare (the sun stays visible in thin fog).
SUN_FOG_DEPTH_M = 120.0
#: Floor of the fog/rain optical depth before cv2.exp: below about -87.3, where exp leaves float32's normal
#: range, OpenCV takes a scalar path 60-500x slower (0.85 ms a 320x240 frame of zeros, 6 ms of denormals),
#: which far pixels in fog and rain always hit. exp(-87) = 1.6e-38 for them instead of 0: no pixel changes
#: (frames compared bit for bit in tests/test_weather_effects.py).
_EXP_FLOOR = np.float32(-87.0)
#: Coarse grid for the smooth fields (sky gradient, sun glow, bloom): a quarter of the resolution, at most
#: this many columns.
_COARSE_MAX_W = 112
#: How much brighter than its saturated 8-bit pixel a vehicle light really is (for glow and reflections).
_LIGHT_EXCESS = 4.0
#: Auto-exposure: the scene's light (ambient luma + half the sun's; 0.81 at clear noon) sets a gain
#: (EXPOSURE_LIGHT / light) ** EXPOSURE_ADAPT within EXPOSURE_RANGE: a camera adapts to the light, only
#: partly (noon is unchanged, overcast a little brighter, night stays dark). From the light, not from the
#: frame's mean, so that one region of a frame never changes another's brightness.
EXPOSURE_LIGHT = 0.8
EXPOSURE_ADAPT = 0.2
EXPOSURE_RANGE = (1.0, 1.4)
#: The camera's tone: saturation (HSV S times this) and contrast (this slope about TONE_PIVOT, 0..255), after
#: the sensor noise; the contrast fades in with the scene's light from TONE_LIGHT[0] (none) to TONE_LIGHT[1]
#: (full), so that a night frame is not clipped to black. Measured with the COCO detector at clear noon
#: (docs/realism_render.md): recall at 10-30 m rose with them; applied before the noise (and about the
#: frame's mean) they lowered it, and an S-curve that keeps the shadows lost the gain.
TONE_SATURATION = 0.75
TONE_CONTRAST = 1.25
TONE_PIVOT = 118.0
TONE_LIGHT = (0.15, 0.6)
#: Lens vignetting: brightness falls by this share at the image corners (quadratically with the radius).
VIGNETTE = 0.15
#: Scale of the uint8-coded noise bank (128 + scale * N(0, 1)).
_NOISE_SCALE = 16.0
#: Number of quantised wind slants for which rain streak layers are prebuilt (lazily).
_WIND_BUCKETS = 11


def _rain_layer_specs(height: int) -> tuple[tuple[float, int, int, int, float, float], ...]:
    """Per depth layer: (streaks per 1000 px, min length, max length, thickness, opacity, fall speed)."""
    s = height / 240.0
    return (
        (3.2, max(2, round(4 * s)), max(3, round(9 * s)), 1, 0.10, 0.9),  # far: short, faint
        (1.4, max(4, round(10 * s)), max(6, round(20 * s)), 1, 0.18, 1.6),  # middle
        (0.35, max(8, round(24 * s)), max(12, round(48 * s)), max(1, round(1.5 * s)), 0.26, 2.7),  # near
    )


def exposure_gain(light: float) -> float:
    """The camera's exposure gain in a scene whose light (ambient luma + half the sun's) is ``light``."""
    g = (EXPOSURE_LIGHT / max(light, 1e-3)) ** EXPOSURE_ADAPT
    return float(min(max(g, EXPOSURE_RANGE[0]), EXPOSURE_RANGE[1]))


def tone_curve(light: float) -> np.ndarray:
    """The camera's contrast curve as a uint8 LUT in a scene whose light is ``light``: slope TONE_CONTRAST
    about TONE_PIVOT in daylight, fading to none in dim light (where it would clip the whole frame to black)."""
    k = 1.0 + (TONE_CONTRAST - 1.0) * smoothstep(*TONE_LIGHT, light)
    curve = TONE_PIVOT + k * (np.arange(256, dtype=np.float64) - TONE_PIVOT)
    return np.clip(np.rint(curve), 0, 255).astype(np.uint8)


def _three(plane: np.ndarray, dst: np.ndarray | None = None) -> np.ndarray:
    """A one-channel float image repeated into three channels (OpenCV's GRAY2BGR: the same values as
    ``cv2.merge([plane] * 3)`` in half the time)."""
    return cv2.cvtColor(plane, cv2.COLOR_GRAY2BGR, dst=dst)


class WeatherCompositor:
    """Applies a :class:`Weather` to rendered frames of one camera (fixed resolution and fov).

    Grids that depend only on the resolution (pixel rays, noise bank, rain layers) are built once here.
    """

    def __init__(self, width: int, height: int, fov_deg: float, seed: int, exposure_jitter: float = 0.0) -> None:
        if width < 8 or height < 8:
            raise ValueError(f"image must be at least 8x8, got {width}x{height}")
        if not 1.0 <= fov_deg <= 170.0:
            raise ValueError(f"fov_deg must be in 1..170, got {fov_deg}")
        self.width, self.height, self.fov_deg, self.seed = int(width), int(height), float(fov_deg), int(seed)
        #: the log-sd of each frame's exposure gain (``CameraConfig.exposure_jitter``; 0: the gain is exact)
        self.exposure_jitter = float(exposure_jitter)
        w, h = self.width, self.height
        #: focal length in pixels (square pixels, principal point at the centre)
        self.focal = (w / 2.0) / math.tan(math.radians(fov_deg) / 2.0)

        # Coarse grid of unit rays in the camera frame: right, up, forward components.
        cw = min(-(-w // 4), _COARSE_MAX_W)
        ch = max(2, round(cw * h / w))
        xs = ((np.arange(cw, dtype=np.float64) + 0.5) * (w / cw) - w / 2.0) / self.focal
        ys = ((np.arange(ch, dtype=np.float64) + 0.5) * (h / ch) - h / 2.0) / self.focal
        xn, yn = np.meshgrid(xs, ys)
        inv = 1.0 / np.sqrt(xn * xn + yn * yn + 1.0)
        self._c_right = (xn * inv).astype(np.float32)
        self._c_up = (-yn * inv).astype(np.float32)
        self._c_fwd = inv.astype(np.float32)

        # Per-row normalised image y at the centre column (horizon row, Fresnel, mirror rows).
        self._row_yn = (np.arange(h, dtype=np.float64) + 0.5 - h / 2.0) / self.focal

        rng = np.random.default_rng((self.seed, 0x5EED))
        # Noise bank: a random window of it per step is far cheaper than drawing fresh normals.
        self._noise_pad = (97, 131)
        bank_shape = (h + self._noise_pad[0], w + self._noise_pad[1], 3)
        # stored as 128 + 16 n in uint8, so that the final add is an 8-bit OpenCV fast path
        normal = rng.standard_normal(bank_shape, dtype=np.float32)
        self._noise = np.clip(np.rint(128.0 + _NOISE_SCALE * normal), 0, 255).astype(np.uint8)
        self._rain_rng_seed = int(rng.integers(2**31))
        #: picks the per-step sensor-noise window; set per episode (the banks above stay per camera)
        self.episode_seed = self.seed
        self._rain_cache: dict[int, list[tuple[np.ndarray, np.ndarray, float]]] = {}

        # Vertical one-sided decaying kernel (half resolution): light reflections smear toward the viewer.
        n = max(6, round(h / 2 * 0.22))
        decay = np.exp(-np.arange(n, dtype=np.float32) / (n / 3.0))
        self._streak_kernel = (decay[::-1] / decay.sum() * 2.5).reshape(n, 1).astype(np.float32)

        # Work buffers, reused every call: fresh multi-megabyte arrays would cost page faults each frame.
        f32 = np.float32
        self._img = np.empty((h, w, 3), f32)
        self._off = np.empty((h, w, 3), f32)
        self._g3 = np.empty((h, w, 3), f32)
        self._tmp3 = np.empty((h, w, 3), f32)
        self._tmp3b = np.empty((h, w, 3), f32)
        self._planes = np.empty((h, w, 3), f32)
        self._sky_buf = np.empty((h, w, 3), f32)
        self._b1 = [np.empty((h, w), f32) for _ in range(10)]
        self._zeros = np.zeros((h, w), f32)
        self._half = (max(1, w // 2), max(1, h // 2))
        hw, hh = self._half
        self._lab_h = np.empty((hh, hw), np.uint8)
        self._h3 = [np.empty((hh, hw, 3), f32) for _ in range(5)]
        self._h1 = [np.empty((hh, hw), f32) for _ in range(4)]
        self._row_yn_h = (np.arange(hh, dtype=np.float64) + 0.5 - hh / 2.0) * (h / hh) / self.focal
        self._u8 = np.empty((h, w, 3), np.uint8)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx + 0.5 - w / 2.0) ** 2 + (yy + 0.5 - h / 2.0) ** 2) / ((w / 2.0) ** 2 + (h / 2.0) ** 2)
        self._vignette = _three(1.0 - np.float32(VIGNETTE) * r2)
        self._u8b = np.empty((h, w, 3), np.uint8)
        self._mx = np.empty((h, w), np.uint8)
        self._mx3 = np.empty((h, w, 3), np.uint8)
        self._sky_lut = np.zeros(256, np.float32)
        self._sky_lut[L.SKY] = 1.0
        self._puddle_lut = np.zeros(256, np.float32)
        self._puddle_lut[L.PUDDLE] = 1.0
        # Per label: [coefficient of the road's wet amount, coefficient of the wetness knob].
        road = [L.ROAD, L.LANE_MARKING, L.PUDDLE]
        self._dark_lut = np.zeros((2, 256), np.float32)  # how much darker (0.45: asphalt soaks up)
        self._dark_lut[0, road] = 0.45
        self._dark_lut[0, L.LANE_MARKING] = 0.30  # paint absorbs less water
        self._dark_lut[1, L.SIDEWALK] = 0.25
        self._gloss_lut = np.zeros((2, 256), np.float32)  # reflectivity scale (times Fresnel)
        self._gloss_lut[0, road] = 0.85
        self._gloss_lut[1, L.SIDEWALK] = 0.25

    # ------------------------------------------------------------------ rain
    def _rain_layers(self, wind: float) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """Streak id images (uint8, 255 = none, periodic in y, 2H tall) for one quantised wind slant."""
        bucket = int(round(min(100.0, max(0.0, wind)) / 100.0 * (_WIND_BUCKETS - 1)))
        cached = self._rain_cache.get(bucket)
        if cached is not None:
            return cached
        w, h = self.width, self.height
        slant = math.radians(4.0 + 36.0 * bucket / (_WIND_BUCKETS - 1))  # from vertical, wind pushes right
        rng = np.random.default_rng((self._rain_rng_seed, bucket))
        layers = []
        for density, lmin, lmax, thick, opacity, speed in _rain_layer_specs(h):
            count = max(1, round(density * w * h / 1000.0))
            canvas = np.full((3 * h, w), 255, np.uint8)
            ids = rng.integers(0, 255, count)
            x0 = rng.uniform(-0.3 * w, 1.3 * w, count)
            y0 = rng.uniform(h, 2 * h, count)
            length = rng.uniform(lmin, lmax, count)
            dx, dy = np.sin(slant) * length, np.cos(slant) * length
            for i in range(count):
                p0 = (int(x0[i]), int(y0[i]))
                p1 = (int(x0[i] + dx[i]), int(y0[i] + dy[i]))
                cv2.line(canvas, p0, p1, int(ids[i]), thick, cv2.LINE_8)
            # Fold the 3h canvas onto a period of h (lines crossing the seams wrap), then tile twice.
            period = np.minimum(np.minimum(canvas[:h], canvas[h : 2 * h]), canvas[2 * h :])
            tiled = np.ascontiguousarray(np.vstack([period, period]))
            alpha = (rng.uniform(0.45, 1.0, 256) * opacity).astype(np.float32)
            alpha[255] = 0.0
            layers.append((tiled, alpha, speed))
        self._rain_cache[bucket] = layers
        return layers

    def _rain_alpha(self, precip: float, wind: float, step: int) -> np.ndarray:
        """Per-pixel streak opacity for this step: more and more opaque streaks as the rain grows."""
        h = self.height
        out, tmp = self._b1[6], self._b1[7]
        cut = int(precip * 255.0)
        gain = 0.5 + 0.5 * precip
        for k, (ids, alpha, speed) in enumerate(self._rain_layers(wind)):
            lut = np.zeros(256, np.float32)
            lut[:cut] = alpha[:cut] * gain
            off = int((step * speed * 0.61 * h + k * 0.37 * h) % h)
            if k == 0:
                cv2.LUT(ids[off : off + h], lut, dst=out)
            else:
                cv2.LUT(ids[off : off + h], lut, dst=tmp)
                np.add(out, tmp, out=out)
        return np.minimum(out, 0.8, out=out)

    # ------------------------------------------------------------------ main
    def apply(
        self,
        rgb: np.ndarray,
        depth: np.ndarray,
        labels: np.ndarray,
        weather: Weather,
        lighting: Lighting,
        camera_yaw: float,
        camera_pitch: float,
        step: int,
    ) -> np.ndarray:
        """The frame as the camera sees it in ``weather``; a new uint8 (H, W, 3) array, inputs untouched.

        Deterministic in (seed, step): noise and rain streaks are drawn from them alone.
        """
        h, w = self.height, self.width
        if rgb.shape != (h, w, 3) or depth.shape != (h, w) or labels.shape != (h, w):
            raise ValueError(
                f"expected rgb ({h}, {w}, 3), depth and labels ({h}, {w}); got {rgb.shape}, "
                f"{depth.shape}, {labels.shape}"
            )
        lab = labels if labels.dtype == np.uint8 else labels.astype(np.uint8)
        img = self._img
        np.copyto(img, rgb, casting="unsafe")

        precip = float(weather["precipitation"]) / 100.0
        deposits = float(weather["precipitation_deposits"]) / 100.0
        wetness = float(weather["wetness"]) / 100.0
        wind = float(weather["wind_intensity"])
        fog_distance = float(weather["fog_distance"])
        alt = math.degrees(math.asin(max(-1.0, min(1.0, lighting.sun_direction[2]))))
        cover = lighting.cloud_cover

        # Camera basis in the world (x east, y north, z up); yaw CCW from +x, pitch positive up.
        cy_, sy_ = math.cos(camera_yaw), math.sin(camera_yaw)
        cp, sp = math.cos(camera_pitch), math.sin(camera_pitch)
        right = (sy_, -cy_, 0.0)
        up = (-sp * cy_, -sp * sy_, cp)
        fwd = (cp * cy_, cp * sy_, sp)
        sun = lighting.sun_direction

        def dot(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
            return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

        s_r, s_u, s_f = dot(right, sun), dot(up, sun), dot(fwd, sun)

        # Extinction beyond what the sky colours already contain (clear-air haze is part of them).
        beta_f, beta_r = lighting.fog_extinction, lighting.rain_extinction
        beta_excess = max(0.0, beta_f - CLEAR_AIR_EXTINCTION) + beta_r
        t_sun = math.exp(-beta_excess * SUN_FOG_DEPTH_M)
        fog_a = np.array(lighting.fog_color, np.float32) * 255.0

        sun_hue = np.array(lighting.sun_color, np.float64) + 0.3 * np.array(lighting.sky_horizon)
        sun_hue = (sun_hue / max(1e-6, float(sun_hue.max()))).astype(np.float32)

        # Glare from a low sun (lens effect): bloom field and veiling glare.
        glare_w = (
            smoothstep(-2.0, 1.0, alt) * (1.0 - smoothstep(6.0, 25.0, alt)) * (1.0 - cover) ** 1.5 * t_sun
        )

        # ---------------------------------------------------------- 1. sky (coarse grid)
        sky_mask = lab == L.SKY
        sky_rows = np.flatnonzero(sky_mask.any(axis=1))
        need_bloom = glare_w > 1e-3
        bloom_full: np.ndarray | None = None
        if sky_rows.size or need_bloom:
            sin_el = self._c_up * cp + self._c_fwd * sp
            one_m_cos = 1.0 - (self._c_right * s_r + self._c_up * s_u + self._c_fwd * s_f)
            np.maximum(one_m_cos, 0.0, out=one_m_cos)
            if sky_rows.size:
                sky_full = self._sky(sin_el, one_m_cos, lighting, alt, cover, beta_excess, t_sun, sun_hue)
                ys = slice(int(sky_rows[0]), int(sky_rows[-1]) + 1)
                cv2.copyTo(sky_full[ys], sky_mask[ys].view(np.uint8), img[ys])
            if need_bloom:
                bloom = (
                    0.9 * np.exp(one_m_cos * np.float32(-1.0 / 0.0015))
                    + 0.30 * np.exp(one_m_cos * np.float32(-1.0 / 0.015))
                    + 0.10 * np.exp(one_m_cos * np.float32(-1.0 / 0.12))
                )
                bloom *= np.float32(glare_w * 255.0)
                bloom_full = cv2.resize(bloom, (w, h), dst=self._b1[5], interpolation=cv2.INTER_LINEAR)

        # Half-resolution labels: lights, reflections and their streaks are computed at half resolution.
        hw, hh = self._half
        lab_h = cv2.resize(lab, (hw, hh), dst=self._lab_h, interpolation=cv2.INTER_NEAREST)
        # Night: bright vehicle lights (a near-saturated channel, so red tail lights count).
        lights = self._bright_lights(rgb, lab, lab_h) if lighting.headlight_strength > 0.05 else None

        # ---------------------------------------------------------- 3. fog transmittance, 4. rain
        b = self._b1
        d = depth if depth.dtype == np.float32 else depth.astype(np.float32)
        t = b[0]
        if fog_distance > 0.0:
            np.subtract(d, np.float32(fog_distance), out=t)
            np.maximum(t, 0.0, out=t)
            np.multiply(t, np.float32(-beta_f), out=t)
            if beta_r > 0.0:
                np.multiply(d, np.float32(beta_r), out=b[1])
                np.subtract(t, b[1], out=t)
        else:
            np.multiply(d, np.float32(-(beta_f + beta_r)), out=t)
        np.maximum(t, _EXP_FLOOR, out=t)  # see _EXP_FLOOR: the same frame, without OpenCV's slow path
        cv2.exp(t, dst=t)
        if sky_rows.size:
            # the sky was fogged on the coarse grid already
            np.maximum(t, cv2.LUT(lab, self._sky_lut, dst=b[1]), out=t)

        veil = 0.25 * precip**1.2  # rain veil: contrast loss toward a grey lit by the sky
        veil_col = fog_a * 0.9
        vg = 0.35 * glare_w * max(0.0, s_f) ** 2  # veiling glare, larger when looking toward the sun
        glare_col = sun_hue * 255.0
        streak = self._rain_alpha(precip, wind, step) if precip > 0.01 else None
        streak_col = (
            np.array(lighting.sky_horizon, np.float32) * 0.35
            + luminance(lighting.ambient_color) * 0.6
            + luminance(lighting.sun_color) * 0.35
        )
        streak_col = np.clip(streak_col * np.float32(255.0 * 1.25), 0.0, 255.0)

        # out = img * gain + offset, offset = const + P1 cA + P2 (cC - cG) + P3 cS (see module docstring)
        k_veil, k_glare = 1.0 - veil, 1.0 - vg
        c_a = k_glare * k_veil * fog_a
        c_g = k_glare * veil * veil_col
        const = c_g + vg * glare_col
        gain, p1 = b[2], b[3]
        if streak is not None:
            one_m_a = np.subtract(1.0, streak, out=b[4])
            np.multiply(t, one_m_a, out=gain)
            np.subtract(one_m_a, gain, out=p1)  # (1 - a)(1 - t)
        else:
            np.copyto(gain, t)
            np.subtract(1.0, t, out=p1)
        np.multiply(gain, np.float32(k_veil * k_glare), out=gain)
        m = np.zeros((3, 4), np.float32)
        m[:, 0] = c_a
        m[:, 1] = k_glare * streak_col - c_g
        m[:, 2] = sun_hue
        m[:, 3] = const
        zeros = self._zeros
        planes = [p1, zeros if streak is None else streak, zeros if bloom_full is None else bloom_full]
        cv2.merge(planes, dst=self._planes)
        offset = cv2.transform(self._planes, m, dst=self._off)  # 3 -> 3 channels: OpenCV's fast path

        # ---------------------------------------------------------- 2. wet road, puddles
        # Darkening multiplies the full-resolution gain; the (blurry) reflections are added at half
        # resolution, already multiplied by the fog/rain gain: they fade into the fog like their road.
        wet_road = max(deposits, 0.75 * wetness)
        puddle_s = smoothstep(0.2, 0.7, deposits)
        extra_h: np.ndarray | None = None
        if wet_road > 0.01 or wetness > 0.01:
            extra_h = self._wet(img, lab, lab_h, gain, lighting, wet_road, wetness, puddle_s, cp, sp, lights)
        if lights is not None:
            # An 8-bit light is far dimmer than a real lamp; give lights their excess brightness back so that
            # they stay visible through fog (attenuated by the gain) and glow: forward scattering spreads
            # them into halos, larger the denser the air.
            gain_h = cv2.resize(gain, (hw, hh), dst=self._h1[3], interpolation=cv2.INTER_AREA)
            src: np.ndarray = cv2.multiply(lights, _three(gain_h), dst=self._h3[4])
            src *= np.float32(_LIGHT_EXCESS * lighting.headlight_strength)
            haze = 1.0 - math.exp(-beta_excess * 30.0)
            quarter = cv2.resize(src, (w // 4, h // 4), interpolation=cv2.INTER_AREA)
            halo = cv2.GaussianBlur(quarter, (0, 0), max(0.7, h * 0.006))
            halo = cv2.resize(halo, (hw, hh), interpolation=cv2.INTER_LINEAR)
            cv2.scaleAdd(halo, 0.15 + 1.2 * haze, src, dst=src)
            if extra_h is None:
                extra_h = src
            else:
                cv2.add(extra_h, src, dst=extra_h)
        if extra_h is not None:
            up_extra = cv2.resize(extra_h, (w, h), dst=self._tmp3, interpolation=cv2.INTER_LINEAR)
            cv2.add(offset, up_extra, dst=offset)

        cv2.multiply(img, _three(gain, self._g3), dst=img)
        cv2.add(img, offset, dst=img)

        # ---------------------------------------------------------- 6. camera
        # Exposure that adapts (partly) to the scene's light, and lens vignetting: one multiply.
        light = luminance(lighting.ambient_color) + 0.5 * luminance(lighting.sun_color)
        # the world's draws of this frame: the noise window first (the order of every version before), then
        # the exposure's jitter, drawn only when the camera has one, so a camera without it is unchanged
        rng = np.random.default_rng((self.episode_seed, int(step)))
        oy = int(rng.integers(self._noise_pad[0]))
        ox = int(rng.integers(self._noise_pad[1]))
        exposure = exposure_gain(light)
        if self.exposure_jitter > 0.0:
            exposure *= math.exp(self.exposure_jitter * float(rng.standard_normal()))
        cv2.multiply(img, self._vignette, dst=img, scale=exposure)
        # 8-bit from here: OpenCV's fixed-point blur is twice as fast; every value is >= 0, so the abs
        # of convertScaleAbs is a plain rounding, saturating cast.
        u8 = cv2.convertScaleAbs(img, dst=self._u8)
        sigma_blur = 0.8 + 0.8 * precip**2  # droplets on the lens soften heavy rain
        ksize = 2 * math.ceil(2.5 * sigma_blur) + 1
        u8 = cv2.GaussianBlur(u8, (ksize, ksize), sigma_blur, dst=self._u8b)
        sigma_noise = 4.0 + 4.5 * (1.0 - smoothstep(0.06, 0.35, light))  # dark scene: more gain, more noise
        noise = self._noise[oy : oy + h, ox : ox + w]
        k = sigma_noise / _NOISE_SCALE
        raw = cv2.addWeighted(u8, 1.0, noise, k, -128.0 * k, dst=self._u8)
        # The camera's processing of its sensor's values: less saturation (HSV S times TONE_SATURATION,
        # hue and value kept: each channel moves towards the pixel's maximum), then a contrast curve.
        ch_r, ch_g, ch_b = cv2.split(raw)
        mx = cv2.max(cv2.max(ch_r, ch_g, dst=self._mx), ch_b, dst=self._mx)
        mixed = cv2.addWeighted(raw, TONE_SATURATION, _three(mx, self._mx3), 1.0 - TONE_SATURATION, 0.0)
        return cv2.LUT(mixed, tone_curve(light))  # 256 entries: ~10 us a frame

    # ------------------------------------------------------------------ helpers
    def _sky(
        self,
        sin_el: np.ndarray,
        one_m_cos: np.ndarray,
        lighting: Lighting,
        alt: float,
        cover: float,
        beta_excess: float,
        t_sun: float,
        sun_hue: np.ndarray,
    ) -> np.ndarray:
        """Full-resolution sky radiance (0..255 float32): gradient, aureole, disk, then fog.

        Computed per channel on the coarse grid (numpy broadcasting over a 3-long axis is slow), then merged.
        """
        tz = np.sqrt(np.clip(sin_el, 0.0, 1.0))
        # Mie aureole around the sun (also glows a little after sunset), weaker through clouds.
        aureole_w = smoothstep(-10.0, 2.0, alt) * (0.2 + 0.8 * (1.0 - cover)) * (
            0.35 + 0.65 * (1.0 - smoothstep(5.0, 60.0, alt))
        )
        t_sky = math.exp(-beta_excess * SKY_FOG_DEPTH_M)
        # Fog: the sky tends to the airlight; forward scattering keeps a bright patch around the sun.
        glow_k = aureole_w * 255.0 * (t_sky + (1.0 - t_sky) * 0.6 * t_sun**0.3)
        halo = np.exp(one_m_cos * np.float32(-1.0 / 0.02)) * np.float32(0.45 * glow_k)
        halo += np.exp(one_m_cos * np.float32(-1.0 / 0.25)) * np.float32(0.18 * glow_k)
        # The disk: hidden below the horizon and behind clouds, seen through thin fog.
        disk_w = smoothstep(-1.5, 1.0, alt) * (1.0 - cover) ** 2 * t_sun
        if disk_w > 1e-3:
            disk = np.exp(np.maximum(one_m_cos, 0.0) * np.float32(-1.0 / 0.0002))
            disk *= np.float32(disk_w * 255.0 * 3.0)
            disk[sin_el < -0.003] = 0.0
            halo += disk
        chans = []
        for c in range(3):
            zen, hor = lighting.sky_zenith[c] * 255.0, lighting.sky_horizon[c] * 255.0
            fog_a = lighting.fog_color[c] * 255.0
            # fog_a + (hor + (zen - hor) tz - fog_a) t_sky + halo * hue
            base = fog_a + (hor - fog_a) * t_sky
            ch = tz * np.float32((zen - hor) * t_sky)
            ch += np.float32(base)
            ch += halo * sun_hue[c]
            chans.append(ch)
        sky = cv2.merge(chans)
        return cv2.resize(sky, (self.width, self.height), dst=self._sky_buf, interpolation=cv2.INTER_LINEAR)

    def _bright_lights(self, rgb: np.ndarray, lab: np.ndarray, lab_h: np.ndarray) -> np.ndarray | None:
        """Half-resolution float image of the vehicles' lights only, or None when no light is on screen.

        Detected at full resolution (a far lamp may be one pixel), then area-averaged, which keeps its energy.
        """
        if not (lab_h >= L.VEHICLE_BASE).any():
            return None
        r, g, b = cv2.split(rgb)
        mask = ((cv2.max(cv2.max(r, g), b) > 204) & (lab >= L.VEHICLE_BASE)).view(np.uint8)
        if cv2.countNonZero(mask) == 0:
            return None
        lit = cv2.bitwise_and(rgb, rgb, mask=mask)
        return cv2.resize(lit, self._half, interpolation=cv2.INTER_AREA).astype(np.float32)

    def _fresnel(self, row_yn: np.ndarray, cp: float, sp: float) -> np.ndarray:
        """Schlick's Fresnel term of water (n = 1.33) per row (a column), by the ray's depression angle."""
        depress = np.clip((row_yn * cp - sp) / np.sqrt(1.0 + row_yn * row_yn), 0.0, 1.0)
        return (0.02 + 0.98 * (1.0 - depress) ** 5).astype(np.float32)[:, None]

    def _wet(
        self,
        img: np.ndarray,
        lab: np.ndarray,
        lab_h: np.ndarray,
        gain: np.ndarray,
        lighting: Lighting,
        wet_road: float,
        wetness: float,
        puddle_s: float,
        cp: float,
        sp: float,
        lights: np.ndarray | None,
    ) -> np.ndarray | None:
        """Wet surfaces below the horizon: multiplies ``gain`` (in place) by the darkening and the loss to
        reflection; returns the half-resolution reflection image (times the half-resolution gain), or None.

        Per pixel: out = base * wb + (0.8 blur(mirror) + 0.2 horizon) * refl + mirror * ws, where mirror
        samples row 2 * horizon - y and ws is a puddle's sharp mirror.
        """
        h = self.height
        hw, hh = self._half
        horizon = h / 2.0 + self.focal * (sp / max(cp, 1e-6)) - 0.5  # row index of the horizon
        y0 = max(0, int(math.floor(horizon)) + 1)
        if y0 >= h - 1:
            return None
        b = self._b1
        dark_lut = self._lut(self._dark_lut, wet_road, wetness)
        gloss_lut = self._lut(self._gloss_lut, wet_road, wetness)
        sub_lab = lab[y0:]
        hs = h - y0
        gloss = cv2.LUT(sub_lab, gloss_lut, dst=b[8][:hs])
        if cv2.countNonZero(gloss) == 0:
            return None
        # Full resolution: darkening and the light lost to reflection.
        wb: np.ndarray = cv2.LUT(sub_lab, dark_lut, dst=b[9][:hs])
        np.subtract(1.0, wb, out=wb)
        fresnel = self._fresnel(self._row_yn[y0:], cp, sp)
        refl = np.multiply(gloss, fresnel, out=gloss)
        np.subtract(1.0, refl, out=refl)
        np.multiply(wb, refl, out=wb)
        has_puddles = puddle_s > 0.0 and bool((lab_h == L.PUDDLE).any())
        if has_puddles:
            pm: np.ndarray = cv2.LUT(sub_lab, self._puddle_lut, dst=b[8][:hs])
            pm *= np.float32(puddle_s)
            rp = 0.6 + 0.4 * fresnel
            wb *= 1.0 - pm
            wb += pm * (0.25 * (1.0 - rp))
        # Half resolution: the reflection itself (times the fog/rain gain, taken before the darkening).
        hz = (horizon + 0.5) / 2.0 - 0.5
        y0h = max(0, int(math.floor(hz)) + 1)
        hsh = hh - y0h
        h1 = self._h1
        gain_h = cv2.resize(gain, (hw, hh), dst=h1[3], interpolation=cv2.INTER_AREA)[y0h:]
        g = gain[y0:]
        np.multiply(g, wb, out=g)
        img_h = cv2.resize(img, (hw, hh), dst=self._h3[0], interpolation=cv2.INTER_AREA)
        sub_lab_h = lab_h[y0h:]
        gloss_h = cv2.LUT(sub_lab_h, gloss_lut, dst=h1[0][:hsh])
        fresnel_h = self._fresnel(self._row_yn_h[y0h:], cp, sp)
        refl_h = np.multiply(gloss_h, fresnel_h, out=h1[1][:hsh])
        mirror_rows = np.clip(np.rint(2.0 * hz - np.arange(y0h, hh)).astype(np.intp), 0, hh - 1)
        sharp = np.take(img_h, mirror_rows, axis=0, out=self._h3[1][:hsh])
        # Rough asphalt: reflections smear mostly vertically (a sun or a lamp becomes a streak).
        mirror: np.ndarray = cv2.blur(sharp, (3, max(3, (hh // 24) | 1)), dst=self._h3[2][:hsh])
        mirror *= np.float32(0.8)
        hor = [c * 0.2 * 255.0 for c in lighting.sky_horizon]
        # OpenCV takes a Scalar (a 4-tuple) as src2; its stubs admit only arrays there
        cv2.add(mirror, cast("cv2.typing.MatLike", (hor[0], hor[1], hor[2], 0.0)), dst=mirror)
        if has_puddles:
            pm_h: np.ndarray = cv2.LUT(sub_lab_h, self._puddle_lut, dst=h1[2][:hsh])
            pm_h *= np.float32(puddle_s)
            refl_h *= 1.0 - pm_h
            ws = np.multiply(pm_h, 0.6 + 0.4 * fresnel_h, out=pm_h)
            cv2.multiply(sharp, _three(ws), dst=sharp)
        cv2.multiply(mirror, _three(refl_h), dst=mirror)
        if has_puddles:
            cv2.add(mirror, sharp, dst=mirror)

        # Night: vertical streaks of vehicle lights on the wet road (a one-sided vertical blur downward).
        if lights is not None and wet_road > 0.05:
            n = self._streak_kernel.shape[0]
            sm = cv2.filter2D(
                lights, -1, self._streak_kernel, anchor=(0, n - 1), borderType=cv2.BORDER_CONSTANT
            )[y0h:]
            k_streak = np.float32(_LIGHT_EXCESS * lighting.headlight_strength / 0.85)
            k = np.multiply(gloss_h, k_streak, out=gloss_h)
            cv2.multiply(sm, _three(k), dst=sm)
            cv2.add(mirror, sm, dst=mirror)

        cv2.multiply(mirror, _three(gain_h), dst=mirror)
        extra = self._h3[3]
        extra[:y0h] = 0.0
        extra[y0h:] = mirror
        return extra

    @staticmethod
    def _lut(base: np.ndarray, wet_road: float, wetness: float) -> np.ndarray:
        """A per-label LUT from its (road coefficient, sidewalk coefficient) rows."""
        return (base[0] * np.float32(wet_road) + base[1] * np.float32(wetness)).astype(np.float32)
