"""The net estimator end to end: rendered frames with exact ground truth, and a real frame.

Frames come from drivers.synthetic_net (a distorted 1280x720 camera with an 82 deg field of view,
a 1.5 cm mesh, underwater background, noise and blur). Tolerances are the issue's targets (1 % in
range and distance, 2 deg in the normal); measured errors are quoted next to each.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import numpy as np
import numpy.typing as npt
import pytest

from drivers.synthetic_net import GroundTruth, NetPose, NetRenderer, SceneStyle
from service.core.camera import CameraModel, load_camera
from service.core.errors import CalibrationError, ConfigError, EstimatorInputError
from service.core.estimator import EstimatorSettings, NetEstimator
from service.core.mesh import MeshGeometry
from service.core.results import NetEstimate
from tests.shared_data import REAL_NET_DIR

F64 = npt.NDArray[np.float64]
Gray = npt.NDArray[np.uint8]

FOCAL = 0.5 * 1280 / math.tan(math.radians(41.0))  # 82 deg horizontal field of view
CAMERA = CameraModel(
    width=1280, height=720, fx=FOCAL, fy=FOCAL, cx=642.5, cy=357.5,
    distortion=(-0.08, 0.05, 0.0005, -0.0003, 0.0), name="test_wide",
)
SQUARE = MeshGeometry(bar_length_m=0.015)
RHOMBIC = MeshGeometry(bar_length_m=0.015, opening_angle_deg=60.0)

REAL_DIR = REAL_NET_DIR
REAL_FRAME = REAL_DIR / "net_1280x720.jpg"
REAL_CALIBRATION = REAL_DIR / "camera_solaqua_1280x720.yaml"


@pytest.fixture(scope="module")
def renderer() -> Iterator[NetRenderer]:
    yield NetRenderer(CAMERA, SQUARE, seed=0)


@pytest.fixture(scope="module")
def estimator() -> NetEstimator:
    return NetEstimator(CAMERA, SQUARE, EstimatorSettings())


def _render(
    renderer: NetRenderer, pose: NetPose, seed: int, style: SceneStyle | None = None
) -> tuple[Gray, GroundTruth]:
    return renderer.render(pose, rng=np.random.default_rng(seed), style=style)


def _errors(estimate: NetEstimate, truth: GroundTruth) -> tuple[float, float, float]:
    """(relative range error, relative distance error, normal error in degrees)."""
    assert estimate.range_m is not None and estimate.distance_m is not None
    assert estimate.normal is not None
    cos = float(np.dot(estimate.normal, truth.normal))
    return (
        estimate.range_m / truth.range_m - 1.0,
        estimate.distance_m / truth.distance_m - 1.0,
        math.degrees(math.acos(min(1.0, cos))),
    )


# -- accuracy on rendered frames ------------------------------------------------------------------

POSES = [
    pytest.param(NetPose(r, tilt_deg=t, tilt_axis_deg=a, roll_deg=roll, phase=(0.3, 0.7)),
                 id=f"{r}m-{t:.0f}deg-axis{a:.0f}")
    for r, t, a, roll in [
        (0.5, 0.0, 0.0, 10.0),
        (0.5, 25.0, 30.0, 55.0),
        (0.5, 40.0, 120.0, 20.0),
        (1.2, 0.0, 0.0, 35.0),
        (1.2, 25.0, 210.0, 5.0),
        (1.2, 40.0, 300.0, 70.0),
        (2.0, 0.0, 0.0, 80.0),
        (2.0, 25.0, 60.0, 15.0),
        (2.0, 40.0, 45.0, 20.0),
    ]
]
# Measured with these seeds: range and distance errors at most 0.19 %, normal at most 0.16 deg,
# reported sigmas 0.08-0.24 % and 0.09-0.24 deg. The 2 m / 40 deg pose about a near-horizontal
# axis once missed the target (far-side ROIs with a 3 px mesh); since the estimator refuses ROIs
# whose mesh the camera does not resolve (< 3.5 px), 10 seeds give at most 0.18 % and 0.29 deg.
POSES.append(
    pytest.param(
        NetPose(2.0, tilt_deg=40.0, tilt_axis_deg=160.0, roll_deg=40.0, phase=(0.3, 0.7)),
        id="2.0m-40deg-axis160",
    )
)


@pytest.mark.parametrize("pose", POSES)
def test_rendered_net_range_distance_and_normal(
    renderer: NetRenderer, estimator: NetEstimator, pose: NetPose
) -> None:
    frame, truth = _render(renderer, pose, seed=int(pose.range_m * 100 + pose.tilt_deg))
    estimate = estimator.estimate(frame)
    assert estimate.detected, estimate.reason
    range_error, distance_error, normal_error = _errors(estimate, truth)
    assert abs(range_error) < 0.01
    assert abs(distance_error) < 0.01
    assert normal_error < 2.0
    assert estimate.tilt_deg == pytest.approx(truth.tilt_deg, abs=2.0)
    assert estimate.rois_used >= EstimatorSettings().min_rois
    assert 0.0 < estimate.confidence <= 1.0
    # The reported 1-sigma uncertainties cover the actual errors (4 sigma, plus a floor of
    # 0.1 % / 0.2 deg for the model bias the sigmas do not include).
    assert estimate.sigma_range_m is not None and estimate.sigma_normal_deg is not None
    assert abs(range_error) * truth.range_m < 4 * estimate.sigma_range_m + 0.001 * truth.range_m
    assert normal_error < 4 * estimate.sigma_normal_deg + 0.2


# -- what must not be detected, and what must still be --------------------------------------------


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_net_free_water_with_fish_is_not_a_net(
    renderer: NetRenderer, estimator: NetEstimator, seed: int
) -> None:
    frame, truth = _render(
        renderer, NetPose(1.0), seed, SceneStyle(net_present=False, fish_behind=6, caustics=0.2)
    )
    assert not truth.net_present
    estimate = estimator.estimate(frame)
    assert not estimate.detected
    # Nothing a consumer could mistake for a measurement.
    assert estimate.distance_m is None and estimate.range_m is None and estimate.normal is None
    assert estimate.reason
    assert estimate.confidence < EstimatorSettings().min_confidence


@pytest.mark.parametrize("seed", [4, 5])
def test_fish_covering_a_third_of_the_frame(
    renderer: NetRenderer, estimator: NetEstimator, seed: int
) -> None:
    pose = NetPose(1.0, tilt_deg=20.0, tilt_axis_deg=60.0 * seed, roll_deg=15.0)
    frame, truth = _render(renderer, pose, seed, SceneStyle(fish_front_cover=1 / 3))
    assert truth.occluded_fraction >= 1 / 3
    estimate = estimator.estimate(frame)
    assert estimate.detected, estimate.reason
    range_error, distance_error, normal_error = _errors(estimate, truth)
    # Measured <= 0.10 % and 0.03 deg (41 % and 38 % of the frame hidden); the target is 2 %.
    assert abs(range_error) < 0.02 and abs(distance_error) < 0.02
    assert normal_error < 2.0
    # Some ROIs were rejected: the fish were seen as such, not fitted.
    assert estimate.rois_used < len(estimate.rois)


# -- mesh shape ---------------------------------------------------------------------------------


def test_rhombic_mesh_with_the_matching_geometry() -> None:
    renderer = NetRenderer(CAMERA, RHOMBIC, seed=0)
    pose = NetPose(1.0, tilt_deg=25.0, tilt_axis_deg=100.0, roll_deg=30.0)
    frame, truth = _render(renderer, pose, seed=9)
    estimate = NetEstimator(CAMERA, RHOMBIC).estimate(frame)
    assert estimate.detected, estimate.reason
    range_error, distance_error, normal_error = _errors(estimate, truth)
    # Measured 0.04 % / 0.08 % / 0.06 deg.
    assert abs(range_error) < 0.01 and abs(distance_error) < 0.01
    assert normal_error < 2.0
    assert estimate.measured_opening_deg == pytest.approx(60.0, abs=2.0)
    # Assuming a square mesh instead would over-estimate the distance by sqrt(1 / sin 60 deg) - 1
    # = 7.5 % (distance scales with the square root of the assumed cell area). The rectified
    # lattice shows the real opening angle, so the estimator refuses the distance and says why,
    # with the angle it measured (issue 17, item 3).
    as_square = NetEstimator(CAMERA, SQUARE).estimate(frame)
    assert not as_square.detected and as_square.distance_m is None
    assert as_square.measured_opening_deg == pytest.approx(60.0, abs=2.0)
    assert "opening angle measured 60 deg" in as_square.reason


@pytest.mark.parametrize("hung", [76.0, 82.0])
def test_a_net_hung_at_another_angle_than_configured_is_measured_as_it_hangs(hung: float) -> None:
    """A net keeps its bars; its opening angle is how it hangs (a square net sheared by the
    current, a diamond net by its load). Within the configured angle's tolerance the distance
    used the configured cell area and read long by sqrt(1 / sin(angle)) - 1: 0.5 % at 82 deg,
    1.5 % at 76 deg, at a sigma of about 0.2 % (the method review's f2_opening_angle.py). The
    rectified view shows the angle to about 0.1 deg, so the cell's area is the measured one."""
    mesh = MeshGeometry(bar_length_m=0.015, opening_angle_deg=hung)
    frame, truth = _render(NetRenderer(CAMERA, mesh, seed=0),
                           NetPose(0.9, tilt_deg=20.0, tilt_axis_deg=30.0, roll_deg=15.0),
                           seed=5)
    estimate = NetEstimator(CAMERA, SQUARE).estimate(frame)
    assert estimate.detected, estimate.reason
    assert estimate.measured_opening_deg == pytest.approx(hung, abs=0.5)
    range_error, distance_error, normal_error = _errors(estimate, truth)
    bias = 1.0 / math.sqrt(math.sin(math.radians(hung))) - 1.0
    # Within a third of the bias the configured angle would have given, and within 2 sigma.
    assert abs(range_error) < bias / 3 and abs(distance_error) < bias / 3, (range_error, bias)
    assert estimate.sigma_range_m is not None
    assert abs(range_error) * truth.range_m < 2.0 * estimate.sigma_range_m
    assert normal_error < 1.0


@pytest.mark.parametrize("opening", [60.0, 120.0])
def test_a_hexagonal_mesh_is_not_taken_for_a_brick_wall(opening: float) -> None:
    """A 60 (or 120) deg mesh's lattice is hexagonal: its short diagonal is as long as its bars,
    so the geometry alone cannot tell which pair is the twine. Choosing the pair by length put
    a bar family among the twine test's "cross terms" and refused about half of these clean
    frames as a brick-like grid (21 and 28 of 40, found by a review). Eight random views, all
    measured within the accuracy targets."""
    mesh = MeshGeometry(bar_length_m=0.015, opening_angle_deg=opening)
    renderer = NetRenderer(CAMERA, mesh, seed=0)
    estimator = NetEstimator(CAMERA, mesh)
    rng = np.random.default_rng(int(opening))
    for k in range(8):
        pose = NetPose(float(rng.uniform(0.5, 1.8)), tilt_deg=float(rng.uniform(0.0, 35.0)),
                       tilt_axis_deg=float(rng.uniform(0.0, 360.0)),
                       roll_deg=float(rng.uniform(0.0, 180.0)),
                       phase=(float(rng.random()), float(rng.random())))
        frame, truth = _render(renderer, pose, seed=100 + k)
        estimate = estimator.estimate(frame)
        assert estimate.detected, (k, estimate.reason)
        range_error, _, normal_error = _errors(estimate, truth)
        assert abs(range_error) < 0.01 and normal_error < 2.0, k


# -- tracking prior -----------------------------------------------------------------------------


def test_prior_gives_the_cold_answer(renderer: NetRenderer, estimator: NetEstimator) -> None:
    pose = NetPose(1.2, tilt_deg=25.0, tilt_axis_deg=30.0, roll_deg=10.0)
    frame, _ = _render(renderer, pose, seed=21)
    cold = estimator.estimate(frame)
    assert cold.detected
    warm = estimator.estimate(frame, prior=cold)
    _assert_same_answer(warm, cold, rel=0.002)  # measured 0.03 %
    # The next frame: the ROV moved 3 cm closer and turned a little. Prior (previous frame)
    # and cold path agree on it too.
    moved = NetPose(1.17, tilt_deg=27.0, tilt_axis_deg=32.0, roll_deg=10.0)
    next_frame, truth = _render(renderer, moved, seed=22)
    tracked = estimator.estimate(next_frame, prior=cold)
    fresh = estimator.estimate(next_frame)
    _assert_same_answer(tracked, fresh, rel=0.002)  # measured 0.01 %, 0.02 deg
    assert abs(_errors(tracked, truth)[0]) < 0.01


def test_a_prior_the_frame_contradicts_is_a_miss_when_the_search_is_deferred(
    renderer: NetRenderer, estimator: NetEstimator
) -> None:
    """With `search=False` (service/pipeline.py defers one search) a tracked pass that lands
    on a plane far from the prior's gives no distance and no search; with the default the
    frame is searched and measured."""
    pose = NetPose(1.0, tilt_deg=15.0, tilt_axis_deg=20.0)
    frame, truth = _render(renderer, pose, seed=24)
    cold = estimator.estimate(frame)
    assert cold.detected and cold.distance_m is not None
    # The prior 15 % further: within the rectified pass's reach (it lands on the true plane),
    # beyond the 8 % at which a tracked plane still counts as the prior's.
    far = dataclasses.replace(cold, distance_m=cold.distance_m * 1.15,
                              range_m=(cold.range_m or 0.0) * 1.15)
    missed = estimator.estimate(frame, prior=far, search=False)
    assert not missed.detected and not missed.searched and missed.distance_m is None
    assert missed.reason.startswith("tracking missed") and missed.confidence <= 0.2
    assert "scale_search" not in missed.timings_ms
    searched = estimator.estimate(frame, prior=far)
    assert searched.detected and searched.searched
    assert abs(_errors(searched, truth)[0]) < 0.01


def test_a_prior_without_detection_falls_back_to_the_search(
    renderer: NetRenderer, estimator: NetEstimator
) -> None:
    frame, _ = _render(renderer, NetPose(0.8, tilt_deg=10.0), seed=23)
    nothing = NetEstimate(detected=False, confidence=0.0, reason="lost")
    _assert_same_answer(estimator.estimate(frame, prior=nothing), estimator.estimate(frame), 0.0)


def test_a_stream_that_changes_resolution_keeps_tracking_the_plane() -> None:
    """A network stream renegotiated from 1280x720 to 640x360 while tracking: the prior's plane
    still holds (the calibration scales), its ROIs do not (their pixels are the old frame's).
    With a strong lens (SOLAQUA's published coefficients, which fold the image over not far
    outside the frame) a prior ROI at (870, 180), outside the new frame, once raised a
    calibration error for a lens that is fine."""
    import cv2

    camera = CameraModel(width=1280, height=720, fx=882.0, fy=821.0, cx=680.0, cy=360.0,
                         distortion=(0.2037, 0.85736, 0.013247, -0.004259, -0.940367),
                         name="solaqua_like")
    mesh = MeshGeometry(bar_length_m=0.02)
    renderer = NetRenderer(camera, mesh, seed=0)
    estimator = NetEstimator(camera, mesh)
    frame, _ = renderer.render(NetPose(1.0, tilt_deg=15.0, tilt_axis_deg=30.0),
                               rng=np.random.default_rng(1))
    full = estimator.estimate(frame)
    assert full.detected and full.frame_px == (1280, 720)
    moved, truth = renderer.render(NetPose(0.98, tilt_deg=15.0, tilt_axis_deg=30.0),
                                   rng=np.random.default_rng(2))
    half = cv2.resize(moved, (640, 360), interpolation=cv2.INTER_AREA)
    tracked = estimator.estimate(half, prior=full)
    assert tracked.detected, tracked.reason
    assert tracked.frame_px == (640, 360) and not tracked.searched  # the prior's plane held
    assert abs(_errors(tracked, truth)[0]) < 0.01  # measured 0.1 %


def _assert_same_answer(a: NetEstimate, b: NetEstimate, rel: float) -> None:
    assert a.detected and b.detected
    assert a.range_m is not None and b.range_m is not None
    assert a.distance_m is not None and b.distance_m is not None
    assert a.normal is not None and b.normal is not None
    assert a.range_m == pytest.approx(b.range_m, rel=rel, abs=1e-12)
    assert a.distance_m == pytest.approx(b.distance_m, rel=rel, abs=1e-12)
    angle = math.degrees(math.acos(min(1.0, float(np.dot(a.normal, b.normal)))))
    assert angle < max(rel * 100, 1e-6)  # 0.2 % -> 0.2 deg


# -- inputs -------------------------------------------------------------------------------------


def test_bgr_and_bgra_input_equal_gray_input(
    renderer: NetRenderer, estimator: NetEstimator
) -> None:
    import cv2

    frame, _ = _render(renderer, NetPose(0.9, tilt_deg=15.0, tilt_axis_deg=80.0), seed=31)
    gray = estimator.estimate(frame)
    bgr = estimator.estimate(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    bgra = estimator.estimate(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGRA))
    single_channel = estimator.estimate(frame[:, :, None])
    assert gray.detected
    for other in (bgr, bgra, single_channel):
        assert dataclasses.replace(other, timings_ms={}) == dataclasses.replace(
            gray, timings_ms={}
        )


def test_half_resolution_stream_uses_the_scaled_calibration(
    renderer: NetRenderer, estimator: NetEstimator
) -> None:
    import cv2

    pose = NetPose(0.6, tilt_deg=20.0, tilt_axis_deg=45.0, roll_deg=25.0)
    frame, truth = _render(renderer, pose, seed=41)
    half = cv2.resize(frame, (640, 360), interpolation=cv2.INTER_AREA)
    estimate = estimator.estimate(half)  # the 1280x720 calibration, scaled by the estimator
    assert estimate.detected, estimate.reason
    # Measured 0.05 % (an unscaled focal length would be off by 100 %).
    range_error, distance_error, normal_error = _errors(estimate, truth)
    assert abs(range_error) < 0.01 and abs(distance_error) < 0.01
    assert normal_error < 2.0


@pytest.mark.parametrize(
    "frame",
    [
        np.zeros(1280 * 720, np.uint8),
        np.zeros((2, 720, 1280, 3), np.uint8),
        np.zeros((720, 1280, 2), np.uint8),
    ],
    ids=["flat-1d", "batch-4d", "two-channels"],
)
def test_wrong_shape_is_an_input_error(
    estimator: NetEstimator, frame: npt.NDArray[np.uint8]
) -> None:
    with pytest.raises(EstimatorInputError, match="shape"):
        estimator.estimate(frame)


def test_frame_smaller_than_a_roi_is_an_input_error(estimator: NetEstimator) -> None:
    # Same aspect ratio as the calibration (so the camera scales), but 112x63 is smaller than
    # the smallest ROI (64 px).
    with pytest.raises(EstimatorInputError, match="smaller than one 64px ROI"):
        estimator.estimate(np.zeros((63, 112), np.uint8))


def test_frame_of_another_aspect_ratio_is_a_calibration_error(estimator: NetEstimator) -> None:
    with pytest.raises(CalibrationError, match="aspect ratio"):
        estimator.estimate(np.zeros((480, 640), np.uint8))


def test_uniform_frame_is_no_net(estimator: NetEstimator) -> None:
    estimate = estimator.estimate(np.full((720, 1280), 128, np.uint8))
    assert not estimate.detected and estimate.distance_m is None


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"roi_size": 100}, "estimator.roi_size"),
        ({"levels": 0}, "estimator.levels"),
        ({"min_rois": 3}, "estimator.min_rois"),
        ({"grid_cols": 2, "grid_rows": 2, "min_rois": 5}, "estimator.min_rois"),
        ({"min_confidence": 1.5}, "estimator.min_confidence"),
        # Each divided by zero, or rooted negative, on every frame (a review found these).
        ({"preferred_period_px": 0.0}, "estimator.preferred_period_px"),
        ({"preferred_period_px": -9.0}, "estimator.preferred_period_px"),
        ({"min_period_px": 0.0}, "estimator.min_period_px"),
        ({"lattice_tolerance": float("nan")}, "estimator.lattice_tolerance"),
        ({"min_inlier_fraction": 0.0}, "estimator.min_inlier_fraction"),
    ],
)
def test_invalid_settings_name_the_key(change: dict[str, float], key: str) -> None:
    with pytest.raises(ConfigError) as err:
        NetEstimator(CAMERA, SQUARE, EstimatorSettings(**change))  # type: ignore[arg-type]
    assert err.value.key == key


