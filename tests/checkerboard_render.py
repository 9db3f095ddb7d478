"""Render checkerboard photographs through a known camera (test helper, not part of the service).

Each output pixel is traced back through the camera: the pixel grid (supersampled) is undistorted
once per camera to normalised rays, every view then intersects those rays with the board plane
and samples an analytic checkerboard. So the images carry exactly the distortion of the camera
they were rendered with, and the true corner positions are `cv2.projectPoints` of the board.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class BoardPose:
    """Board pose: rotation (Rodrigues vector) and translation of the board's centre, metres."""

    rvec: tuple[float, float, float]
    tvec: tuple[float, float, float]


class CheckerboardRenderer:
    """Renders a `columns` x `rows` inner-corner board with `square`-metre squares."""

    def __init__(
        self, camera: CameraModel, columns: int, rows: int, square: float, supersample: int = 3
    ) -> None:
        self.camera = camera
        self.columns, self.rows, self.square = columns, rows, square
        self.supersample = supersample
        self._rays = self._pixel_rays()

    def _pixel_rays(self) -> FloatArray:
        """Undistorted normalised rays (H*s, W*s, 2) through the sub-pixel sample positions."""
        s = self.supersample
        offsets = (np.arange(s) + 0.5) / s - 0.5
        xs = (np.arange(self.camera.width)[:, None] + offsets[None, :]).ravel()
        ys = (np.arange(self.camera.height)[:, None] + offsets[None, :]).ravel()
        grid = np.stack(np.meshgrid(xs, ys), axis=-1)
        return self.camera.undistort_pixels(grid)

    def board_points(self) -> FloatArray:
        """Inner corners in board coordinates (detector order), origin at the board centre."""
        grid = np.mgrid[0 : self.columns, 0 : self.rows].T.reshape(-1, 2).astype(np.float64)
        centre = np.array([(self.columns - 1) / 2.0, (self.rows - 1) / 2.0])
        pts = np.zeros((grid.shape[0], 3))
        pts[:, :2] = (grid - centre) * self.square
        return pts

    def true_corners(self, pose: BoardPose) -> FloatArray:
        """Where the inner corners land in the image (N x 2 pixels)."""
        img, _ = cv2.projectPoints(
            self.board_points(), np.array(pose.rvec), np.array(pose.tvec),
            self.camera.matrix, self.camera.dist_coeffs,
        )
        return np.asarray(img, dtype=np.float64).reshape(-1, 2)

    def render(
        self, pose: BoardPose, *, blur_sigma: float = 0.7, noise_sigma: float = 2.0,
        seed: int = 0,
    ) -> npt.NDArray[np.uint8]:
        """A grey 8-bit image of the board at `pose` in front of a textured grey background."""
        rot, _ = cv2.Rodrigues(np.array(pose.rvec, dtype=np.float64))
        t = np.array(pose.tvec, dtype=np.float64)
        normal = rot[:, 2]
        rays = np.concatenate([self._rays, np.ones(self._rays.shape[:2] + (1,))], axis=-1)
        denom = rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = (normal @ t) / denom
            hits = rays * depth[..., None] - t
        board_xy = hits @ rot[:, :2]  # world hit -> board frame (x, y)
        # Squares are centred so that inner corners fall on multiples of `square` from the first
        # corner; the board shows one extra square on every side plus a white border.
        ix = np.floor(board_xy[..., 0] / self.square + (self.columns - 1) / 2.0) + 1
        iy = np.floor(board_xy[..., 1] / self.square + (self.rows - 1) / 2.0) + 1
        dark = ((ix + iy) % 2 == 0)
        inside_squares = (ix >= 0) & (ix <= self.columns) & (iy >= 0) & (iy <= self.rows)
        border = 0.6 * self.square
        half_w = (self.columns + 1) / 2.0 * self.square + border
        half_h = (self.rows + 1) / 2.0 * self.square + border
        on_board = (
            (np.abs(board_xy[..., 0]) <= half_w) & (np.abs(board_xy[..., 1]) <= half_h)
            & np.isfinite(depth) & (depth > 0)
        )
        h, w = self._rays.shape[:2]
        yy, xx = np.mgrid[0:h, 0:w]
        background = 70.0 + 40.0 * np.sin(xx / (w / 3.0)) * np.cos(yy / (h / 2.5))
        image = np.where(on_board, 235.0, background)
        image = np.where(on_board & inside_squares & dark, 25.0, image)
        s = self.supersample
        image = image.reshape(h // s, s, w // s, s).mean(axis=(1, 3))
        if blur_sigma > 0:
            image = cv2.GaussianBlur(image, (0, 0), blur_sigma)
        rng = np.random.default_rng(seed)
        image = image + rng.normal(0.0, noise_sigma, image.shape)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def varied_poses(camera: CameraModel, board_width_m: float, count: int = 14) -> list[BoardPose]:
    """Poses that tilt the board 0-40 deg in all directions and visit centre, edges and corners.

    The board centre is placed at a sequence of image positions at a depth where the board spans
    about 45 % of the image width, as an operator would wave a board in front of a camera.
    """
    depth = camera.fx * board_width_m / (0.45 * camera.width)
    targets = [
        (0.50, 0.50), (0.25, 0.27), (0.75, 0.27), (0.25, 0.73), (0.75, 0.73),
        (0.50, 0.27), (0.50, 0.73), (0.27, 0.50), (0.73, 0.50), (0.35, 0.40),
        (0.65, 0.60), (0.40, 0.62), (0.62, 0.38), (0.50, 0.50),
    ]
    tilts = [
        (0.0, 0.0), (25.0, -25.0), (25.0, 25.0), (-25.0, -25.0), (-25.0, 25.0),
        (35.0, 0.0), (-35.0, 0.0), (0.0, -35.0), (0.0, 35.0), (15.0, 30.0),
        (-20.0, -30.0), (30.0, 15.0), (-30.0, 20.0), (40.0, 10.0),
    ]
    poses = []
    for i in range(count):
        u, v = targets[i % len(targets)]
        ax, ay = tilts[i % len(tilts)]
        rot = (
            cv2.Rodrigues(np.array([np.radians(ax), 0.0, 0.0]))[0]
            @ cv2.Rodrigues(np.array([0.0, np.radians(ay), 0.0]))[0]
            @ cv2.Rodrigues(np.array([0.0, 0.0, np.radians(8.0 * (i % 5) - 16.0)]))[0]
        )
        ray = camera.undistort_pixels(np.array([u * camera.width, v * camera.height]))
        z = depth * (1.0 + 0.1 * (i % 3))
        tvec = (float(ray[0] * z), float(ray[1] * z), float(z))
        rvec = cv2.Rodrigues(rot)[0].ravel()
        poses.append(BoardPose(rvec=(float(rvec[0]), float(rvec[1]), float(rvec[2])), tvec=tvec))
    return poses


# A 640x480 camera with barrel distortion of the size seen behind flat underwater ports, and
# fx != fy so that an estimator which assumes square pixels is caught.
TEST_CAMERA = CameraModel(
    width=640, height=480, fx=520.0, fy=516.0, cx=323.5, cy=236.0,
    distortion=(-0.28, 0.09, 0.0012, -0.0008, -0.01), name="rendered",
)
# The paper's board: 7x4 inner corners, 3.11 cm squares.
PAPER_BOARD = (7, 4, 0.0311)


def render_views(
    camera: CameraModel = TEST_CAMERA, columns: int = 7, rows: int = 4, square: float = 0.0311,
    count: int = 14, supersample: int = 3,
) -> tuple[list[npt.NDArray[np.uint8]], list[FloatArray]]:
    """`count` rendered views (grey images) and their true corner positions."""
    renderer = CheckerboardRenderer(camera, columns, rows, square, supersample=supersample)
    poses = varied_poses(camera, (columns + 1) * square, count)
    images = [renderer.render(pose, seed=i) for i, pose in enumerate(poses)]
    return images, [renderer.true_corners(pose) for pose in poses]
