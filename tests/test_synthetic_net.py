"""Synthetic net renderer: ground truth, determinism, and the rendered mesh against projection.

The rendered mesh is measured with the spectrum analyzer and a least-squares fit of the peaks to
the lattice predicted from physics (pinhole + lens), not with the estimator's lattice finder, so
a renderer error cannot be hidden by the code it is meant to test.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from drivers.synthetic_net import GroundTruth, NetPose, NetRenderer, SceneStyle
from service.core.camera import CameraModel
from service.core.mesh import MeshGeometry
from service.core.spectrum import SpectrumAnalyzer

F64 = npt.NDArray[np.float64]
N = 128
F = 736.0
PINHOLE = CameraModel(width=640, height=480, fx=F, fy=F, cx=319.5, cy=239.5)
BARREL = CameraModel(
    width=640, height=480, fx=F, fy=F, cx=319.5, cy=239.5,
    distortion=(-0.08, 0.05, 0.0005, -0.0003, 0.0),
)
SQUARE = MeshGeometry(0.015)
RHOMBIC = MeshGeometry(0.015, opening_angle_deg=60.0)


# -- ground truth ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "pose",
    [
        NetPose(1.0),
        NetPose(0.5, tilt_deg=25.0, tilt_axis_deg=30.0, roll_deg=10.0),
        NetPose(2.0, tilt_deg=40.0, tilt_axis_deg=200.0, roll_deg=75.0, phase=(0.3, 0.8)),
        NetPose(1.2, tilt_deg=-15.0, tilt_axis_deg=90.0),
    ],
)
def test_pose_geometry_is_consistent(pose: NetPose) -> None:
    n = pose.normal_towards_camera()
    assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-12)
    assert n[2] < 0  # towards the camera, which looks along +z
    # Perpendicular distance = range along the axis x cos(tilt).
    assert pose.distance_m() == pytest.approx(pose.range_m * abs(n[2]), rel=1e-12)
    assert math.degrees(math.acos(abs(n[2]))) == pytest.approx(abs(pose.tilt_deg), abs=1e-9)
    # The point where the optical axis meets the net lies on the plane n_away . X = distance.
    assert float(-n @ np.array([0.0, 0.0, pose.range_m])) == pytest.approx(pose.distance_m())
    # The normal tilts perpendicular to the tilt axis (a rotation about that axis).
    axis = np.array([math.cos(math.radians(pose.tilt_axis_deg)),
                     math.sin(math.radians(pose.tilt_axis_deg)), 0.0])
    assert float(n @ axis) == pytest.approx(0.0, abs=1e-12)
    rot = pose.rotation()
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)


def test_frontal_net_has_normal_minus_z_whatever_its_roll() -> None:
    for roll in (0.0, 33.0, 90.0):
        pose = NetPose(0.8, tilt_deg=0.0, tilt_axis_deg=47.0, roll_deg=roll)
        np.testing.assert_allclose(pose.normal_towards_camera(), [0.0, 0.0, -1.0], atol=1e-12)
        assert pose.distance_m() == pytest.approx(0.8)


def test_render_reports_the_pose_it_drew() -> None:
    renderer = NetRenderer(BARREL, SQUARE, seed=0)
    pose = NetPose(1.2, tilt_deg=25.0, tilt_axis_deg=30.0, roll_deg=10.0)
    image, truth = renderer.render(pose)
    assert image.shape == (480, 640) and image.dtype == np.uint8
    assert isinstance(truth, GroundTruth)
    assert truth.net_present and truth.pose == pose
    assert truth.range_m == 1.2
    assert truth.distance_m == pytest.approx(pose.distance_m())
    np.testing.assert_allclose(truth.normal, pose.normal_towards_camera())
    assert truth.tilt_deg == 25.0
    assert truth.occluded_fraction == 0.0
    # Not saturated: a plausible underwater exposure.
    assert 40 < float(image.mean()) < 200
    assert (image == 255).mean() < 0.01


def test_front_fish_cover_is_reported() -> None:
    renderer = NetRenderer(PINHOLE, SQUARE, seed=0)
    _, truth = renderer.render(
        NetPose(1.0), rng=np.random.default_rng(1), style=SceneStyle(fish_front_cover=1 / 3)
    )
    # Fish are added until the cover is reached; the last one overshoots (measured 0.34-0.49).
    assert 1 / 3 <= truth.occluded_fraction < 0.6


def test_net_free_scene_says_so() -> None:
    renderer = NetRenderer(PINHOLE, SQUARE, seed=0)
    _, truth = renderer.render(NetPose(1.0), style=SceneStyle(net_present=False))
    assert not truth.net_present


# -- determinism ----------------------------------------------------------------------------------


def test_same_seed_same_frames_other_seed_other_frames() -> None:
    pose = NetPose(1.0, tilt_deg=20.0)
    a = NetRenderer(PINHOLE, SQUARE, seed=7)
    b = NetRenderer(PINHOLE, SQUARE, seed=7)
    c = NetRenderer(PINHOLE, SQUARE, seed=8)
    first_a, _ = a.render(pose)
    second_a, _ = a.render(pose)
    np.testing.assert_array_equal(first_a, b.render(pose)[0])
    np.testing.assert_array_equal(second_a, b.render(pose)[0])
    assert not np.array_equal(first_a, second_a)  # a new scene draw each frame
    assert not np.array_equal(first_a, c.render(pose)[0])
    # An explicit generator makes one frame reproducible regardless of the renderer's own state.
    x, _ = a.render(pose, rng=np.random.default_rng(3))
    y, _ = c.render(pose, rng=np.random.default_rng(3))
    np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("net_seed", [None, 7])
def test_a_seeded_nets_fouling_and_seams_stay_on_the_net(net_seed: int | None) -> None:
    """Two frames of a fouled, seamed net facing the camera, the second with the net moved by
    4 cells along the image's x (its lattice looks the same), the same frame noise. Averaged
    over a cell (which leaves the fouling's thickness, patches and colour, and the seam), the
    second frame is the first moved by those 4 cells when the net has a seed: what grows on a
    real net travels with it. Without a seed each frame draws them over the view instead, so
    they stay where they were in the image."""
    import cv2

    style = SceneStyle(vertical_gradient=0.0, blotches=0.0, caustics=0.0, sun_rays=0.0,
                       snow_per_mpx=0.0, fish_behind=0, blur_sigma_px=0.0, noise_sigma=0.0,
                       vignetting=0.0, twine_level=0.9, twine_fraction=0.2, fouling=1.0, seams=1,
                       net_seed=net_seed)
    renderer = NetRenderer(PINHOLE, SQUARE)
    period = F * SQUARE.bar_length_m / 0.5
    shift, cell = round(4 * period), round(period)
    first, _ = renderer.render(NetPose(0.5, phase=(0.3, 0.3)), np.random.default_rng(1), style)
    moved, _ = renderer.render(NetPose(0.5, phase=(4.3, 0.3)), np.random.default_rng(1), style)
    a = cv2.blur(first.astype(np.float32), (cell, cell))[40:-40]
    b = cv2.blur(moved.astype(np.float32), (cell, cell))[40:-40]
    b = b[:, 40:-shift - 40]
    followed = float(np.corrcoef(b.ravel(), a[:, shift + 40:-40].ravel())[0, 1])
    stayed = float(np.corrcoef(b.ravel(), a[:, 40:-shift - 40].ravel())[0, 1])
    if net_seed is None:
        assert stayed > 0.99 and abs(followed) < 0.3
    else:
        assert followed > 0.99 and abs(stayed) < 0.3


# -- the rendered mesh against projection ---------------------------------------------------------


def _plane_edges(mesh: MeshGeometry, roll_deg: float) -> F64:
    """Mesh edge vectors (columns) on the net plane in metres, for a frontal net."""
    a, r = math.radians(mesh.opening_angle_deg), math.radians(roll_deg)
    rot = np.array([[math.cos(r), -math.sin(r)], [math.sin(r), math.cos(r)]])
    cell = mesh.bar_length_m * np.array([[1.0, math.cos(a)], [0.0, math.sin(a)]])
    return np.asarray(rot @ cell, dtype=np.float64)


def _predicted_reciprocal(
    camera: CameraModel, mesh: MeshGeometry, range_m: float, roll_deg: float, centre: F64
) -> F64:
    """Reciprocal basis (cycles per N-px ROI) of a frontal net around pixel `centre`.

    Plane point (X, Y) at depth range_m has normalised coordinates (X, Y) / range_m; the lens
    maps those to pixels; its local Jacobian (central differences) maps mesh edges to pixels.
    """
    norm = camera.undistort_pixels(centre[None, :])[0]
    h = 1e-6
    jac = np.stack(
        [
            (camera.project_normalized(norm + [h, 0])
             - camera.project_normalized(norm - [h, 0])) / (2 * h),
            (camera.project_normalized(norm + [0, h])
             - camera.project_normalized(norm - [0, h])) / (2 * h),
        ],
        axis=1,
    )
    edges_px = jac @ _plane_edges(mesh, roll_deg) / range_m
    return np.asarray(N * np.linalg.inv(edges_px).T, dtype=np.float64)


def _measured_reciprocal(image: npt.NDArray[np.uint8], centre: F64, predicted: F64) -> F64:
    """Least-squares lattice through the ROI's spectral peaks that sit on the predicted lattice
    (within 0.3 bin): k = B n over all matched harmonics."""
    x0, y0 = round(centre[0] + 0.5 - N / 2), round(centre[1] + 0.5 - N / 2)
    patch = image[y0 : y0 + N, x0 : x0 + N].astype(np.float32)
    peaks = SpectrumAnalyzer(N).peaks(patch)
    idx = np.round(np.linalg.solve(predicted, peaks.k.T).T)
    residual = np.linalg.norm(peaks.k - idx @ predicted.T, axis=1)
    on_lattice = (residual < 0.3) & (np.abs(idx).sum(axis=1) > 0)
    assert on_lattice.sum() >= 6, "too few harmonics to measure the rendered lattice"
    # Most peaks are the net's: the render is a clean lattice, not noise.
    assert on_lattice.mean() > 0.6
    solution = np.linalg.lstsq(idx[on_lattice], peaks.k[on_lattice], rcond=None)[0]
    return np.asarray(solution.T, dtype=np.float64)


@pytest.mark.parametrize("camera", [PINHOLE, BARREL], ids=["pinhole", "barrel"])
@pytest.mark.parametrize("mesh", [SQUARE, RHOMBIC], ids=["square", "rhombic60"])
@pytest.mark.parametrize(("range_m", "roll_deg"), [(0.6, 0.0), (1.0, 20.0), (1.5, 35.0)])
def test_mesh_period_at_the_image_centre_is_f_bar_over_range(
    camera: CameraModel, mesh: MeshGeometry, range_m: float, roll_deg: float
) -> None:
    renderer = NetRenderer(camera, mesh, seed=3)
    image, _ = renderer.render(NetPose(range_m, roll_deg=roll_deg, phase=(0.2, 0.4)))
    centre = np.array([camera.cx, camera.cy])
    # At the principal point the lens Jacobian is the identity: a pure pinhole prediction,
    # cell area (f L / range)^2 sin(alpha) in pixels.
    edges_px = F * _plane_edges(mesh, roll_deg) / range_m
    predicted = np.asarray(N * np.linalg.inv(edges_px).T, dtype=np.float64)
    measured = _measured_reciprocal(image, centre, predicted)
    cell_px = N * N / abs(np.linalg.det(measured))
    expected_cell_px = (F * mesh.bar_length_m / range_m) ** 2 * math.sin(
        math.radians(mesh.opening_angle_deg)
    )
    # Measured within 0.18 % over these 12 renders; allow 0.5 %.
    assert cell_px == pytest.approx(expected_cell_px, rel=0.005)
    # Direction and shape too (measured <= 0.018 bin per component).
    np.testing.assert_allclose(measured, predicted, atol=0.05)


def test_lens_distortion_is_rendered_off_centre() -> None:
    # Near the top-left corner barrel distortion changes the mesh area by ~5 %; the
    # rendered lattice follows the lens model, not the pinhole.
    renderer = NetRenderer(BARREL, SQUARE, seed=3)
    image, _ = renderer.render(NetPose(1.0, roll_deg=20.0, phase=(0.1, 0.6)))
    centre = np.array([80.5, 70.5])
    with_lens = _predicted_reciprocal(BARREL, SQUARE, 1.0, 20.0, centre)
    pinhole = _predicted_reciprocal(PINHOLE, SQUARE, 1.0, 20.0, centre)
    lens_effect = abs(np.linalg.det(with_lens) / np.linalg.det(pinhole) - 1.0)
    assert lens_effect > 0.03  # clearly distinguishable (4.6 % in area here)
    measured = _measured_reciprocal(image, centre, with_lens)
    # Measured 0.11 %; the lens varies across the ROI (a chirp), so allow 1 % against the 4.6 %.
    error = abs(np.linalg.det(measured) / np.linalg.det(with_lens) - 1.0)
    assert error < 0.01
