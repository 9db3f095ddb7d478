"""Synthetic underwater net renderer with exact ground truth.

A flat net (square or rhombic mesh of twine) is placed at a known pose in front of a known,
distorted camera and rendered over an underwater-looking scene: light gradient, caustics, sun
rays, marine snow, fish behind and (optionally) in front of the net, blur and sensor noise.

Anti-aliasing is analytic instead of by brute-force supersampling: each twine family is a pulse
train in lattice coordinates, and its coverage of a pixel is the exact box-filtered pulse train
over the pixel's footprint in that coordinate. That keeps long-range renders (twine narrower than
a pixel, mesh period of a few pixels) free of aliasing at the cost of one render per frame.

The renderer is used by the tests, the benchmarks and the `synthetic:` frame source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.core.mesh import MeshGeometry

FloatMap = npt.NDArray[np.float64]
Gray = npt.NDArray[np.uint8]


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
    ) -> tuple[Gray, GroundTruth]:
        rng = self._rng if rng is None else rng
        style = SceneStyle() if style is None else style
        h, w = self.camera.height, self.camera.width
        image = self._background(style, rng)
        self._draw_fish(image, rng, style.fish_behind, dark=True)
        if style.net_present:
            self._draw_net(image, pose, style)
        occluded = 0.0
        if style.fish_front_cover > 0:
            occluded = self._draw_front_fish(image, rng, style.fish_front_cover)
        image *= 1.0 - style.vignetting * self._radial2 * 2.0
        frame = self._camera_effects(image, style, rng)
        normal = pose.normal_towards_camera()
        truth = GroundTruth(
            net_present=style.net_present,
            range_m=pose.range_m,
            distance_m=pose.distance_m(),
            normal=(float(normal[0]), float(normal[1]), float(normal[2])),
            tilt_deg=abs(pose.tilt_deg),
            pose=pose,
            occluded_fraction=occluded,
        )
        del h, w
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

    def _draw_net(self, image: FloatMap, pose: NetPose, style: SceneStyle) -> None:
        rot = pose.rotation()
        axis_u, axis_v, away = rot[:, 0], rot[:, 1], rot[:, 2]
        d = pose.distance_m()
        denom = away[0] * self._rx + away[1] * self._ry + away[2]
        hits = denom > 1e-6
        t = np.where(hits, d / np.where(hits, denom, 1.0), np.inf)  # depth along z (ray z = 1)
        p0 = np.array([0.0, 0.0, pose.range_m])
        # Plane coordinates of the hit point X = t * (rx, ry, 1), relative to p0.
        pu = t * (axis_u[0] * self._rx + axis_u[1] * self._ry + axis_u[2]) - p0 @ axis_u
        pv = t * (axis_v[0] * self._rx + axis_v[1] * self._ry + axis_v[2]) - p0 @ axis_v
        L = self.mesh.bar_length_m
        alpha = math.radians(self.mesh.opening_angle_deg)
        # Knots at i*L*b1 + j*L*b2, b1 = (1, 0), b2 = (cos a, sin a): invert that basis.
        s2 = pv / (L * math.sin(alpha))
        s1 = pu / L - s2 * math.cos(alpha)
        s1 = s1 + pose.phase[0]
        s2 = s2 + pose.phase[1]
        half = 0.5 * style.twine_width_m / (L * math.sin(alpha))
        gaps = (1.0 - _box_filtered_pulses(s1, half)) * (1.0 - _box_filtered_pulses(s2, half))
        cover = 1.0 - gaps
        cover = np.where(hits & np.isfinite(t), cover, 0.0)
        depth = np.where(np.isfinite(t), t * np.sqrt(1 + self._rx**2 + self._ry**2), 1e9)
        transmit = np.exp(-style.attenuation_per_m * depth)
        net_colour = style.twine_level * transmit + image * (1.0 - transmit)
        image[:] = image + cover * (net_colour - image)

    def _camera_effects(
        self, image: FloatMap, style: SceneStyle, rng: np.random.Generator
    ) -> Gray:
        import cv2

        img = np.asarray(image, dtype=np.float32)
        if style.blur_sigma_px > 0:
            img = np.asarray(cv2.GaussianBlur(img, (0, 0), style.blur_sigma_px), dtype=np.float32)
        if style.noise_sigma > 0:
            shot = np.sqrt(np.clip(img, 0, None)) * style.noise_sigma
            noise = rng.standard_normal(img.shape, dtype=np.float32)
            img = np.asarray(img + noise * (style.noise_sigma * 0.5 + shot), dtype=np.float32)
        return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _box_filtered_pulses(s: FloatMap, half_width: float) -> FloatMap:
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
    width = np.float32(2.0 * half_width)

    def integral(y: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        fl = np.floor(y)
        return fl * width + np.minimum(y - fl, width)

    lo = frac - 0.5 * footprint + np.float32(half_width)
    hi = frac + 0.5 * footprint + np.float32(half_width)
    return np.asarray((integral(hi) - integral(lo)) / footprint, dtype=np.float64)
