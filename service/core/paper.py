"""The paper's single-ROI method, kept for comparison: one mesh from one ROI, then PnP.

One square ROI at the image centre gives the reciprocal lattice; the dual basis gives one mesh
cell (a parallelogram) in the image; OpenCV's IPPE solves the pose of that cell from its four
corners and the known mesh size. IPPE returns two poses with (nearly) equal reprojection error
that mirror each other about the viewing ray; like the paper, the lower error is taken, which is
why this path shows the orientation ambiguity that the multi-ROI estimator removes.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.camera import CameraModel
from service.core.grey import to_gray
from service.core.lattice import LatticeFinder
from service.core.mesh import MeshGeometry
from service.core.results import NetEstimate, RoiResult
from service.core.spectrum import SpectrumAnalyzer

Image = npt.NDArray[Any]


@dataclass(frozen=True)
class PaperSettings:
    roi_size: int = 256
    levels: int = 3
    min_period_px: float = 4.0
    max_period_fraction: float = 0.25


class PaperEstimator:
    """Single ROI, single mesh, PnP (IPPE): the method of the paper, with sub-bin peaks."""

    def __init__(
        self, camera: CameraModel, mesh: MeshGeometry, settings: PaperSettings | None = None
    ) -> None:
        self.camera = camera
        self.mesh = mesh
        self.settings = settings or PaperSettings()
        self._spectrum = SpectrumAnalyzer(self.settings.roi_size)
        self._lattice = LatticeFinder()
        half = mesh.bar_length_m / 2.0
        alpha = math.radians(mesh.opening_angle_deg)
        # Cell corners in the net plane, centred: e1 = L (1, 0), e2 = L (cos a, sin a).
        e1 = np.array([mesh.bar_length_m, 0.0])
        e2 = mesh.bar_length_m * np.array([math.cos(alpha), math.sin(alpha)])
        centre = (e1 + e2) / 2.0
        corners = [np.zeros(2), e1, e1 + e2, e2]
        self._object = np.array([[*(c - centre), 0.0] for c in corners], dtype=np.float64)
        self._square = abs(mesh.opening_angle_deg - 90.0) < 1e-9
        del half

    def estimate(self, frame: Image) -> NetEstimate:
        import cv2

        t0 = time.perf_counter()
        gray = to_gray(frame)  # the one grey conversion (raises EstimatorInputError)
        h, w = gray.shape
        camera = self.camera.scaled_to(w, h)
        n = self.settings.roi_size
        image = gray
        for level in range(self.settings.levels):
            if image.shape[0] < n or image.shape[1] < n:
                break
            y0, x0 = (image.shape[0] - n) // 2, (image.shape[1] - n) // 2
            patch = np.asarray(image[y0 : y0 + n, x0 : x0 + n], dtype=np.float32)
            fit = self._lattice.fit(self._spectrum.peaks(patch))
            if fit is not None:
                lengths = np.linalg.norm(fit.basis, axis=0)
                period_ok = lengths.max() <= n / self.settings.min_period_px and (
                    lengths.min() >= 1.0 / self.settings.max_period_fraction
                )
                if period_ok:
                    scale = 2**level
                    centre = np.array(
                        [(x0 + (n - 1) / 2) * scale + (scale - 1) / 2,
                         (y0 + (n - 1) / 2) * scale + (scale - 1) / 2]
                    )
                    reciprocal = fit.basis / (n * scale)
                    return self._pose(camera, centre, reciprocal, fit.inlier_weight_fraction,
                                      level, t0)
            image = cv2.pyrDown(image)
        return NetEstimate(detected=False, confidence=0.0, reason="no lattice in the centre ROI",
                           timings_ms={"total": (time.perf_counter() - t0) * 1e3})

    def _pose(
        self, camera: CameraModel, centre: npt.NDArray[np.float64],
        reciprocal: npt.NDArray[np.float64], quality: float, level: int, t0: float,
    ) -> NetEstimate:
        import cv2

        edges = np.linalg.inv(reciprocal).T  # columns e1, e2 in pixels
        e1, e2 = edges[:, 0], edges[:, 1]
        mid = (e1 + e2) / 2.0
        # Image y points down while the object's second axis points "up" the plane: flip e2's
        # role so the corner order keeps the same handedness as the object points.
        corners = np.array([centre - mid, centre - mid + e1, centre + mid, centre - mid + e2])
        normalised = camera.undistort_pixels(corners)
        flags = cv2.SOLVEPNP_IPPE_SQUARE if self._square else cv2.SOLVEPNP_IPPE
        obj = self._object
        if self._square:
            s = self.mesh.bar_length_m / 2.0
            obj = np.array([[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]], dtype=np.float64)
            normalised = normalised[[3, 2, 1, 0]] if _clockwise(normalised) else normalised
        count, rvecs, tvecs, errors = cv2.solvePnPGeneric(
            obj, normalised.reshape(-1, 1, 2), np.eye(3), None, flags=flags
        )
        if count == 0:
            return NetEstimate(detected=False, confidence=0.0, reason="PnP failed")
        best = int(np.argmin(np.asarray(errors).ravel())) if errors is not None else 0
        rot, _ = cv2.Rodrigues(rvecs[best])
        t = np.asarray(tvecs[best], dtype=np.float64).ravel()
        normal = rot[:, 2]
        if normal @ t > 0:  # point from the net towards the camera
            normal = -normal
        distance = float(abs(normal @ t))
        range_m = distance / abs(float(normal[2]))
        roi = RoiResult(
            center_px=(float(centre[0]), float(centre[1])),
            size_px=self.settings.roi_size * 2**level,
            level=level,
            detected=True,
            reciprocal=(
                (float(reciprocal[0, 0]), float(reciprocal[1, 0])),
                (float(reciprocal[0, 1]), float(reciprocal[1, 1])),
            ),
            mesh_edges=((float(e1[0]), float(e1[1])), (float(e2[0]), float(e2[1]))),
            cell_area_px=abs(float(np.linalg.det(edges))),
            inlier_fraction=quality,
            used_in_fit=True,
        )
        return NetEstimate(
            detected=True,
            confidence=float(quality),
            normal=(float(normal[0]), float(normal[1]), float(normal[2])),
            distance_m=distance,
            range_m=range_m,
            rois=(roi,),
            rois_used=1,
            level=level,
            timings_ms={"total": (time.perf_counter() - t0) * 1e3},
        )


def _clockwise(points: npt.NDArray[np.float64]) -> bool:
    """True when the polygon's vertices run clockwise in the normalised image plane."""
    x, y = points[:, 0], points[:, 1]
    return float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) < 0
