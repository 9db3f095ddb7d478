"""`netpose calibrate`: checkerboard images, folders or videos -> camera calibration YAML."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from service.commands._progress import ProgressBar
from service.commands.undistort import side_by_side
from service.core.camera import save_camera
from service.core.errors import CalibrationError
from service.tools.calibration import (
    MIN_VIEWS,
    BoardSpec,
    BoardView,
    calibrate,
    detect_board,
    guess_board_size,
    parse_board_size,
)
from service.tools.calibration_io import (
    CalibrationInputError,
    Frame,
    plan_inputs,
    read_image,
    sample_video,
)

DEFAULT_BOARD = "7x4"  # inner corners of the paper's board
DEFAULT_SQUARE_M = 0.0311
DEFAULT_MAX_VIDEO_FRAMES = 40
# When no view shows the expected board, this many frames are asked what board they do show.
SIZE_GUESS_FRAMES = 6


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate the camera from checkerboard images, folders or videos",
        description=(
            "Detect a checkerboard in every image (or in sharp, distinct frames sampled over a "
            "video), solve focal length, principal point and plumb-bob distortion (k1 k2 p1 p2 "
            "k3), drop outlier views, and write a ROS camera_info YAML file."
        ),
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="image files, folders or videos")
    p.add_argument(
        "--board", default=DEFAULT_BOARD,
        help=f"inner corners COLUMNSxROWS (default {DEFAULT_BOARD})",
    )
    p.add_argument(
        "--square", type=float, default=DEFAULT_SQUARE_M,
        help=f"square edge in metres (default {DEFAULT_SQUARE_M})",
    )
    p.add_argument(
        "--output", "-o", type=Path, default=Path("camera.yaml"),
        help="calibration file to write (default camera.yaml)",
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.add_argument("--name", default="camera", help="camera_name written to the file")
    p.add_argument(
        "--max-frames", type=int, default=DEFAULT_MAX_VIDEO_FRAMES,
        help=f"frames sampled per video (default {DEFAULT_MAX_VIDEO_FRAMES})",
    )
    p.add_argument(
        "--fix-k3", action="store_true",
        help="hold k3 at zero (for few views or a narrow-angle lens)",
    )
    p.add_argument(
        "--preview", type=Path, default=None,
        help="also write an original|undistorted side-by-side image of one view here",
    )
    p.add_argument("--json", action="store_true", help="print a machine-readable summary")
    progress = p.add_mutually_exclusive_group()
    progress.add_argument(
        "--progress", dest="progress", action="store_true", default=None,
        help="show a progress bar (default: only when stderr is a terminal)",
    )
    progress.add_argument("--no-progress", dest="progress", action="store_false")
    p.set_defaults(handler=run)


@dataclass
class _Collected:
    views: list[Any] = field(default_factory=list)  # BoardView
    image_size: tuple[int, int] | None = None
    frames_seen: int = 0
    no_board: list[str] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)
    wrong_size: list[str] = field(default_factory=list)
    video_skipped: int = 0
    # A few frames kept for the board-size hint and the preview (not all: memory).
    sample_frames: list[Any] = field(default_factory=list)


def _collect(args: argparse.Namespace, board: Any) -> _Collected:
    plan = plan_inputs(args.inputs)
    out = _Collected()

    def handle(frame: Frame) -> None:
        out.frames_seen += 1
        size = (int(frame.gray.shape[1]), int(frame.gray.shape[0]))
        if out.image_size is None:
            out.image_size = size
        elif size != out.image_size:
            out.wrong_size.append(f"{frame.name} ({size[0]}x{size[1]})")
            return
        corners = detect_board(frame.gray, board)
        if corners is None:
            out.no_board.append(frame.name)
            if len(out.sample_frames) < SIZE_GUESS_FRAMES:
                out.sample_frames.append(frame)
            return
        out.views.append(BoardView(name=frame.name, corners=corners))
        if not any(f.name == "preview" for f in out.sample_frames):
            out.sample_frames.append(Frame(name="preview", gray=frame.gray))

    if plan.images:
        with ProgressBar("detecting board", enabled=args.progress) as bar:
            for done, path in enumerate(plan.images, start=1):
                try:
                    gray = read_image(path)
                except CalibrationInputError as exc:
                    out.unreadable.append(str(exc))
                else:
                    handle(Frame(name=path.name, gray=gray))
                bar.update(done, len(plan.images))
    for video in plan.videos:
        with ProgressBar(f"scanning {video.name}", enabled=args.progress) as bar:
            frames, _decoded, skipped = sample_video(video, args.max_frames, bar.update)
        out.video_skipped += skipped
        with ProgressBar("detecting board", enabled=args.progress) as bar:
            for done, frame in enumerate(frames, start=1):
                handle(frame)
                bar.update(done, len(frames))
    return out


def _no_board_error(collected: _Collected, board: Any) -> CalibrationError:
    candidates = [f for f in collected.sample_frames if f.name != "preview"]
    guesses = [g for g in (guess_board_size(f.gray) for f in candidates) if g is not None]
    found = len(collected.views)
    seen = (
        f"{collected.frames_seen} frame(s)" if not found
        else f"{collected.frames_seen} frame(s) but {found} (at least {MIN_VIEWS} are needed)"
    )
    if guesses:
        cols, rows = max(set(guesses), key=guesses.count)
        return CalibrationError(
            f"found no {board.label} board in any of {seen}; the images look like a "
            f"{cols}x{rows} board (inner corners): try --board {cols}x{rows}"
        )
    return CalibrationError(
        f"found no {board.label} checkerboard in any of {seen}; check --board (inner corners, "
        "not squares), lighting and focus"
    )


def run(args: argparse.Namespace) -> int:
    board = BoardSpec(*parse_board_size(args.board), square=args.square)
    if args.max_frames < 1:
        raise CalibrationError(f"--max-frames must be at least 1, got {args.max_frames}")
    if args.output.exists() and not args.force:
        raise CalibrationError(f"{args.output} exists; use --force to overwrite it")
    if not args.output.parent.is_dir():
        raise CalibrationError(f"{args.output.parent}: output folder does not exist")

    collected = _collect(args, board)
    if collected.frames_seen == 0:
        raise CalibrationInputError(
            "no input could be read: " + "; ".join(collected.unreadable[:3])
        )
    if len(collected.views) < MIN_VIEWS:
        # Mostly no board: most likely the wrong --board; say what the images do show.
        raise _no_board_error(collected, board)
    assert collected.image_size is not None
    result = calibrate(
        collected.views, board, collected.image_size, fix_k3=args.fix_k3, name=args.name
    )
    save_camera(result.camera, args.output)

    notes = list(result.warnings)
    if collected.unreadable:
        notes.append(f"skipped {len(collected.unreadable)} unreadable input(s): "
                     + "; ".join(collected.unreadable))
    if collected.wrong_size:
        notes.append(
            f"skipped {len(collected.wrong_size)} frame(s) of another size than "
            f"{collected.image_size[0]}x{collected.image_size[1]}: "
            + ", ".join(collected.wrong_size)
        )
    if args.preview is not None:
        _write_preview(args.preview, result.camera, collected)

    summary = result.summary()
    summary.update(
        output=str(args.output),
        frames_examined=collected.frames_seen,
        frames_without_board=collected.no_board,
        video_frames_skipped_blurred_or_duplicate=collected.video_skipped,
        unreadable=collected.unreadable,
        warnings=notes,
    )
    if args.json:
        json.dump(summary, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        _print_report(summary, result)
        for note in notes:
            print(f"warning: {note}", file=sys.stderr)
    return 0


def _write_preview(path: Path, camera: Any, collected: _Collected) -> None:
    frame = next((f for f in collected.sample_frames if f.name == "preview"), None)
    if frame is None:
        return
    if not cv2.imwrite(str(path), side_by_side(camera, frame.gray)):
        raise CalibrationError(f"{path}: cannot write the preview image")


def _print_report(summary: dict[str, Any], result: Any) -> None:
    cam = result.camera
    std = result.std_devs
    print(f"wrote {summary['output']} ({cam.width}x{cam.height})")
    print(
        f"  fx {cam.fx:.2f} ± {std.get('fx', float('nan')):.2f}   "
        f"fy {cam.fy:.2f} ± {std.get('fy', float('nan')):.2f}   "
        f"cx {cam.cx:.2f}   cy {cam.cy:.2f}"
    )
    k1, k2, p1, p2, k3 = cam.distortion
    print(f"  k1 {k1:+.5f}  k2 {k2:+.5f}  p1 {p1:+.6f}  p2 {p2:+.6f}  k3 {k3:+.5f}")
    print(
        f"  RMS reprojection error {result.rms:.3f} px over {len(result.views)} views; "
        f"board coverage {result.coverage:.0%}"
    )
    errors = np.array([v.rms for v in result.views])
    print(f"  per-view RMS: median {np.median(errors):.3f} px, worst {errors.max():.3f} px")
    for view in result.views:
        print(f"    {view.name:40s} {view.rms:6.3f} px  tilt {view.tilt_deg:4.0f} deg")
    for rej in result.rejected:
        print(f"  rejected {rej.name}: {rej.reason}")
    if summary["frames_without_board"]:
        print(f"  no board found in {len(summary['frames_without_board'])} frame(s)")
