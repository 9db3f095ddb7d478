"""Synthetic underwater net renderer with exact ground truth.

A flat net (square or rhombic mesh of twine) is placed at a known pose in front of a known,
distorted camera and rendered over an underwater-looking scene: light gradient, caustics, sun
rays, marine snow, fish behind and (optionally) in front of the net, blur and sensor noise.

What real fish-farm footage adds (all off by default, drawn together by `SceneStyle.realistic`):
biofouling (thick, uneven, furry and often light twine, fouled patches that fill the cells),
seams and ropes on the net, marker boards in front of it, a net that billows instead of being a
plane, turbidity (veiling light and backscatter), uneven artificial light, motion blur and JPEG
compression. Non-net grids (pool tiles, a brick wall, a checkerboard) can replace the net, with the
same pose geometry, to test what the estimator must refuse.

Anti-aliasing is analytic instead of by brute-force supersampling: each twine family is a pulse
train in lattice coordinates, and its coverage of a pixel is the exact box-filtered pulse train
over the pixel's footprint in that coordinate. That keeps long-range renders (twine narrower than
a pixel, mesh period of a few pixels) free of aliasing at the cost of one render per frame.

The renderer is used by the tests, the benchmarks and the `synthetic:` frame source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.core.mesh import MeshGeometry

FloatMap = npt.NDArray[np.float64]
Gray = npt.NDArray[np.uint8]


class TwineCut(Protocol):
    """Damage to the net (cut bars, missing knots, torn holes; drivers/synthetic_damage.py):
    given the lattice coordinates of every pixel (s1, s2: knots at integers, the bars of the
    first family along s1 = const, the second along s2 = const), the fraction of each family's
    twine that is still there (1 = intact, 0 = cut away)."""

    def __call__(self, s1: FloatMap, s2: FloatMap) -> tuple[FloatMap, FloatMap]: ...


@dataclass(frozen=True)
class NetPose:
    """Where the net plane is, seen from the camera.

    The plane crosses the optical axis at `range_m`. Its normal is tilted by `tilt_deg` away
    from the optical axis, about an axis lying in the image plane at `tilt_axis_deg` from the
    image x axis. `roll_deg` rotates the mesh within its plane; `phase` shifts it (in cells).
    """

    range_m: float
    tilt_deg: float = 0.0
    tilt_axis_deg: float = 0.0
    roll_deg: float = 0.0
    phase: tuple[float, float] = (0.0, 0.0)

    def rotation(self) -> FloatMap:
        """Rotation taking net-plane axes (u, v, n_away) into camera axes."""
        roll = math.radians(self.roll_deg)
        c, s = math.cos(roll), math.sin(roll)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        phi = math.radians(self.tilt_axis_deg)
        axis = np.array([math.cos(phi), math.sin(phi), 0.0])
        tilt = math.radians(self.tilt_deg)
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        r_tilt = np.eye(3) + math.sin(tilt) * k + (1 - math.cos(tilt)) * (k @ k)
        return np.asarray(r_tilt @ rz, dtype=np.float64)

    def normal_towards_camera(self) -> FloatMap:
        return np.asarray(-self.rotation()[:, 2], dtype=np.float64)

    def distance_m(self) -> float:
        """Perpendicular distance from the camera centre to the plane."""
        away = self.rotation()[:, 2]
        return float(self.range_m * away[2])


@dataclass(frozen=True)
class GroundTruth:
    net_present: bool
    range_m: float
    distance_m: float
    normal: tuple[float, float, float]
    tilt_deg: float
    pose: NetPose
    occluded_fraction: float = 0.0
    # A billowing net: rms distance of the visible surface from the plane reported above (the
    # least-squares plane through it).
    billow_rms_m: float = 0.0


@dataclass(frozen=True)
class SceneStyle:
    """Look of the water, light and clutter. All intensities are in 0..1."""

    net_present: bool = True
    water_level: float = 0.45
    vertical_gradient: float = 0.25
    blotches: float = 0.08
    caustics: float = 0.12
    sun_rays: float = 0.06
    snow_per_mpx: float = 300.0
    fish_behind: int = 3
    fish_front_cover: float = 0.0
    twine_level: float = 0.12
    twine_width_m: float = 0.0018
    attenuation_per_m: float = 0.25
    blur_sigma_px: float = 0.6
    noise_sigma: float = 0.012
    vignetting: float = 0.25
    # -- realism of real footage (0 / None = off) --
    # Twine width as a fraction of the bar length (overrides twine_width_m when > 0): real nets'
    # twine is 10-30 % of the bar, more when fouled.
    twine_fraction: float = 0.0
    # Clutter of a few pixels' scale over the whole view (growth, particles, texture of what is
    # behind the net), amplitude in 0..1 intensity.
    texture: float = 0.0
    # Biofouling, 0 clean .. 1 heavy: twine up to ~3x thicker and uneven along the bars, furry
    # (fine texture around the twine), fouled patches that fill the cells; fouled twine is light.
    fouling: float = 0.0
    seams: int = 0  # seams: a mesh row of much thicker twine
    # The net's own identity: with a seed, its fouling (thickness, fouled patches, pale growth)
    # and its seams are drawn from it at the net's lattice coordinates, so they stay at their
    # place on the net from frame to frame, as on a real net an ROV passes along. Without one
    # they are drawn anew for every frame, over the view (the integrity benchmark's independent
    # frames). The fine fuzz, ropes, boards, billows and fish are drawn per frame either way.
    net_seed: int | None = None
    ropes: int = 0  # ropes lying on the net, at any angle
    boards: int = 0  # marker boards (dark panel, white fiducial) in front of the net
    # Net billowing: displacement along the normal, amplitude as a fraction of the distance, with
    # this wavelength on the net (zero mean over the view: the ground truth is the mean plane).
    billow: float = 0.0
    billow_wavelength_m: float = 1.5
    turbidity: float = 0.0  # 0..1: veiling light, extra attenuation, backscatter blobs
    spotlight: float = 0.0  # 0..1: the ROV's lamps, bright centre falling off to the edges
    motion_blur_px: float = 0.0  # length of a linear motion blur
    # Defocus: a thin lens focused at `focus_m` with this aperture diameter blurs a net at range
    # z by a circle of confusion of f * aperture * |1/z - 1/focus| pixels (0 = always sharp).
    focus_m: float = 0.0
    aperture_m: float = 0.003
    jpeg_quality: int = 0  # 0 = none; else the JPEG quality the frame is compressed at
    # What is in front of the camera: "net", or a grid that is not a net ("tiles", "bricks",
    # "checkerboard") on the same plane, `pattern_size_m` the tile / brick height / square side
    # (0 = the mesh's bar length), `grout_fraction` the grout (mortar) width over that size.
    pattern: str = "net"
    pattern_size_m: float = 0.0
    grout_fraction: float = 0.08

    @staticmethod
    def varied(rng: np.random.Generator, **overrides: object) -> SceneStyle:
        """A plausible random scene: the benchmark and the synthetic source draw from this."""
        style = SceneStyle(
            water_level=float(rng.uniform(0.3, 0.6)),
            vertical_gradient=float(rng.uniform(0.05, 0.35)),
            blotches=float(rng.uniform(0.02, 0.12)),
            caustics=float(rng.uniform(0.0, 0.2)),
            sun_rays=float(rng.uniform(0.0, 0.1)),
            snow_per_mpx=float(rng.uniform(0, 600)),
            fish_behind=int(rng.integers(0, 6)),
            twine_level=float(rng.uniform(0.05, 0.2)),
            twine_width_m=float(rng.uniform(0.0014, 0.0024)),
            attenuation_per_m=float(rng.uniform(0.15, 0.35)),
            blur_sigma_px=float(rng.uniform(0.4, 1.0)),
            noise_sigma=float(rng.uniform(0.005, 0.02)),
            vignetting=float(rng.uniform(0.1, 0.35)),
        )
        return replace(style, **overrides)  # type: ignore[arg-type]

    @staticmethod
    def realistic(rng: np.random.Generator, **overrides: object) -> SceneStyle:
        """A scene with the look of real fish-farm footage: `varied` plus fouling, seams, ropes,
        boards, billowing, turbidity, lamps, motion blur and JPEG, each drawn independently.

        The ranges follow what the real SOLAQUA frames show (see `netpose bench integrity`, which
        prints real and rendered frames' statistics side by side): light, fouled twine as often
        as dark clean twine, mesh contrast from a few grey levels up, JPEG at quality 50-95.
        """
        base = SceneStyle.varied(rng)
        light_twine = rng.random() < 0.5
        fouling = float(rng.choice([0.0, rng.uniform(0.1, 0.5), rng.uniform(0.5, 1.0)]))
        style = replace(
            base,
            twine_level=float(rng.uniform(0.65, 0.95) if light_twine else base.twine_level),
            fouling=fouling,
            seams=int(rng.random() < 0.25),
            ropes=int(rng.random() < 0.25),
            boards=int(rng.choice([0, 0, 0, 1, 2])),
            twine_fraction=float(rng.uniform(0.1, 0.35)),
            texture=float(rng.uniform(0.02, 0.12)),
            noise_sigma=float(rng.uniform(0.008, 0.025)),
            billow=float(rng.choice([0.0, rng.uniform(0.0, 0.03)])),
            billow_wavelength_m=float(rng.uniform(0.6, 3.0)),
            turbidity=float(rng.choice([0.0, rng.uniform(0.0, 0.6)])),
            spotlight=float(rng.choice([0.0, rng.uniform(0.0, 0.8)])),
            motion_blur_px=float(rng.choice([0.0, rng.uniform(0.0, 4.0)])),
            focus_m=float(rng.uniform(0.8, 3.0)),
            aperture_m=float(rng.uniform(0.0015, 0.004)),
            jpeg_quality=int(rng.choice([0, int(rng.integers(50, 96))])),
            fish_front_cover=float(rng.choice([0.0, 0.0, 0.0, rng.uniform(0.05, 0.35)])),
        )
        return replace(style, **overrides)  # type: ignore[arg-type]


class NetRenderer:
    """Renders frames of a flat net for one camera; per-pixel rays are computed once."""

    def __init__(self, camera: CameraModel, mesh: MeshGeometry, seed: int = 0) -> None:
        self.camera = camera
        self.mesh = mesh
        self._rng = np.random.default_rng(seed)
        h, w = camera.height, camera.width
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        rays = camera.undistort_pixels(np.stack([u, v], axis=-1))
        self._rx = np.ascontiguousarray(rays[..., 0])
        self._ry = np.ascontiguousarray(rays[..., 1])
        yy = (v - camera.cy) / camera.height
        xx = (u - camera.cx) / camera.width
        self._radial2 = xx * xx + yy * yy
        self._vertical = v / max(h - 1, 1)

    # -- public ---------------------------------------------------------------------------------
    def render(
        self,
        pose: NetPose,
        rng: np.random.Generator | None = None,
        style: SceneStyle | None = None,
        damage: TwineCut | None = None,
    ) -> tuple[Gray, GroundTruth]:
        rng = self._rng if rng is None else rng
        style = SceneStyle() if style is None else style
        image = self._background(style, rng)
        if style.pattern == "net":
            self._draw_fish(image, rng, style.fish_behind, dark=True)
        plane: tuple[FloatMap, float, float] | None = None
        net_present = style.net_present and style.pattern == "net"
        if style.pattern != "net":
            self._draw_surface(image, pose, style, rng)
        elif style.net_present:
            plane = self._draw_net(image, pose, style, rng, damage)
        if style.texture > 0:
            w = self.camera.width
            image += style.texture * (0.6 * self._smooth_field(rng, max(4, w // 6))
                                      + 0.4 * self._smooth_field(rng, max(4, int(w / 2.5))))
        occluded = 0.0
        if style.boards > 0:
            occluded += self._draw_boards(image, rng, style.boards)
        if style.fish_front_cover > 0:
            occluded += self._draw_front_fish(image, rng, style.fish_front_cover)
        if style.turbidity > 0:
            self._turbid_water(image, style, rng)
        image *= 1.0 - style.vignetting * self._radial2 * 2.0
        if style.spotlight > 0:
            image *= self._lamps(style.spotlight, rng)
        if style.focus_m > 0:
            # Defocus at the range where the optical axis meets the net (the circle of confusion's
            # diameter in pixels; a Gaussian of a third of it is a fair stand-in for the disc).
            f = math.sqrt(self.camera.fx * self.camera.fy)
            coc = f * style.aperture_m * abs(1.0 / pose.range_m - 1.0 / style.focus_m)
            style = replace(style, blur_sigma_px=math.hypot(style.blur_sigma_px, coc / 3.0))
        frame = self._camera_effects(image, style, rng)
        normal = pose.normal_towards_camera()
        range_m, distance_m, billow_rms = pose.range_m, pose.distance_m(), 0.0
        if plane is not None:  # a billowing net: the truth is its best plane over the view
            normal, distance_m, billow_rms = plane
            range_m = distance_m / float(-normal[2])
        truth = GroundTruth(
            net_present=net_present,
            range_m=range_m,
            distance_m=distance_m,
            normal=(float(normal[0]), float(normal[1]), float(normal[2])),
            tilt_deg=(
                abs(pose.tilt_deg) if plane is None
                else math.degrees(math.acos(min(1.0, abs(float(normal[2])))))
            ),
            pose=pose,
            occluded_fraction=min(1.0, occluded),
            billow_rms_m=billow_rms,
        )
        return frame, truth

    # -- scene pieces ---------------------------------------------------------------------------
    def _smooth_field(
        self, rng: np.random.Generator, cells: int, shape: tuple[int, int] | None = None
    ) -> FloatMap:
        import cv2

        h, w = shape if shape is not None else (self.camera.height, self.camera.width)
        gh = max(2, round(cells * h / w))
        coarse = rng.standard_normal((gh, cells)).astype(np.float32)
        field = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
        return np.asarray(field, dtype=np.float64)

    def _background(self, style: SceneStyle, rng: np.random.Generator) -> FloatMap:
        """Water, light gradient, caustics and sun rays: all smooth, so drawn at half size."""
        import cv2

        h, w = self.camera.height, self.camera.width
        hh, hw = (h + 1) // 2, (w + 1) // 2
        v, u = np.mgrid[0:hh, 0:hw].astype(np.float32)
        vertical = v / max(hh - 1, 1)
        img = style.water_level * (1.0 + style.vertical_gradient * (0.5 - vertical) * 2.0)
        img = img + style.blotches * self._smooth_field(rng, 4, (hh, hw))
        if style.caustics > 0:
            f1 = self._smooth_field(rng, 14, (hh, hw))
            f2 = self._smooth_field(rng, 11, (hh, hw))
            web = np.exp(-(f1 * f1) * 50.0) + np.exp(-(f2 * f2) * 50.0)
            img = img + style.caustics * web * (1.0 - vertical)
        if style.sun_rays > 0:
            angle = rng.uniform(-0.4, 0.4)
            coord = (u - hw / 2) * math.cos(angle) + v * math.sin(angle)
            rays = np.zeros_like(img)
            for _ in range(int(rng.integers(2, 6))):
                centre = rng.uniform(-hw / 2, hw / 2)
                width = rng.uniform(7.5, 30)
                rays += np.exp(-(((coord - centre) / width) ** 2))
            img = img + style.sun_rays * rays * (1.2 - vertical)
        full = np.asarray(
            cv2.resize(img.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR),
            dtype=np.float64,
        )
        if style.snow_per_mpx > 0:
            n = int(style.snow_per_mpx * h * w / 1e6)
            ys = rng.integers(0, h, n)
            xs = rng.integers(0, w, n)
            full[ys, xs] += rng.uniform(0.05, 0.3, n)
        return full

    def _draw_fish(
        self, image: FloatMap, rng: np.random.Generator, count: int, dark: bool
    ) -> None:
        import cv2

        h, w = image.shape
        mask = np.zeros((h, w), np.float32)
        shade = np.zeros((h, w), np.float32)
        for _ in range(count):
            self._one_fish(mask, shade, rng, rng.uniform(0.05, 0.25) * w)
        soft = np.asarray(cv2.GaussianBlur(mask, (0, 0), 1.5), dtype=np.float64)
        level = 0.25 if dark else 0.5
        image[:] = image * (1 - soft) + soft * (level + 0.25 * shade)

    def _one_fish(
        self, mask: npt.NDArray[np.float32], shade: npt.NDArray[np.float32],
        rng: np.random.Generator, length: float,
    ) -> None:
        import cv2

        h, w = mask.shape
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        angle = rng.uniform(-25, 25) + (180 if rng.random() < 0.5 else 0)
        axes = (int(length / 2), max(2, int(length * rng.uniform(0.16, 0.24))))
        cv2.ellipse(mask, (int(cx), int(cy)), axes, angle, 0, 360, 1.0, -1)
        a = math.radians(angle)
        tail = np.array([cx - math.cos(a) * length * 0.45, cy - math.sin(a) * length * 0.45])
        perp = np.array([-math.sin(a), math.cos(a)]) * axes[1] * 1.1
        back = tail - np.array([math.cos(a), math.sin(a)]) * length * 0.22
        tri = np.array([tail, back + perp, back - perp], dtype=np.int32)
        cv2.fillConvexPoly(mask, tri, 1.0)
        # Silvery belly, dark back: a vertical gradient inside the body.
        cv2.ellipse(shade, (int(cx), int(cy + axes[1] * 0.3)), (axes[0], axes[1] // 2), angle,
                    0, 360, float(rng.uniform(0.3, 1.0)), -1)

    def _draw_front_fish(
        self, image: FloatMap, rng: np.random.Generator, cover: float
    ) -> float:
        """Salmon swimming between camera and net until `cover` of the frame is hidden."""
        import cv2

        h, w = image.shape
        mask = np.zeros((h, w), np.float32)
        shade = np.zeros((h, w), np.float32)
        for _ in range(200):
            if float(mask.mean()) >= cover:
                break
            self._one_fish(mask, shade, rng, rng.uniform(0.25, 0.6) * w)
        covered = float(mask.mean())
        soft = cv2.GaussianBlur(mask, (0, 0), 2.0)
        texture = 0.04 * self._smooth_field(rng, 40)
        image[:] = image * (1 - soft) + soft * (0.3 + 0.3 * shade + texture)
        return covered

    def _plane_hits(
        self, pose: NetPose, style: SceneStyle, rng: np.random.Generator | None
    ) -> tuple[FloatMap, FloatMap, FloatMap, npt.NDArray[np.bool_], tuple[FloatMap, float, float]
               | None]:
        """Where each pixel's ray meets the net: plane coordinates (pu, pv) in metres, depth t
        along z, and which rays hit. A billowing net displaces the surface along the normal by
        a smooth wave of the plane coordinates (two fixed-point steps of the ray-surface
        intersection); its ground truth is then the least-squares plane through the visible
        surface: (normal towards the camera, distance, rms deviation)."""
        rot = pose.rotation()
        axis_u, axis_v, away = rot[:, 0], rot[:, 1], rot[:, 2]
        d = pose.distance_m()
        denom = away[0] * self._rx + away[1] * self._ry + away[2]
        hits = denom > 1e-6
        safe = np.where(hits, denom, 1.0)
        t = np.where(hits, d / safe, np.inf)  # depth along z (ray z = 1)
        p0 = np.array([0.0, 0.0, pose.range_m])
        ru = axis_u[0] * self._rx + axis_u[1] * self._ry + axis_u[2]
        rv = axis_v[0] * self._rx + axis_v[1] * self._ry + axis_v[2]
        pu = np.where(hits, t * ru - p0 @ axis_u, 0.0)
        pv = np.where(hits, t * rv - p0 @ axis_v, 0.0)
        if style.billow <= 0 or rng is None:
            return pu, pv, t, hits, None
        waves = []
        for scale, weight in ((1.0, 1.0), (0.55, 0.5)):
            phi = rng.uniform(0, 2 * math.pi)
            waves.append((math.cos(phi), math.sin(phi), style.billow_wavelength_m * scale,
                          rng.uniform(0, 2 * math.pi), weight))
        amplitude = style.billow * d / 1.5
        for _ in range(2):
            u = np.where(hits, pu, 0.0)
            v = np.where(hits, pv, 0.0)
            delta = np.zeros_like(u)
            for cx, sx, lam, psi, weight in waves:
                delta += weight * np.sin(2 * math.pi * (u * cx + v * sx) / lam + psi)
            t = np.where(hits, (d + amplitude * delta) / safe, np.inf)
            pu = np.where(hits, t * ru - p0 @ axis_u, 0.0)
            pv = np.where(hits, t * rv - p0 @ axis_v, 0.0)
        # Best plane through the visible surface (a coarse grid of hit points is plenty).
        sel = (slice(None, None, 8), slice(None, None, 8))
        ok = hits[sel] & np.isfinite(t[sel])
        pts = np.stack([t[sel][ok] * self._rx[sel][ok], t[sel][ok] * self._ry[sel][ok],
                        t[sel][ok]], axis=1)
        centre = pts.mean(axis=0)
        _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
        n_away = vt[2] if vt[2] @ away > 0 else -vt[2]
        dist = float(n_away @ centre)
        rms = float(np.sqrt(np.mean((pts @ n_away - dist) ** 2)))
        return pu, pv, t, hits, (-n_away, dist, rms)

    def _draw_net(
        self, image: FloatMap, pose: NetPose, style: SceneStyle,
        rng: np.random.Generator | None = None,
        damage: TwineCut | None = None,
    ) -> tuple[FloatMap, float, float] | None:
        import cv2

        pu, pv, t, hits, plane = self._plane_hits(pose, style, rng)
        L = self.mesh.bar_length_m
        alpha = math.radians(self.mesh.opening_angle_deg)
        # Knots at i*L*b1 + j*L*b2, b1 = (1, 0), b2 = (cos a, sin a): invert that basis.
        s2 = pv / (L * math.sin(alpha))
        s1 = pu / L - s2 * math.cos(alpha)
        s1 = s1 + pose.phase[0]
        s2 = s2 + pose.phase[1]
        width = style.twine_fraction * L if style.twine_fraction > 0 else style.twine_width_m
        half: float | FloatMap = 0.5 * width / (L * math.sin(alpha))
        fouling = style.fouling if rng is not None else 0.0
        seed = style.net_seed

        def field(tag: int, cells: float, across_view: int) -> FloatMap:
            """Smooth unit noise: fixed on the net (features of `cells` mesh cells) when the
            net has a seed, else drawn for this frame (`across_view` features across it)."""
            assert rng is not None
            if seed is None:
                return self._smooth_field(rng, across_view)
            return _net_field(seed, tag, s1, s2, cells)

        if fouling > 0 and rng is not None:
            # Fouled twine: up to ~3x thicker, uneven along the bars (a smooth field over the
            # view plus a finer one), never closing the cells.
            uneven = 0.5 + 0.5 * np.tanh(field(1, 6.0, 10)) + 0.35 * np.abs(field(2, 1.5, 45))
            half = np.minimum(np.asarray(half) * (1.0 + 3.0 * fouling * uneven), 0.42)
        pulses1, pulses2 = _box_filtered_pulses(s1, half), _box_filtered_pulses(s2, half)
        if damage is not None:
            kept1, kept2 = damage(s1, s2)
            pulses1, pulses2 = pulses1 * kept1, pulses2 * kept2
        gaps = (1.0 - pulses1) * (1.0 - pulses2)
        cover = 1.0 - gaps
        colour_field: FloatMap | float = 1.0
        if fouling > 0 and rng is not None:
            h, w = cover.shape
            # Furry growth: fine texture hugging the twine.
            fuzz = np.asarray(cv2.GaussianBlur(cover.astype(np.float32), (0, 0), 1.6),
                              dtype=np.float64)
            hair = rng.random((h, w), dtype=np.float32)
            hair = np.asarray(cv2.GaussianBlur(hair, (0, 0), 0.7), dtype=np.float64)
            cover = np.clip(cover + fouling * 1.4 * fuzz * (hair - 0.3), 0.0, 1.0)
            # Fouled patches: growth that fills the cells over part of the net.
            patch = field(3, 10.0, 5)
            patch_mask = fouling * np.clip((patch - 0.3) / 0.6, 0.0, 1.0)
            cover = cover + patch_mask * (1.0 - cover) * (0.3 + 0.6 * hair)
            # Growth is pale (hydroids, algae): fouled twine turns lighter, unevenly.
            colour_field = (1.0 + 0.25 * field(4, 3.0, 20)) * (
                1.0 + fouling * (0.75 / max(style.twine_level, 0.05) - 1.0) * 0.6)
        if style.seams > 0 and rng is not None:
            cover = np.maximum(cover, self._seams(s1, s2, style, rng))
        if style.ropes > 0 and rng is not None:
            cover = np.maximum(cover, self._ropes(pu, pv, style, rng))
        cover = np.where(hits & np.isfinite(t), cover, 0.0)
        depth = np.where(np.isfinite(t), t * np.sqrt(1 + self._rx**2 + self._ry**2), 1e9)
        attenuation = style.attenuation_per_m + 1.2 * style.turbidity
        transmit = np.exp(-attenuation * depth)
        net_colour = style.twine_level * colour_field * transmit + image * (1.0 - transmit)
        image[:] = image + cover * (net_colour - image)
        return plane

    def _seams(
        self, s1: FloatMap, s2: FloatMap, style: SceneStyle, rng: np.random.Generator
    ) -> FloatMap:
        """Seams: a mesh row (or column) sewn with much thicker twine."""
        h, w = s1.shape
        cover = np.zeros_like(s1)
        # A net with a seed has its seams at fixed rows of its lattice (near its origin, where a
        # pass starts); otherwise each frame draws them near the view's centre.
        fixed = style.net_seed is not None
        draw = rng if style.net_seed is None else np.random.default_rng([style.net_seed, 5])
        for _ in range(style.seams):
            coord = s1 if draw.random() < 0.5 else s2
            base = 0 if fixed else math.floor(float(coord[h // 2, w // 2]))
            centre = base + int(draw.integers(-4, 5))
            half = float(draw.uniform(0.06, 0.16)) * (1.0 + style.fouling)
            gy, gx = np.gradient(coord)
            foot = np.maximum(np.abs(gx) + np.abs(gy), 1e-6)
            dist = np.abs(coord - centre)
            cover = np.maximum(cover, np.clip((half - dist) / foot + 0.5, 0.0, 1.0))
        return cover

    def _ropes(
        self, pu: FloatMap, pv: FloatMap, style: SceneStyle, rng: np.random.Generator
    ) -> FloatMap:
        """Ropes lying on the net: straight, 1-3 cm thick, with a twisted texture."""
        h, w = pu.shape
        cover = np.zeros_like(pu)
        for _ in range(style.ropes):
            theta = rng.uniform(0, math.pi)
            u0, v0 = float(pu[h // 2, w // 2]), float(pv[h // 2, w // 2])
            span = float(np.nanstd(np.where(np.isfinite(pu), pu, np.nan)))
            offset = rng.uniform(-1.0, 1.0) * (span if math.isfinite(span) else 0.1)
            across = (pu - u0) * math.sin(theta) - (pv - v0) * math.cos(theta) - offset
            along = (pu - u0) * math.cos(theta) + (pv - v0) * math.sin(theta)
            width = float(rng.uniform(0.01, 0.03))
            gy, gx = np.gradient(across)
            foot = np.maximum(np.abs(gx) + np.abs(gy), 1e-9)
            body = np.clip((width / 2 - np.abs(across)) / foot + 0.5, 0.0, 1.0)
            twist = 0.75 + 0.25 * np.sin(2 * math.pi * (along + across) / (1.4 * width))
            cover = np.maximum(cover, body * twist)
        return cover

    def _draw_surface(
        self, image: FloatMap, pose: NetPose, style: SceneStyle, rng: np.random.Generator
    ) -> None:
        """A wall or floor of tiles, bricks or a checkerboard on the net's plane (not a net):
        opaque, filling the view, each tile or brick with its own shade."""
        pu, pv, t, hits, _ = self._plane_hits(pose, style, None)
        size = style.pattern_size_m or self.mesh.bar_length_m
        g = style.grout_fraction
        u = np.where(hits, pu, 0.0) / size + pose.phase[0]
        v = np.where(hits, pv, 0.0) / size + pose.phase[1]
        if style.pattern == "tiles":
            joints = 1.0 - (1.0 - _box_filtered_pulses(u, g / 2)) * (
                1.0 - _box_filtered_pulses(v, g / 2))
            cell = (np.floor(u + 0.5), np.floor(v + 0.5))
        elif style.pattern == "bricks":
            row = np.floor(v + 0.5)
            ub = u / 2.0 + 0.5 * np.mod(row, 2.0)  # bricks twice as long as high, running bond
            joints = 1.0 - (1.0 - _box_filtered_pulses(v, g / 2)) * (
                1.0 - _box_filtered_pulses(ub, g / 4))
            cell = (np.floor(ub + 0.5), row)
        elif style.pattern == "checkerboard":
            # XOR of two 50 % square waves, each box-filtered over the pixel.
            qa = _box_filtered_pulses(u - 0.25, 0.25)
            qb = _box_filtered_pulses(v - 0.25, 0.25)
            joints = qa + qb - 2.0 * qa * qb
            cell = (np.zeros_like(u), np.zeros_like(v))
        else:
            raise ValueError(f"unknown pattern {style.pattern!r}")
        base = float(rng.uniform(0.45, 0.75))
        # Each tile or brick its own shade: a hash of its index (fract(sin(x) * 43758.5)).
        hashed = np.sin(cell[0] * 12.9898 + cell[1] * 78.233 + rng.uniform(0, 6.3)) * 43758.5453
        jitter = 0.12 * (hashed - np.floor(hashed) - 0.5)
        joint_level = float(rng.choice([0.15, 0.9])) if style.pattern != "checkerboard" else 0.1
        surface = (base + jitter) * (1.0 - joints) + joint_level * joints
        depth = np.where(hits, t * np.sqrt(1 + self._rx**2 + self._ry**2), 1e9)
        transmit = np.exp(-(style.attenuation_per_m + 1.2 * style.turbidity) * depth)
        image[:] = np.where(hits, surface * transmit + image * (1.0 - transmit), image)

    def _draw_boards(self, image: FloatMap, rng: np.random.Generator, count: int) -> float:
        """Marker boards in front of the net: a dark panel carrying a white square fiducial with
        a random block code, each 15-35 % of the frame width, turned up to 25 degrees."""
        import cv2

        h, w = image.shape
        mask = np.zeros((h, w), np.float32)
        for _ in range(count):
            tex_w, tex_h = 60, 80
            tex = np.full((tex_h, tex_w), rng.uniform(0.08, 0.2), np.float32)
            tex[22:70, 8:52] = 0.9  # white square with a black border and a 4x4 code
            tex[28:64, 14:46] = 0.05
            code = rng.random((4, 4)) < 0.5
            for (r, c), on in np.ndenumerate(code):
                if on:
                    tex[32 + r * 7 : 39 + r * 7, 18 + c * 6 : 24 + c * 6] = 0.9
            size = rng.uniform(0.15, 0.35) * w
            scale = size / tex_w
            angle = rng.uniform(-25, 25)
            centre = (rng.uniform(0.1, 0.9) * w, rng.uniform(0.15, 0.85) * h)
            m = cv2.getRotationMatrix2D((tex_w / 2, tex_h / 2), angle, scale)
            m[:, 2] += np.array(centre) - np.array([tex_w / 2, tex_h / 2])
            board = cv2.warpAffine(tex, m, (w, h), flags=cv2.INTER_LINEAR)
            inside = cv2.warpAffine(np.ones_like(tex), m, (w, h), flags=cv2.INTER_LINEAR)
            image[:] = image * (1.0 - inside) + board * inside
            mask = np.maximum(mask, inside)
        return float(mask.mean())

    def _turbid_water(self, image: FloatMap, style: SceneStyle, rng: np.random.Generator) -> None:
        """Veiling light (contrast lost to scattered light) and backscatter: soft bright specks
        of particles lit near the camera."""
        import cv2

        h, w = image.shape
        tau = style.turbidity
        veil = style.water_level * (1.1 + 0.2 * self._smooth_field(rng, 3))
        image[:] = image * (1.0 - 0.55 * tau) + 0.55 * tau * veil
        n = int(tau * 600 * h * w / 1e6)
        if n:
            specks = np.zeros((h, w), np.float32)
            xs, ys = rng.integers(0, w, n), rng.integers(0, h, n)
            radii = rng.uniform(1.5, 6.0, n)
            levels = rng.uniform(0.03, 0.12, n)
            for x, y, r, lv in zip(xs, ys, radii, levels, strict=True):
                cv2.circle(specks, (int(x), int(y)), int(r), float(lv), -1)
            image += np.asarray(cv2.GaussianBlur(specks, (0, 0), 2.0), dtype=np.float64)

    def _lamps(self, strength: float, rng: np.random.Generator) -> FloatMap:
        """The ROV's lamps: light falling off from a spot near the centre of the view."""
        h, w = self.camera.height, self.camera.width
        cx = rng.uniform(0.3, 0.7) * w
        cy = rng.uniform(0.3, 0.7) * h
        sigma = rng.uniform(0.25, 0.5) * w
        v, u = np.ogrid[0:h, 0:w]
        spot = np.exp(-((u - cx) ** 2 + (v - cy) ** 2) / (2 * sigma * sigma))
        return np.asarray((1.0 - strength) + strength * 1.5 * spot, dtype=np.float64)

    def _camera_effects(
        self, image: FloatMap, style: SceneStyle, rng: np.random.Generator
    ) -> Gray:
        import cv2

        img = np.asarray(image, dtype=np.float32)
        if style.blur_sigma_px > 0:
            img = np.asarray(cv2.GaussianBlur(img, (0, 0), style.blur_sigma_px), dtype=np.float32)
        if style.motion_blur_px >= 1.0:
            # A straight streak: the ROV moving during the exposure.
            length = int(round(style.motion_blur_px))
            kernel = np.zeros((2 * length + 1, 2 * length + 1), np.float32)
            angle = rng.uniform(0, math.pi)
            for i in np.linspace(-length / 2, length / 2, 4 * length + 1):
                x = int(round(length + i * math.cos(angle)))
                y = int(round(length + i * math.sin(angle)))
                kernel[y, x] += 1.0
            img = np.asarray(cv2.filter2D(img, -1, kernel / kernel.sum()), dtype=np.float32)
        if style.noise_sigma > 0:
            shot = np.sqrt(np.clip(img, 0, None)) * style.noise_sigma
            noise = rng.standard_normal(img.shape, dtype=np.float32)
            img = np.asarray(img + noise * (style.noise_sigma * 0.5 + shot), dtype=np.float32)
        frame = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
        if style.jpeg_quality > 0:
            ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, style.jpeg_quality])
            if ok:
                frame = np.asarray(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), dtype=np.uint8)
        return frame


