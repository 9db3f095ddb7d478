"""The `netpose` command: one entry point, one module per sub-command in `service.commands`.

Each command module exposes `add_parser(subparsers)` and registers a `handler(args) -> int`.
Command modules import their heavy dependencies (OpenCV, Zenoh, pymavlink) inside the handler so
that `netpose --help` and a mistyped command answer instantly.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Callable, Sequence

from service.core.errors import CalibrationError, ConfigError, NetposeError

# Exit status for configuration errors (sysexits.h EX_CONFIG); the systemd unit lists it in
# RestartPreventExitStatus so a broken configuration does not restart forever.
EXIT_CONFIG = 78

COMMAND_MODULES = (
    "run",
    "estimate",
    "bench",
    "calibrate",
    "undistort",
    "replay",
    "mavlink_check",
    "monitor",
)

Handler = Callable[[argparse.Namespace], int]


def build_parser() -> argparse.ArgumentParser:
    from service import __version__

    parser = argparse.ArgumentParser(
        prog="netpose",
        description="Camera-only distance and orientation to a fish-net, for ArduSub/BlueOS ROVs.",
    )
    parser.add_argument("--version", action="version", version=f"netpose {__version__}")
    parser.add_argument(
        "--log-level",
        default="INFO",
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        help="logging threshold (default: INFO)",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"service.commands.{name}").add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    handler: Handler | None = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 2
    try:
        return handler(args)
    except ConfigError as exc:
        print(f"netpose: configuration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except CalibrationError as exc:
        print(f"netpose: calibration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except NetposeError as exc:
        print(f"netpose: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (`netpose estimate ... | head`): not an error of ours. Point
        # stdout at /dev/null so the interpreter's final flush does not complain again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
