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
from service.core.camera import CameraModel, check_invertible, save_camera
from service.core.errors import CalibrationError, NetposeError
from service.tools.calibration import (
    MIN_VIEWS,
    RECOMMENDED_VIEWS,
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
    GrayImage,
    InputPlan,
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
class _SizeGroup:
    """The frames of one image size: a calibration is of one camera at one resolution."""

    names: list[str] = field(default_factory=list)
    views: list[BoardView] = field(default_factory=list)
    preview: GrayImage | None = None  # one frame showing the board, for --preview


@dataclass
class _Collected:
    groups: dict[tuple[int, int], _SizeGroup] = field(default_factory=dict)
    frames_seen: int = 0
    no_board: list[str] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)
    video_skipped: int = 0
    # Video frames in which the quick look on a small copy saw the board.
    video_board_seen: int = 0
    # A few frames without the board, for the board-size hint (not all: memory).
    guess_frames: list[Frame] = field(default_factory=list)


def _collect(args: argparse.Namespace, plan: InputPlan, board: BoardSpec) -> _Collected:
    out = _Collected()

    def handle(frame: Frame) -> None:
        out.frames_seen += 1
        size = (int(frame.gray.shape[1]), int(frame.gray.shape[0]))
        # Every size is kept apart until all are read: the first image read need not be of the
        # size most of them have.
        group = out.groups.setdefault(size, _SizeGroup())
        group.names.append(frame.name)
        corners = detect_board(frame.gray, board)
        if corners is None:
            out.no_board.append(frame.name)
            if len(out.guess_frames) < SIZE_GUESS_FRAMES:
                out.guess_frames.append(frame)
            return
        group.views.append(BoardView(name=frame.name, corners=corners))
        if group.preview is None:
            group.preview = frame.gray

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
            sample = sample_video(video, args.max_frames, board.pattern_size, bar.update)
        out.video_skipped += sample.skipped
        out.video_board_seen += sample.board_seen
        with ProgressBar("detecting board", enabled=args.progress) as bar:
            for done, frame in enumerate(sample.frames, start=1):
                handle(frame)
                bar.update(done, len(sample.frames))
    return out


def _choose_size(collected: _Collected) -> tuple[int, int]:
    """The image size with the most board views; refused when another size has as many."""
    ranked = sorted(
        collected.groups.items(), key=lambda item: (len(item[1].views), len(item[1].names)),
        reverse=True,
    )
    (size, group), rest = ranked[0], ranked[1:]
    if group.views and any(len(g.views) == len(group.views) for _, g in rest):
        counts = " and ".join(
            f"{len(g.views)} at {w}x{h}" for (w, h), g in ranked if g.views
        )
        raise CalibrationError(
            f"the inputs are of mixed sizes with as many boards in each ({counts}): a "
            "calibration is of one camera at one resolution; give the images of one size only"
        )
    return size


def _other_sizes(collected: _Collected, size: tuple[int, int]) -> list[str]:
    return [
        f"{name} ({w}x{h})"
        for (w, h), group in collected.groups.items() if (w, h) != size
        for name in group.names
    ]


def _left_out(collected: _Collected, size: tuple[int, int]) -> str:
    """What was read but not used, for the too-few-views error: the board may be in it."""
    notes = []
    others = _other_sizes(collected, size)
    if others:
        notes.append(f"{len(others)} frame(s) of another size than {size[0]}x{size[1]} were "
                     "skipped: " + ", ".join(others[:3]) + (", ..." if len(others) > 3 else ""))
    if collected.video_skipped:
        notes.append(f"{collected.video_skipped} video frame(s) were left out as blurred or "
                     "repeating a view already taken (move the board between views and hold "
                     "it still a moment in each)")
    return "".join(f"; {note}" for note in notes)


def _too_few_views_error(
    collected: _Collected, board: BoardSpec, size: tuple[int, int]
) -> CalibrationError:
    found = len(collected.groups[size].views)
    left_out = _left_out(collected, size)
    if found:
        return CalibrationError(
            f"found a {board.label} checkerboard in only {found} of {collected.frames_seen} "
            f"frame(s); at least {MIN_VIEWS} are needed ({RECOMMENDED_VIEWS} or more "
            f"recommended, at varied tilts and positions){left_out}"
        )
    # A guess of the very board asked for (a blurred board the guesser still makes out) is no
    # hint: "try --board 7x4" to one who gave --board 7x4.
    asked = {board.pattern_size, board.pattern_size[::-1]}
    guesses = [g for g in (guess_board_size(f.gray) for f in collected.guess_frames)
               if g is not None and g not in asked]
    if guesses:
        cols, rows = max(set(guesses), key=guesses.count)
        return CalibrationError(
            f"found no {board.label} board in any of {collected.frames_seen} frame(s); the "
            f"images look like a {cols}x{rows} board (inner corners): try --board {cols}x{rows}"
        )
    if collected.video_board_seen:
        # The board was there (a quick look saw it) but its corners could not be measured:
        # --board is not what is wrong.
        return CalibrationError(
            f"found no {board.label} checkerboard sharp enough to measure in any of "
            f"{collected.frames_seen} frame(s), though it showed in "
            f"{collected.video_board_seen} video frame(s) scanned: hold the board still, in "
            f"focus and well lit{left_out}"
        )
    return CalibrationError(
        f"found no {board.label} checkerboard in any of {collected.frames_seen} frame(s); check "
        f"--board (inner corners, not squares), lighting and focus{left_out}"
    )