def _net_field(seed: int, tag: int, s1: FloatMap, s2: FloatMap, cells: float) -> FloatMap:
    """A smooth random field fixed on the net: unit normal noise on a grid of one node per
    `cells` mesh cells (64 x 64 nodes, repeating beyond), cubic between them, looked up at the
    lattice coordinates (s1, s2). The same place of the net reads the same value in every frame,
    from any pose."""
    import cv2

    nodes = 64
    grid = np.random.default_rng([seed, tag]).standard_normal((nodes, nodes)).astype(np.float32)
    mx = np.mod(s1 / cells, nodes).astype(np.float32)
    my = np.mod(s2 / cells, nodes).astype(np.float32)
    out = cv2.remap(grid, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_WRAP)
    return np.asarray(out, dtype=np.float64)


def _box_filtered_pulses(s: FloatMap, half_width: float | FloatMap) -> FloatMap:
    """Coverage of a pixel by unit-period pulses |s - round(s)| < half_width, box-filtered.

    The pixel's footprint in s is estimated from the local gradient (L1 norm over one pixel),
    and the pulse train's integral G(y) = floor(y)*2h + min(frac(y), 2h) gives the exact average.
    The footprint varies smoothly, so its gradient is taken on a 4x decimated grid; the integer
    part of s is removed in double precision and the rest done in single precision.
    """
    import cv2

    step = 4
    coarse = s[::step, ::step]
    gy, gx = np.gradient(coarse)
    foot_coarse = ((np.abs(gx) + np.abs(gy)) / step).astype(np.float32)
    footprint = cv2.resize(foot_coarse, (s.shape[1], s.shape[0]), interpolation=cv2.INTER_LINEAR)
    footprint = np.maximum(footprint, np.float32(1e-6))
    frac = (s - np.floor(s)).astype(np.float32)
    half = np.asarray(half_width, dtype=np.float32)
    width = np.float32(2.0) * half

    def integral(y: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        fl = np.floor(y)
        return fl * width + np.minimum(y - fl, width)

    lo = frac - 0.5 * footprint + half
    hi = frac + 0.5 * footprint + half
    return np.asarray((integral(hi) - integral(lo)) / footprint, dtype=np.float64)