# -- the real frame -----------------------------------------------------------------------------


@pytest.mark.skipif(not REAL_FRAME.exists(), reason="real-net-frame data set not present")
def test_real_net_frame() -> None:
    import cv2

    camera = load_camera(REAL_CALIBRATION)
    frame = cv2.imread(str(REAL_FRAME), cv2.IMREAD_COLOR)
    assert frame is not None
    estimate = NetEstimator(camera, MeshGeometry(bar_length_m=0.02)).estimate(frame)
    assert estimate.detected, estimate.reason
    assert estimate.normal is not None and estimate.range_m is not None
    # No ground truth; the public implementation reports ~0.82 m with these intrinsics and a
    # 2.0 cm mesh (ROI depths 0.61-0.93 m). Plausible range only (measured here: 0.90 m).
    assert 0.5 < estimate.range_m < 1.3
    # Direction of the tilt. The net is nearer at the bottom right. On the plane n_away . X = d
    # (n_away = -normal, pointing from the camera to the net) the depth along the ray
    # (x, y, 1) is z = d / (n_away . (x, y, 1)): it decreases towards +x (right) and +y (down)
    # exactly when n_away_x > 0 and n_away_y > 0, i.e. normal_x < 0 and normal_y < 0.
    nx, ny, nz = estimate.normal
    assert nx < 0 and ny < 0 and nz < 0
    # Cross-check without the plane fit: the mesh looks larger (nearer) at the bottom right.
    used = [r for r in estimate.rois if r.used_in_fit]
    xs = np.array([r.center_px[0] for r in used])
    ys = np.array([r.center_px[1] for r in used])
    periods = np.array([r.period_px for r in used])
    assert np.corrcoef(xs, periods)[0, 1] > 0.3
    assert np.corrcoef(ys, periods)[0, 1] > 0.3
    assert estimate.rois_used >= 8


