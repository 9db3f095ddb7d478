"""`netpose calibrate` and `netpose undistort` end to end: real files, video and processes."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from service.cli import EXIT_CONFIG, main
from service.core.camera import CameraModel, load_camera, save_camera
from service.tools.calibration import BoardSpec, detect_board
from service.tools.calibration_io import CalibrationInputError, sample_video
from tests.checkerboard_render import (
    TEST_CAMERA,
    CheckerboardRenderer,
    render_views,
    varied_poses,
)
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

    sample = sample_video(video, 24, (7, 4))
    assert sample.decoded == 48
    assert len(sample.frames) == 8  # one per distinct pose
    board = BoardSpec(7, 4, 0.0311)
    assert all(detect_board(f.gray, board) is not None for f in sample.frames)  # none blurred
    # The 8 repeated poses, and the blurred segments in which a quick look still saw the board.
    assert 8 <= sample.skipped <= 24 - 8

    # The same video through the real command in a child process, with the progress bar on.
    out = tmp_path / "video.yaml"
    proc = _netpose("calibrate", str(video), "-o", str(out), "--max-frames", "24", "--progress",
                    "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert len(summary["views_used"]) == 8
    assert summary["video_frames_skipped_blurred_or_duplicate"] == sample.skipped
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
        sample_video(not_video, 10, (7, 4))
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


def _net_background(width: int, height: int, shift: int) -> np.ndarray:
    """Fish-net twine (bright diagonal lines every 14 px, drifting) over dim water: a frame far
    sharper, by any whole-frame measure, than a frame showing the board."""
    yy, xx = np.mgrid[0:height, 0:width]
    period = 14.0
    twine = (np.abs((xx + yy + 2 * shift) % period - period / 2) < 1.2) | (
        np.abs((xx - yy + shift) % period - period / 2) < 1.2
    )
    return np.clip(60.0 + 90.0 * twine, 0, 255).astype(np.uint8)


def test_video_with_a_net_behind_the_board_keeps_the_board_frames(
    images: list[np.ndarray], tmp_path: Path
) -> None:
    """The board is in 1 frame of 4: a net fills the others. Ranked by whole-frame sharpness the
    net frames won every segment and then cut the board frames as "blurred": "found no 7x4
    board in any of 11 frame(s); ... try --board 6x3" for a video full of 7x4 boards."""
    video = tmp_path / "net.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (640, 480))
    assert writer.isOpened()
    for i, image in enumerate(images[:8]):
        # Segments of 4 frames: board, board, net, net, then 4 of net.
        frames = [image] * 2 + [_net_background(640, 480, 8 * i + k) for k in range(6)]
        for frame in frames:
            writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()

    sample = sample_video(video, 16, (7, 4))
    board = BoardSpec(7, 4, 0.0311)
    assert len(sample.frames) == 8  # one per pose, no net frame
    assert all(detect_board(f.gray, board) is not None for f in sample.frames)
    assert sample.board_seen == 16  # the net is never taken for the board

    out = tmp_path / "net.yaml"
    assert main(["calibrate", str(video), "-o", str(out), "--max-frames", "16", "--json"]) == 0
    assert load_camera(out).fx == pytest.approx(TEST_CAMERA.fx, rel=0.01)


def test_a_board_too_blurred_to_measure_is_not_blamed_on_board(
    images: list[np.ndarray], tmp_path: Path, capsys
) -> None:
    """The board is in every frame but too blurred for its corners to be measured: the error
    said "check --board (inner corners, not squares)" of the right board."""
    video = tmp_path / "blurred.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (640, 480))
    for k in range(6):
        blurred = cv2.GaussianBlur(images[0], (0, 0), 6.0 + 0.05 * k)
        writer.write(cv2.cvtColor(blurred, cv2.COLOR_GRAY2BGR))
    writer.release()
    out = tmp_path / "never.yaml"
    assert main(["calibrate", str(video), "-o", str(out), "--max-frames", "3"]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "found no 7x4 checkerboard sharp enough to measure" in err, err
    assert "hold the board still, in focus" in err and "--board" not in err
    assert not out.exists()


class _FisheyeRenderer(CheckerboardRenderer):
    """Renders through an equidistant fisheye (cv2.fisheye), a lens plumb-bob cannot follow out
    to the corners of the image."""

    MATRIX = np.array([[250.0, 0.0, 320.0], [0.0, 250.0, 180.0], [0.0, 0.0, 1.0]])
    DISTORTION = np.array([0.02, -0.005, 0.0, 0.0])

    def _pixel_rays(self) -> np.ndarray:
        s = self.supersample
        offsets = (np.arange(s) + 0.5) / s - 0.5
        xs = (np.arange(self.camera.width)[:, None] + offsets).ravel()
        ys = (np.arange(self.camera.height)[:, None] + offsets).ravel()
        grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 1, 2)
        rays = cv2.fisheye.undistortPoints(grid, self.MATRIX, self.DISTORTION)
        return np.asarray(rays, dtype=np.float64).reshape(len(ys), len(xs), 2)


