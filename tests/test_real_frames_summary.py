"""`netpose bench real`'s verdicts on its targets, without the data set: a target that one run
cannot evaluate says so instead of reading as missed or met."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np

from drivers.synthetic_net import NetPose, NetRenderer
from service.benchmarks.real_frames import SOLAQUA_MESH, RealFrame, RealSummary, run_frames
from service.core.camera import CameraModel, save_camera

SUMMARY = RealSummary(
    stills=4, stills_detected=4, sequence=44, sequence_detected=5, sequence_seen=23, no_net=18,
    false_nets=0, false_too_close=0, sequence_distance_median_m=0.77,
    sequence_range_median_m=0.78, sequence_frame_to_frame_m=0.014,
    sequence_sigma_median_m=0.013,
)
SPREAD = "sequence sigma >= frame-to-frame spread"


def test_the_spread_target_is_judged_when_the_spread_was_measured() -> None:
    assert SUMMARY.targets[SPREAD] is False
    wider = dataclasses.replace(SUMMARY, sequence_sigma_median_m=0.015)
    assert wider.targets[SPREAD] is True


def test_the_spread_target_is_not_measurable_without_two_steps() -> None:
    # One pair of consecutive measured frames (or none) leaves the spread undefined.
    single = dataclasses.replace(SUMMARY, sequence_frame_to_frame_m=math.nan)
    assert single.targets[SPREAD] is None
    assert single.targets["all stills detected"] is True


SEEN_SPREAD = "sequence sigma >= frame-to-frame spread, ranges measured or seen"


def test_the_spread_of_seen_ranges_is_judged_on_its_own_sigmas() -> None:
    """The refused ranges a pilot reads ("net seen, ~0.8 m") have sigmas too: judged against
    their own frame-to-frame spread, whatever the measured frames' verdict."""
    seen = dataclasses.replace(SUMMARY, sequence_seen_frame_to_frame_m=0.03,
                               sequence_seen_sigma_median_m=0.02)
    assert seen.targets[SEEN_SPREAD] is False
    assert dataclasses.replace(seen, sequence_seen_sigma_median_m=0.035).targets[SEEN_SPREAD]
    assert SUMMARY.targets[SEEN_SPREAD] is None  # no two consecutive ranges: not measurable


def _frame(tmp_path: Path, name: str, kind: str, camera: CameraModel, range_m: float) -> RealFrame:
    image, _ = NetRenderer(camera, SOLAQUA_MESH, seed=0).render(
        NetPose(range_m, tilt_deg=10.0), rng=np.random.default_rng(0))
    cv2.imwrite(str(tmp_path / f"{name}.png"), image)
    save_camera(camera, tmp_path / f"{name}.yaml")
    return RealFrame(name, tmp_path / f"{name}.png", tmp_path / f"{name}.yaml", kind)


def test_tracking_starts_afresh_at_a_sequence(tmp_path: Path) -> None:
    """`bench real`'s tracked run feeds each sequence frame the previous detection, as the
    daemon does; a still before the sequence (another camera, another place) is not the
    sequence's past, so the sequence's first frame is searched, not tracked from it."""
    still_camera = CameraModel(width=1280, height=720, fx=882.0, fy=821.0, cx=640.0, cy=360.0)
    strip_camera = CameraModel(width=640, height=360, fx=441.0, fy=410.5, cx=320.0, cy=180.0)
    frames = [_frame(tmp_path, "still", "still", still_camera, 1.0),
              _frame(tmp_path, "seq0", "sequence", strip_camera, 1.0),
              _frame(tmp_path, "seq1", "sequence", strip_camera, 1.0)]
    still, first, second = run_frames(frames, tracking=True)
    assert still.estimate.detected and first.estimate.detected and second.estimate.detected
    assert first.estimate.searched and not second.estimate.searched
