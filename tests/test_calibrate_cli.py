"""`netpose calibrate` and `netpose undistort` end to end: real files, video and processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from service.cli import EXIT_CONFIG, main
from service.core.camera import load_camera, save_camera
from service.tools.calibration import BoardSpec, detect_board
from service.tools.calibration_io import CalibrationInputError, sample_video
from tests.checkerboard_render import TEST_CAMERA, render_views
from tests.shared_data import REAL_NET_FRAME, needs_real_net_frame

REPO = Path(__file__).resolve().parents[1]
NET_FRAME = REAL_NET_FRAME


@pytest.fixture(scope="module")
def images() -> list[np.ndarray]:
    return render_views()[0]


@pytest.fixture(scope="module")
def board_folder(images: list[np.ndarray], tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("boards")
    for i, image in enumerate(images):
        assert cv2.imwrite(str(folder / f"view{i:02d}.png"), image)
    (folder / "notes.txt").write_text("not an image, must be ignored\n")
    return folder


def _netpose(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
        timeout=timeout, env=env, cwd=REPO, check=False,
    )


def test_folder_to_yaml_with_json_summary(board_folder: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "camera.yaml"
    code = main(["calibrate", str(board_folder), "--board", "7x4", "--square", "0.0311",
                 "--output", str(out), "--json", "--no-progress"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    cam = load_camera(out)  # the file netpose estimate and the daemon read
    assert cam.fx == pytest.approx(TEST_CAMERA.fx, rel=0.005)
    assert cam.fy == pytest.approx(TEST_CAMERA.fy, rel=0.005)
    assert cam.cx == pytest.approx(TEST_CAMERA.cx, rel=0.005)
    assert cam.cy == pytest.approx(TEST_CAMERA.cy, rel=0.005)
    assert summary["fx"] == pytest.approx(cam.fx)
    assert summary["camera_matrix"][0][0] == pytest.approx(cam.fx)
    assert set(summary["distortion"]) == {"k1", "k2", "p1", "p2", "k3"}
    assert summary["rms_px"] < 0.2
    assert len(summary["views_used"]) == 14 and summary["views_rejected"] == []
    assert summary["frames_examined"] == 14
    text = out.read_text()
    assert "distortion_model: plumb_bob" in text and "projection_matrix" in text


def test_human_report_and_preview(board_folder: Path, tmp_path: Path, capsys) -> None:
    out, preview = tmp_path / "cam.yaml", tmp_path / "preview.png"
    code = main(["calibrate", str(board_folder), "-o", str(out), "--preview", str(preview),
                 "--no-progress"])
    assert code == 0
    report = capsys.readouterr().out
    assert "RMS reprojection error" in report and "view00.png" in report
    side = cv2.imread(str(preview))
    assert side is not None and side.shape[:2] == (480, 2 * 640 + 4)


def test_video_is_sampled_skipping_blurred_and_duplicate_frames(
    images: list[np.ndarray], tmp_path: Path
) -> None:
    video = tmp_path / "board.avi"
    fourcc = cv2.VideoWriter.fourcc(*"MJPG")
    writer = cv2.VideoWriter(str(video), fourcc, 10.0, (640, 480))
    assert writer.isOpened()
    # Eight distinct poses, each held for 4 frames (duplicates), each followed by 2 blurred frames
    # (camera moving): 48 frames of which 8 are worth keeping.
    for image in images[:8]:
        for _ in range(4):
            writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
        blurred = cv2.GaussianBlur(image, (0, 0), 6.0)
        for _ in range(2):
            writer.write(cv2.cvtColor(blurred, cv2.COLOR_GRAY2BGR))
    writer.release()

    frames, decoded, skipped = sample_video(video, max_frames=24)
    assert decoded == 48
    assert len(frames) == 8  # one per distinct pose
    board = BoardSpec(7, 4, 0.0311)
    assert all(detect_board(f.gray, board) is not None for f in frames)  # none blurred away
    assert skipped == 24 - 8

    # The same video through the real command in a child process, with the progress bar on.
    out = tmp_path / "video.yaml"
    proc = _netpose("calibrate", str(video), "-o", str(out), "--max-frames", "24", "--progress",
                    "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert len(summary["views_used"]) == 8
    assert summary["video_frames_skipped_blurred_or_duplicate"] == 16
    assert "scanning board.avi" in proc.stderr and "detecting board" in proc.stderr
    assert load_camera(out).fx == pytest.approx(TEST_CAMERA.fx, rel=0.01)  # 8 views only


def test_wrong_board_size_names_the_board_seen(board_folder: Path, tmp_path: Path) -> None:
    """The board seen is named as --board names boards (7x4, 9x6: the larger count first), not
    in the detector's orientation of its grid, which varies from view to view: the hint said
    "try --board 4x7" where docs/calibration.md shows 7x4."""
    out = tmp_path / "never.yaml"
    proc = _netpose("calibrate", str(board_folder), "--board", "9x6", "-o", str(out))
    assert proc.returncode == EXIT_CONFIG
    assert "found no 9x6 board" in proc.stderr
    assert "the images look like a 7x4 board (inner corners): try --board 7x4" in proc.stderr
    assert not out.exists()


@needs_real_net_frame
def test_no_board_in_real_net_frame(tmp_path: Path, capsys) -> None:
    out = tmp_path / "never.yaml"
    code = main(["calibrate", str(NET_FRAME), "-o", str(out)])
    assert code == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "found no 7x4 checkerboard in any of 1 frame" in err
    assert not out.exists()


def test_unreadable_inputs(tmp_path: Path, capsys) -> None:
    garbage = tmp_path / "broken.jpg"
    garbage.write_bytes(b"\xff\xd8 this is not really a jpeg")
    out = tmp_path / "never.yaml"
    assert main(["calibrate", str(garbage), "-o", str(out)]) == 1
    assert "broken.jpg: not an image OpenCV can decode" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path / "missing.png"), "-o", str(out)]) == 1
    assert "missing.png: no such file or folder" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["calibrate", str(empty), "-o", str(out)]) == 1
    assert "folder contains no images" in capsys.readouterr().err
    not_video = tmp_path / "clip.mp4"
    not_video.write_bytes(b"\x00" * 1000)
    with pytest.raises(CalibrationInputError):
        sample_video(not_video, 10)
    assert not out.exists()


def test_unreadable_file_among_good_ones_is_skipped_and_reported(
    board_folder: Path, tmp_path: Path, capsys
) -> None:
    garbage = tmp_path / "broken.png"
    garbage.write_bytes(b"nope")
    out = tmp_path / "cam.yaml"
    code = main(["calibrate", str(board_folder), str(garbage), "-o", str(out), "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert any("broken.png" in u for u in summary["unreadable"])
    assert any("unreadable" in w for w in summary["warnings"])


def test_existing_output_is_not_overwritten(board_folder: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "camera.yaml"
    out.write_text("precious\n")
    assert main(["calibrate", str(board_folder), "-o", str(out)]) == EXIT_CONFIG
    assert "use --force" in capsys.readouterr().err
    assert out.read_text() == "precious\n"


def test_bad_board_argument(tmp_path: Path, capsys) -> None:
    assert main(["calibrate", str(NET_FRAME), "--board", "7by4", "-o",
                 str(tmp_path / "x.yaml")]) == EXIT_CONFIG
    assert "COLUMNSxROWS" in capsys.readouterr().err


def _row_straightness(corners: np.ndarray, board: BoardSpec) -> float:
    """Largest distance (px) of a corner from the straight line fitted through its board row."""
    worst = 0.0
    for row in corners.reshape(board.rows, board.columns, 2):
        centre = row.mean(axis=0)
        _, _, vt = np.linalg.svd(row - centre)
        worst = max(worst, float(np.abs((row - centre) @ vt[1]).max()))
    return worst


def test_undistort_makes_board_rows_straight(images: list[np.ndarray], tmp_path: Path) -> None:
    board = BoardSpec(7, 4, 0.0311)
    camera_file = tmp_path / "true.yaml"
    save_camera(TEST_CAMERA, camera_file)
    source = tmp_path / "distorted.png"
    cv2.imwrite(str(source), images[1])  # board near the top-left corner: strongly bent
    out = tmp_path / "straight.png"
    proc = _netpose("undistort", str(source), "--camera", str(camera_file), "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    before = detect_board(images[1], board)
    after_image = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    assert after_image is not None
    after = detect_board(after_image, board)
    assert before is not None and after is not None
    bent, straight = _row_straightness(before, board), _row_straightness(after, board)
    # Measured: rows bent by 1.1 px before, straight within 0.06 px (the corner noise) after.
    assert bent > 0.8
    assert straight < 0.2
    assert straight < bent / 5


@needs_real_net_frame
def test_undistort_errors(tmp_path: Path, capsys) -> None:
    camera_file = tmp_path / "cam.yaml"
    save_camera(TEST_CAMERA, camera_file)
    out = tmp_path / "o.png"
    assert main(["undistort", str(tmp_path / "nope.png"), "-c", str(camera_file),
                 "-o", str(out)]) == 1
    assert "no such file" in capsys.readouterr().err
    assert main(["undistort", str(NET_FRAME), "-c", str(tmp_path / "missing.yaml"),
                 "-o", str(out)]) == EXIT_CONFIG
    assert "calibration file not found" in capsys.readouterr().err
    # A 640x480 calibration cannot be stretched onto a 16:9 frame.
    assert main(["undistort", str(NET_FRAME), "-c", str(camera_file), "-o", str(out)]) == (
        EXIT_CONFIG
    )
    assert "aspect ratio" in capsys.readouterr().err
    assert not out.exists()


def test_undistort_says_what_is_wrong_with_its_paths(tmp_path: Path, capsys) -> None:
    """A folder as INPUT and an output of no image type: one line each, no traceback."""
    camera_file = tmp_path / "cam.yaml"
    save_camera(TEST_CAMERA, camera_file)
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), np.full((TEST_CAMERA.height, TEST_CAMERA.width), 128, np.uint8))
    assert main(["undistort", str(tmp_path), "-c", str(camera_file),
                 "-o", str(tmp_path / "o.png")]) == 1
    err = capsys.readouterr().err
    assert "not a file" in err and len(err.strip().splitlines()) == 1, err
    assert main(["undistort", str(frame), "-c", str(camera_file),
                 "-o", str(tmp_path / "o.txt")]) == 1
    err = capsys.readouterr().err
    assert "cannot write" in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_opencv_filestorage_calibrations_are_read(tmp_path: Path, suffix: str) -> None:
    """Files written by OpenCV's own calibration sample (cv::FileStorage) load unchanged."""
    path = tmp_path / f"out_camera_data{suffix}"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", TEST_CAMERA.matrix)
    fs.write("distortion_coefficients", TEST_CAMERA.dist_coeffs.reshape(5, 1))
    fs.release()
    cam = load_camera(path)
    assert (cam.width, cam.height) == (640, 480)
    assert cam.fx == TEST_CAMERA.fx and cam.cy == TEST_CAMERA.cy
    assert cam.distortion == pytest.approx(TEST_CAMERA.distortion)


def test_frames_of_another_size_are_skipped_and_reported(
    board_folder: Path, tmp_path: Path, capsys
) -> None:
    small = tmp_path / "thumb.png"
    full = cv2.imread(str(board_folder / "view00.png"))
    assert full is not None
    cv2.imwrite(str(small), cv2.resize(full, (320, 240)))
    out = tmp_path / "cam.yaml"
    code = main(["calibrate", str(board_folder), str(small), "-o", str(out), "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["image_width"], summary["image_height"]) == (640, 480)
    assert len(summary["views_used"]) == 14
    assert any("thumb.png (320x240)" in w for w in summary["warnings"])