def _check_destination(path: Path, option: str, plan: InputPlan, force: bool) -> None:
    """Refuse, before any work, a file that cannot or must not be written: never an input
    (not even with --force: the photos are what the calibration is checked against), an
    existing file only with --force, and only into a folder that exists."""
    target = path.resolve()
    if any(target == p.resolve() for p in (*plan.images, *plan.videos)):
        raise CalibrationError(f"{option} {path} would overwrite one of the inputs")
    if path.is_dir():
        raise CalibrationError(f"{option} {path} is a folder, not a file name")
    if path.exists() and not force:
        raise CalibrationError(f"{path} exists; use --force to overwrite it")
    if not path.parent.is_dir():
        raise CalibrationError(f"{path.parent}: {option} folder does not exist")


def _check_destinations(args: argparse.Namespace, plan: InputPlan) -> None:
    _check_destination(args.output, "--output", plan, args.force)
    if args.preview is None:
        return
    _check_destination(args.preview, "--preview", plan, args.force)
    if args.preview.resolve() == args.output.resolve():
        raise CalibrationError("--preview and --output name the same file")
    if not cv2.haveImageWriter(str(args.preview)):
        raise CalibrationError(
            f"--preview {args.preview} is not an image type OpenCV can write (.png, .jpg)"
        )


def _refuse_folding_model(camera: CameraModel, output: Path) -> None:
    """The loader's own check (load_camera refuses a lens model that folds the image over, so
    undistort, estimate and run would all refuse the file): run before writing, not after."""
    try:
        check_invertible(camera, output)
    except CalibrationError:
        raise CalibrationError(
            f"the solved lens model cannot be inverted over the whole {camera.width}x"
            f"{camera.height} image (its distortion folds the image over, e.g. in corners no "
            f"board reached), so every netpose command would refuse it; {output} not written: "
            "add views with the board near the corners of the image, or hold k3 at zero with "
            "--fix-k3 (a fisheye lens is beyond the plumb-bob model)"
        ) from None


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except (NetposeError, OSError) as exc:
        if args.json:
            # As `netpose estimate --json` does: a failure is a JSON object too, so that a
            # script reading stdout sees why (the message also goes to stderr, as always).
            print(json.dumps({"error": str(exc)}), flush=True)
        raise


def _run(args: argparse.Namespace) -> int:
    board = BoardSpec(*parse_board_size(args.board), square=args.square)
    if args.max_frames < 1:
        raise CalibrationError(f"--max-frames must be at least 1, got {args.max_frames}")
    plan = plan_inputs(args.inputs)
    _check_destinations(args, plan)

    collected = _collect(args, plan, board)
    if collected.frames_seen == 0:
        raise CalibrationInputError(
            "no input could be read: " + "; ".join(collected.unreadable[:3])
        )
    size = _choose_size(collected)
    group = collected.groups[size]
    if len(group.views) < MIN_VIEWS:
        raise _too_few_views_error(collected, board, size)
    result = calibrate(group.views, board, size, fix_k3=args.fix_k3, name=args.name)
    _refuse_folding_model(result.camera, args.output)
    save_camera(result.camera, args.output)

    notes = list(result.warnings)
    if collected.unreadable:
        notes.append(f"skipped {len(collected.unreadable)} unreadable input(s): "
                     + "; ".join(collected.unreadable))
    others = _other_sizes(collected, size)
    if others:
        notes.append(f"skipped {len(others)} frame(s) of another size than {size[0]}x{size[1]}: "
                     + ", ".join(others))
    if args.preview is not None:
        _write_preview(args.preview, result.camera, group.preview)

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


def _write_preview(path: Path, camera: CameraModel, gray: GrayImage | None) -> None:
    if gray is None:
        return
    if not cv2.imwrite(str(path), side_by_side(camera, gray)):
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