def test_a_lens_model_every_command_would_refuse_is_not_written(tmp_path: Path, capsys) -> None:
    """Through a fisheye the plumb-bob solve fits the boards (RMS 0.1 px) but folds the image
    over in its corners: calibrate said OK and wrote it, then undistort and run --check refused
    the file ("lens model cannot be inverted at pixel (0, 0)")."""
    pinhole = CameraModel(640, 360, 250.0, 250.0, 320.0, 180.0)  # places the boards only
    renderer = _FisheyeRenderer(pinhole, 7, 4, 0.0311, supersample=2)
    folder = tmp_path / "fisheye"
    folder.mkdir()
    for i, pose in enumerate(varied_poses(pinhole, 8 * 0.0311, 14)):
        assert cv2.imwrite(str(folder / f"f{i:02d}.png"), renderer.render(pose, seed=i))
    out = tmp_path / "fish.yaml"
    assert main(["calibrate", str(folder), "-o", str(out)]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "cannot be inverted" in err and "not written" in err, err
    assert not out.exists()


def test_preview_never_overwrites_an_input_nor_without_force(
    board_folder: Path, tmp_path: Path, capsys
) -> None:
    """--preview replaced an existing file without --force, even the checkerboard photo named
    as an input. Refused before any work, as -o is; an input stays refused with --force."""
    folder = shutil.copytree(board_folder, tmp_path / "photos")  # a copy: a failure must not
    photo = folder / "view01.png"  # spoil the shared folder for the other tests
    before = photo.read_bytes()
    out = tmp_path / "cam.yaml"
    for force in ([], ["--force"]):
        code = main(["calibrate", str(folder), "-o", str(out), "--preview", str(photo),
                     *force])
        assert code == EXIT_CONFIG
        assert "--preview" in capsys.readouterr().err
        assert photo.read_bytes() == before and not out.exists()
    kept = tmp_path / "kept.png"
    kept.write_bytes(b"precious")
    assert main(["calibrate", str(folder), "-o", str(out), "--preview",
                 str(kept)]) == EXIT_CONFIG
    assert "use --force" in capsys.readouterr().err
    assert kept.read_bytes() == b"precious" and not out.exists()


def test_preview_path_is_checked_before_the_calibration_is_written(
    board_folder: Path, tmp_path: Path, capsys
) -> None:
    """A preview into a missing folder failed after camera.yaml was written; the re-run then
    stopped on "camera.yaml exists"."""
    out = tmp_path / "cam.yaml"
    for preview, problem in ((tmp_path / "nodir" / "p.png", "folder does not exist"),
                             (tmp_path / "p.txt", "not an image type")):
        code = main(["calibrate", str(board_folder), "-o", str(out), "--preview", str(preview)])
        assert code == EXIT_CONFIG
        assert problem in capsys.readouterr().err
        assert not out.exists()


def test_the_size_most_views_have_wins_over_the_first_one_read(
    board_folder: Path, tmp_path: Path, capsys
) -> None:
    """One odd-sized image read first (its name sorted first) made every other image "of
    another size": "found no 7x4 checkerboard in any of 15 frame(s) but 1"."""
    odd = tmp_path / "a_big.png"
    full = cv2.imread(str(board_folder / "view00.png"))
    assert full is not None
    cv2.imwrite(str(odd), cv2.resize(full, (960, 720)))
    out = tmp_path / "cam.yaml"
    assert main(["calibrate", str(odd), str(board_folder), "-o", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["image_width"], summary["image_height"]) == (640, 480)
    assert len(summary["views_used"]) == 14
    assert any("1 frame(s) of another size than 640x480: a_big.png (960x720)" in w
               for w in summary["warnings"]), summary["warnings"]


def test_as_many_views_at_two_sizes_is_refused_naming_both(
    board_folder: Path, tmp_path: Path, capsys
) -> None:
    for i in range(3):
        full = cv2.imread(str(board_folder / f"view{i:02d}.png"))
        assert full is not None
        cv2.imwrite(str(tmp_path / f"big{i}.png"), cv2.resize(full, (960, 720)))
    small = [str(board_folder / f"view{i:02d}.png") for i in range(3, 6)]
    out = tmp_path / "cam.yaml"
    assert main(["calibrate", str(tmp_path), *small, "-o", str(out)]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "3 at 960x720 and 3 at 640x480" in err, err
    assert "--board" not in err and not out.exists()


def test_too_few_views_says_how_many_were_found_without_blaming_the_board(
    board_folder: Path, tmp_path: Path, capsys
) -> None:
    """It said "found no 7x4 checkerboard in any of 2 frame(s) but 2 (at least 3 are needed);
    check --board" of two good views, and --json printed nothing at all."""
    two = [str(board_folder / "view00.png"), str(board_folder / "view01.png")]
    out = tmp_path / "cam.yaml"
    assert main(["calibrate", *two, "-o", str(out), "--json"]) == EXIT_CONFIG
    captured = capsys.readouterr()
    assert "found a 7x4 checkerboard in only 2 of 2 frame(s); at least 3 are needed" in (
        captured.err
    ), captured.err
    assert "--board" not in captured.err
    error = json.loads(captured.out)["error"]  # what estimate --json does with a failure
    assert "at least 3 are needed" in error and not out.exists()
