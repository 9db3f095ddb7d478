"""`netpose bench accuracy|speed|integrity|real|soak|damage`: the numbers the targets are judged
by."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from service.core.errors import ConfigError


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser("bench", help="accuracy and speed benchmarks on rendered nets")
    sub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)

    acc = sub.add_parser("accuracy", help="paper Table-1 protocol, occlusion and net-free sets")
    acc.add_argument("--frames", type=int, default=20, help="frames per Table-1 cell (default 20)")
    acc.add_argument("--occluded-frames", type=int, default=10,
                     help="frames per cell with fish covering a third of the frame (default 10)")
    acc.add_argument("--netfree-frames", type=int, default=200,
                     help="frames without a net for the false-positive rate (default 200)")
    acc.add_argument("--seed", type=int, default=1)
    acc.add_argument("--out", type=Path, default=Path("bench/out"),
                     help="folder for accuracy.csv and accuracy.png (default bench/out)")
    acc.set_defaults(handler=_accuracy)

    speed = sub.add_parser("speed", help="frames per second and per-stage time on one core")
    speed.add_argument("--frames", type=int, default=60, help="timed frames per case (default 60)")
    speed.add_argument("--seed", type=int, default=1)
    speed.set_defaults(handler=_speed)

    integ = sub.add_parser(
        "integrity", help="randomised envelope: gross errors, 3-sigma coverage, realism")
    integ.add_argument("--frames", type=int, default=20_000,
                       help="frames to render and estimate (default 20000)")
    integ.add_argument("--seed", type=int, default=1)
    integ.add_argument("--jobs", type=int, default=0,
                       help="worker processes (default: up to 2, the machine's cores)")
    integ.add_argument("--out", type=Path, default=Path("bench/out"),
                       help="folder for integrity.csv (default bench/out)")
    integ.add_argument("--no-realism", action="store_true",
                       help="skip the real-vs-rendered frame statistics")
    integ.set_defaults(handler=_integrity)

    real = sub.add_parser("real", help="real fish-farm frames and net-free scenes (shared data)")
    real.add_argument("--data", type=Path, default=None,
                      help="the shared data folder holding real-field/ (default: shared/data "
                      "beside the checkout, or NETPOSE_SHARED_DATA)")
    real.add_argument("--copies", type=int, default=10,
                      help="noisy copies of each net frame for the stability figure (0: skip)")
    real.set_defaults(handler=_real)

    dmg = sub.add_parser("damage", help="net inspection: holes found and measured, false "
                         "alarms, cost (rendered passes and the real frames)")
    dmg.add_argument("--passes", type=int, default=400,
                     help="rendered passes along a net, half with a hole (default 400)")
    dmg.add_argument("--seed", type=int, default=1)
    dmg.add_argument("--jobs", type=int, default=0,
                     help="worker processes (default: up to 2, the machine's cores)")
    dmg.add_argument("--size", default="1280x720", help="frame size (default 1280x720)")
    dmg.add_argument("--frames", type=int, default=None,
                     help="inspected frames per pass, 10 a second (default 36)")
    dmg.add_argument("--out", type=Path, default=Path("bench/out"),
                     help="folder for damage-misses.png (default bench/out)")
    dmg.add_argument("--no-real", action="store_true", help="skip the real frames")
    dmg.set_defaults(handler=_damage)

    soak = sub.add_parser("soak", help="the daemon for minutes on a 720p camera-like source, "
                          "unconstrained and held to 25 %% of a core")
    soak.add_argument("--duration", type=float, default=120.0,
                      help="seconds per case (default 120)")
    soak.add_argument("--size", default="1280x720", help="frame size (default 1280x720)")
    soak.add_argument("--fps", type=float, default=30.0, help="source frame rate (default 30)")
    soak.add_argument("--json", type=Path, default=None, help="also write the report as JSON")
    soak.set_defaults(handler=_soak)


def _accuracy(args: argparse.Namespace) -> int:
    from service.benchmarks import accuracy

    return accuracy.run(args.frames, args.occluded_frames, args.netfree_frames, args.seed,
                        args.out)


def _speed(args: argparse.Namespace) -> int:
    from service.benchmarks import speed

    return speed.run(args.frames, args.seed)


def _integrity(args: argparse.Namespace) -> int:
    from service.benchmarks import integrity

    return integrity.run(args.frames, args.seed, args.jobs, args.out,
                         realism=not args.no_realism)


def _real(args: argparse.Namespace) -> int:
    from service.benchmarks import real_frames

    return real_frames.run(args.data, copies=args.copies)


def _damage(args: argparse.Namespace) -> int:
    from service.benchmarks import damage

    width, _, height = args.size.partition("x")
    frames = damage.FRAMES_PER_PASS if args.frames is None else args.frames
    if frames < 1:
        raise ConfigError("--frames", "must be at least 1")
    return damage.run(args.passes, args.seed, args.jobs, args.out, width=int(width),
                      height=int(height), real=not args.no_real, frames=frames)


def _soak(args: argparse.Namespace) -> int:
    from service.benchmarks.soak import main_soak

    width, _, height = args.size.partition("x")
    return main_soak(args.duration, width=int(width), height=int(height), fps=args.fps,
                     json_out=args.json)