@pytest.mark.parametrize("seed", [3, 21])
def test_a_net_too_uncertain_for_a_distance_is_still_said_to_be_seen(seed: int) -> None:
    """2 m and 40 deg on the 1.5 cm mesh: the far side's mesh is below 5 px, the ROIs that
    measure sit on the near side, and the plane is refused as too uncertain for a distance
    (the 2 % limit). The net is still reported in view, with the range that was refused and
    its sigma, which must be honest (truth within 3 sigma), and no distance at all."""
    from service.benchmarks.accuracy import draw_pose
    from service.benchmarks.scenes import PAPER_MESH, bench_camera

    cam = bench_camera(1280, 720)
    rng = np.random.default_rng([seed, 200, 40])
    draw = draw_pose(rng)
    pose = NetPose(2.0, 40.0, draw.tilt_axis_deg, draw.roll_deg, draw.phase)
    image, truth = NetRenderer(cam, PAPER_MESH).render(pose, rng, SceneStyle.varied(rng))
    est = NetEstimator(cam, PAPER_MESH).estimate(image)
    assert not est.detected and est.net_seen, est.reason
    assert est.reason.startswith("plane too uncertain")
    assert est.range_m is None and est.distance_m is None and est.normal is None
    assert est.approx_range_m is not None and est.approx_sigma_range_m is not None
    assert est.approx_sigma_range_m > 0.02 * est.approx_range_m  # why it was refused
    assert abs(est.approx_range_m - truth.range_m) <= 3.0 * est.approx_sigma_range_m
    message = est.to_json_dict()
    assert message["net_seen"] is True and message["range_m"] is None


