"""`netpose bench real`'s stability figure: valid outputs of one view, under noise of less than
a grey level, must agree within their sigmas (service/benchmarks/real_stability.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.benchmarks.real_frames import real_field_frames
from service.benchmarks.real_stability import (
    disagreement,
    frame_stability,
    noisy_copies,
)
from service.core.camera import load_camera
from service.core.estimator import NetEstimator
from service.core.results import NetEstimate
from tests.numeric_stack import failing_case
from tests.shared_data import shared_data_dir


def _valid(range_m: float, sigma_m: float, tilt_deg: float, sigma_deg: float) -> NetEstimate:
    t = math.radians(tilt_deg)
    return NetEstimate(detected=True, confidence=0.9, normal=(math.sin(t), 0.0, -math.cos(t)),
                       distance_m=range_m * math.cos(t), range_m=range_m,
                       sigma_distance_m=sigma_m, sigma_range_m=sigma_m,
                       sigma_normal_deg=sigma_deg)


def test_two_distances_of_one_view_are_judged_by_their_joint_sigma() -> None:
    # 0.60 and 0.78 m, each claiming 1 cm: 18 cm apart is 12.7 sigma of their difference.
    range_z, normal_z = disagreement([_valid(0.60, 0.01, 18.0, 2.5), _valid(0.78, 0.01, 5.0,
                                                                            2.5)])
    assert range_z == pytest.approx(0.18 / math.hypot(0.01, 0.01))
    assert normal_z == pytest.approx(13.0 / math.hypot(2.5, 2.5))
    # The same pair with honest sigmas agrees; a refused frame is not an output at all.
    assert disagreement([_valid(0.60, 0.06, 18.0, 6.0), _valid(0.78, 0.06, 5.0, 6.0)])[0] < 3.0
    refused = NetEstimate(detected=False, confidence=0.2, approx_range_m=0.6,
                          approx_sigma_range_m=0.01)
    assert disagreement([refused, _valid(0.78, 0.01, 5.0, 2.5)]) == (0.0, 0.0)


def test_noisy_copies_change_pixels_by_about_a_grey_level_and_no_more() -> None:
    gray = np.full((90, 120), 128, dtype=np.uint8)
    gray[::7] = 250  # near the top: clipped, never wrapped
    copies = list(noisy_copies(gray, 3, 0.6, np.random.default_rng(0)))
    for copy in copies:
        diff = copy.astype(int) - gray.astype(int)
        assert copy.dtype == np.uint8 and np.abs(diff).max() <= 4
        # Rounded N(0, 0.6): a pixel changes where |x| >= 0.5, P = 2 (1 - Phi(0.83)) = 0.405.
        assert 0.37 < float((diff != 0).mean()) < 0.44
    assert not np.array_equal(copies[0], copies[1])


REAL = shared_data_dir()


@pytest.mark.skipif(not (REAL / "real-net-frame").is_dir(),
                    reason=f"real-net-frame not found under {REAL} (set NETPOSE_SHARED_DATA)")
def test_the_clear_real_net_frame_is_stable_under_sub_grey_level_noise() -> None:
    """The one real frame where the net fills the view cleanly (18 of 18 ROIs): every copy
    gives a distance, and they agree far inside their sigmas (measured: 1.216-1.217 m, pair
    z 0.1)."""
    frame = next(f for f in real_field_frames(REAL) if f.name == "real-net-frame")
    estimator = NetEstimator(load_camera(frame.calibration), frame.mesh)
    row = frame_stability(frame, estimator, 4, 0.6, np.random.default_rng(3))
    assert row.valid == row.tries == 5
    assert row.stable and row.range_z < 1.0 and row.normal_z < 1.0


def _noisy(gray: np.ndarray, seed: int) -> np.ndarray:
    """The noisy copy the case below was found with (float64 noise, as the search drew it)."""
    rng = np.random.default_rng(seed)
    return np.asarray(np.rint(np.clip(gray.astype(np.float32) + rng.normal(0.0, 0.6, gray.shape),
                                      0, 255)), dtype=np.uint8)


def _real_frame_estimator(name: str) -> tuple[np.ndarray, NetEstimator]:
    from service.core.grey import decode_gray

    frame = next(f for f in real_field_frames(REAL) if f.name == name)
    gray, _ = decode_gray(frame.image.read_bytes())
    return gray, NetEstimator(load_camera(frame.calibration), frame.mesh)


# Open (docs/benchmarks.md, `netpose bench real`, stability): valid outputs of one real view,
# under less than a grey level of noise, more than 3 sigma apart.
# - Sequence frame 004, noise seed 82: five faint ROIs, two of them on a marker board whose ArUco
#   grid repeats at 1.65 times the net's period, tilt the plane to 18 deg and give 0.599 +- 0.010
#   m; seed 5 gives 0.781 +- 0.007 m at 9.5 deg (15 sigma apart). Found on numpy 2 / OpenCV 5;
#   on bookworm's stack one of the two copies gives no distance (an expected failure there too).
@pytest.mark.skipif(not (REAL / "real-field").is_dir(),
                    reason=f"real-field not found under {REAL} (set NETPOSE_SHARED_DATA)")
@failing_case("open: ROIs on a marker board's grid join the plane")
@pytest.mark.parametrize(("name", "seeds"), [("2024-08-22_142905/004", (82, 5))])
def test_two_noisy_copies_of_a_real_view_agree_within_their_sigmas(
    name: str, seeds: tuple[int, int]
) -> None:
    gray, estimator = _real_frame_estimator(name)
    estimates = [estimator.estimate(_noisy(gray, seed)) for seed in seeds]
    assert all(e.detected for e in estimates)  # both give a distance: the case as found
    range_z, normal_z = disagreement(estimates)
    assert range_z <= 3.0 and normal_z <= 3.0


@pytest.mark.skipif(not (REAL / "real-field").is_dir(),
                    reason=f"real-field not found under {REAL} (set NETPOSE_SHARED_DATA)")
def test_the_fouled_seams_valid_outputs_agree_within_their_sigmas() -> None:
    """The bench's own copies of the fouled-seam still gave tilts of 2.3-14.2 deg to opposite
    sides at a claimed +-1.3-3.9 deg: the plane kept 9 of 12 ROIs that show the net's lattice
    in one copy, 6 of 7 in another, and the ones it left out pulled the other way. Their pull
    is now part of the sigma (estimator._left_out_pull)."""
    frame = next(f for f in real_field_frames(REAL) if f.name == "ni_fouled_seam")
    estimator = NetEstimator(load_camera(frame.calibration), frame.mesh)
    index = [f.name for f in real_field_frames(REAL) if f.kind in ("still", "sequence")].index(
        "ni_fouled_seam")
    row = frame_stability(frame, estimator, 10, 0.6, np.random.default_rng([1, index]))
    assert row.valid >= 2 and row.stable
