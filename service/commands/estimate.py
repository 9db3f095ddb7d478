"""`netpose estimate IMAGE... --calibration CAMERA.yaml --mesh-size METRES [--json]`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from service.core.errors import ConfigError
from service.core.grey import IMAGE_SUFFIXES, frame_order, is_image_name
from service.core.results import NetEstimate
from service.core.scale import (
    DEFAULT_BAR_LENGTH_TOLERANCE,
    DEFAULT_FOCAL_TOLERANCE,
    check_tolerance,
    scale_sigma_fraction,
    total_sigma,
)


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "estimate",
        help="detect the net and estimate distance and orientation in still images",
        description="One line per image, in input order. Unreadable, truncated or corrupt images "
        "are reported with a warning and give no estimate; the exit status is then 1.",
    )
    p.add_argument("images", nargs="+", type=Path, metavar="IMAGE",
                   help="image files, or folders (their images in name order)")
    p.add_argument("--calibration", "-c", required=True, type=Path,
                   help="camera calibration (ROS camera_info YAML or OpenCV FileStorage)")
    p.add_argument("--mesh-size", required=True, type=float, metavar="METRES",
                   help="bar length of the mesh, knot to knot (side of a square mesh), in metres")
    p.add_argument("--opening-angle", type=float, default=90.0, metavar="DEG",
                   help="mesh opening angle in degrees (90 = square, default)")
    p.add_argument("--bar-tolerance", type=float, default=DEFAULT_BAR_LENGTH_TOLERANCE,
                   metavar="FRACTION",
                   help="how well --mesh-size is known, one sigma as a fraction (default "
                   f"{DEFAULT_BAR_LENGTH_TOLERANCE:g}: a used net's bars stretch and foul)")
    p.add_argument("--focal-tolerance", type=float, default=DEFAULT_FOCAL_TOLERANCE,
                   metavar="FRACTION",
                   help="how well the calibration's focal length is known in water, one sigma "
                   f"as a fraction (default {DEFAULT_FOCAL_TOLERANCE:g})")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.set_defaults(handler=run)


def describe(name: str, est: NetEstimate, scale: float = 0.0) -> str:
    """The human-readable line for one image; `scale`: the relative sigma of the image's
    metric scale (service.core.scale), in the range's sigma beside the image's own."""
    if est.too_close:
        return f"{name}: net too close ({est.reason}); no distance"
    if (seen := est.seen_text()) is not None:
        return f"{name}: {seen}"
    if not est.detected or est.range_m is None or est.normal is None:
        return f"{name}: no net ({est.reason or 'not detected'}; confidence {est.confidence:.2f})"
    nx, ny, nz = est.normal
    total = total_sigma(est.range_m, est.sigma_range_m, scale)
    sigma = "" if total is None or est.sigma_range_m is None else (
        f" +- {total:.3f} (image {est.sigma_range_m:.3f}, scale {100 * scale:.1f} %)")
    return (
        f"{name}: net detected, confidence {est.confidence:.2f}: range {est.range_m:.3f} m{sigma}"
        f", distance {est.distance_m:.3f} m, tilt {est.tilt_deg:.1f} deg "
        f"(normal {nx:+.3f} {ny:+.3f} {nz:+.3f}), {est.rois_used}/{len(est.rois)} ROIs, "
        f"{est.timings_ms.get('total', 0.0):.0f} ms"
    )


def _images(paths: list[Path]) -> list[Path]:
    """The paths given, each folder replaced by its images in name order (a folder without any
    stays, to be reported)."""
    out: list[Path] = []
    for path in paths:
        found = sorted((p for p in path.iterdir() if p.is_file() and is_image_name(p)),
                       key=frame_order) if path.is_dir() else []
        out.extend(found or [path])
    return out


def run(args: argparse.Namespace) -> int:
    from service.core.camera import load_camera
    from service.core.estimator import NetEstimator
    from service.core.grey import decode_gray
    from service.core.mesh import MeshGeometry

    try:  # the options first (named as typed), then the calibration file
        mesh = MeshGeometry(args.mesh_size, args.opening_angle)
    except ConfigError as exc:
        option = "--mesh-size" if exc.key.endswith("bar_length_m") else "--opening-angle"
        raise ConfigError(option, exc.problem) from None
    check_tolerance("--bar-tolerance", args.bar_tolerance)
    check_tolerance("--focal-tolerance", args.focal_tolerance)
    scale = scale_sigma_fraction(args.bar_tolerance, args.focal_tolerance)
    camera = load_camera(args.calibration)
    estimator = NetEstimator(camera, mesh)
    failures = 0
    images = _images(args.images)
    for path in images:
        name = str(path)
        try:
            if path.is_dir():
                raise ValueError(f"a folder without images ({', '.join(sorted(IMAGE_SUFFIXES))})")
            if not path.is_file():
                raise ValueError("no such file")
            # The same decoding and grey conversion as every other frame path; a truncated or
            # corrupt file is refused here, before it can produce a distance.
            image, _ = decode_gray(path.read_bytes())
            est = estimator.estimate(image)
        except Exception as exc:  # one bad image must not lose the rest
            failures += 1
            if args.json:
                print(json.dumps({"image": name, "error": str(exc)}), flush=True)
            else:
                print(f"{name}: error: {exc}", flush=True)
            print(f"netpose: warning: {name}: {exc}; no estimate", file=sys.stderr, flush=True)
            continue
        if args.json:
            totals = {f"sigma_{q}_total_m": None if total is None else round(total, 5)
                      for q, total in (
                          ("range", total_sigma(est.range_m, est.sigma_range_m, scale)),
                          ("distance", total_sigma(est.distance_m, est.sigma_distance_m, scale)))}
            print(json.dumps({"image": name, **est.to_json_dict(), **totals}), flush=True)
        else:
            print(describe(name, est, scale), flush=True)
    if failures:
        print(f"netpose: {failures} of {len(images)} images could not be processed",
              file=sys.stderr)
    return 1 if failures else 0