@pytest.mark.parametrize("nearer", [0.95, 0.90])
def test_a_net_nearer_in_the_middle_is_not_given_the_range_of_its_sides(
    renderer: NetRenderer, estimator: NetEstimator, nearer: float
) -> None:
    """The middle of the view (360 px square) shows the net 5 or 10 % nearer than the rest,
    as a net that bulges between its ropes does. The ROIs around the middle agree on a plane
    and the one on the optical axis is its outlier; the range on the axis is the middle's.
    Before the axis check the estimator reported the sides' range, 1.000 +- 0.0015 m, where
    the axis meets the net at 0.95 or 0.90 m (33 and 67 sigma): a distance that must not reach
    the autopilot. Now it is refused (the range the sides give is uncertain by the 5 or 10 %
    the middle contradicts it by), or within 3 sigma of the axis's truth."""
    pose = NetPose(range_m=1.0, tilt_deg=10.0, tilt_axis_deg=30.0)
    sides, _ = _render(renderer, pose, 1)
    middle, truth = _render(renderer, dataclasses.replace(pose, range_m=nearer), 1)
    image = sides.copy()
    image[180:540, 460:820] = middle[180:540, 460:820]
    flat = estimator.estimate(sides)
    assert flat.detected and flat.sigma_range_m is not None and flat.range_m is not None
    assert flat.sigma_range_m < 0.005 * flat.range_m  # the check leaves a flat net alone
    est = estimator.estimate(image)
    if est.detected:
        assert est.range_m is not None and est.sigma_range_m is not None
        assert abs(est.range_m - truth.range_m) <= 3.0 * est.sigma_range_m
    else:
        assert est.net_seen, est.reason
        assert "off the plane of the ROIs around it" in est.reason
