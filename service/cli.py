"""The `netpose` command: one entry point, one module per sub-command in `service.commands`.

Each command module exposes `add_parser(subparsers)` and registers a `handler(args) -> int`; its
imports sit at its top. Only the command being run is imported (this is the one lazy import
site), so `netpose --help` and a mistyped command answer instantly, without OpenCV, Zenoh or
pymavlink.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Callable, Sequence
from types import MappingProxyType
from typing import NoReturn

from service import __version__
from service.core.errors import CalibrationError, ConfigError, NetposeError
from service.signals import EarlySignals

# Exit status for configuration errors (sysexits.h EX_CONFIG), a mistake on the command line
# included; the systemd unit lists it in RestartPreventExitStatus so a broken configuration (or
# ExecStart= line) does not restart forever.
EXIT_CONFIG = 78

# name: (module, one-line help shown by `netpose --help`)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("run", "run the service: camera to distance for the autopilot (systemd-ready)"),
    "estimate": ("estimate", "estimate the net's distance and orientation in image files"),
    "bench": ("bench", "benchmarks: accuracy, speed, soak and more"),
    "calibrate": ("calibrate", "calibrate the camera from checkerboard images or a video"),
    "undistort": ("undistort", "undistorted preview of an image with a calibration"),
    "replay": ("replay", "run the pipeline over a recording: CSV, annotated video, summary"),
    "mavlink-check": ("mavlink_check", "check the autopilot's rangefinder settings"),
    "monitor": ("monitor", "topside view of a vehicle's telemetry (Zenoh)"),
    "schema": ("schema", "print the telemetry schema (Markdown)"),
}

Handler = Callable[[argparse.Namespace], int]


class Parser(argparse.ArgumentParser):
    """argparse's parser, with a usage error exiting 78 (EX_CONFIG) rather than argparse's 2.

    The docs promise 78 for bad arguments, and the unit does not restart on 78: with 2, a typo
    in an ExecStart= of a drop-in restarted the service every 2 s for ever. Sub-commands' parsers
    are made of the same class (add_subparsers' default), so this holds for every command.
    """

    def error(self, message: str) -> NoReturn:
        self.print_usage(sys.stderr)
        self.exit(EXIT_CONFIG, f"{self.prog}: error: {message}\n")


def build_parser(argv: Sequence[str] | None = None) -> Parser:
    parser = Parser(
        prog="netpose",
        description="Camera-only distance and orientation to a fish-net, for ArduSub/BlueOS ROVs.",
    )
    parser.add_argument("--version", action="version", version=f"netpose {__version__}")
    parser.add_argument(
        "--log-level",
        default=None,
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        help="logging threshold (default: INFO; for `run`, service.log_level, which this "
        "overrides)",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen = _chosen_command(argv)
    for name, (module, help_text) in COMMANDS.items():
        if name == chosen:
            importlib.import_module(f"service.commands.{module}").add_parser(subparsers)
        else:
            subparsers.add_parser(name, help=help_text, add_help=False)
    return parser


def _chosen_command(argv: Sequence[str] | None) -> str | None:
    """The sub-command named on the command line (the first word that is one)."""
    words = list(sys.argv[1:] if argv is None else argv)
    return next((w for w in words if w in COMMANDS), None)


# numpy's BLAS (OpenBLAS) sizes its thread pool when numpy is first imported, from these. The
# frame loop is one thread on purpose, and the OpenBLAS of numpy 1.24's wheels (bookworm's numpy
# version) spins its idle pool threads after each call: they burned as much CPU as the loop
# itself (the soak's daemon at 171 % of a core instead of 80-87 %); a Pi would have three.
SINGLE_THREADED_NUMERICS = MappingProxyType({"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
                                             "MKL_NUM_THREADS": "1"})


# OpenCV's own warnings repeat on every retry of a camera that is away ("can't be used to
# capture by name", 17 lines in 4 s): the source logs why once, and again when it changes. Read
# by OpenCV when cv2 is first imported; a value set by the user wins (FFmpeg's messages, which
# name a stream's own errors, are left as they are: OPENCV_FFMPEG_LOGLEVEL, docs/sources.md).
QUIET_OPENCV = MappingProxyType({"OPENCV_LOG_LEVEL": "ERROR"})


CONSOLE_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
# The journal stamps each line itself, and reads a leading <N> as its syslog priority.
JOURNAL_FORMAT = "%(levelname)s %(name)s: %(message)s"


class _JournalFormatter(logging.Formatter):
    """Each line prefixed with its syslog priority, so `journalctl -p warning` finds it (every
    line of a stream without one is priority info)."""

    def format(self, record: logging.LogRecord) -> str:
        if record.levelno >= logging.CRITICAL:
            priority = 2
        elif record.levelno >= logging.ERROR:
            priority = 3
        elif record.levelno >= logging.WARNING:
            priority = 4
        elif record.levelno >= logging.INFO:
            priority = 6
        else:
            priority = 7
        # A traceback's lines are one record: each line gets the priority.
        return "\n".join(f"<{priority}>{line}" for line in super().format(record).split("\n"))


def _stderr_is_the_journal() -> bool:
    """systemd names the stream it connected stderr to in JOURNAL_STREAM (device:inode); a
    child's stderr redirected elsewhere no longer matches it."""
    stream = os.environ.get("JOURNAL_STREAM", "")
    try:
        st = os.fstat(sys.stderr.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    return stream == f"{st.st_dev}:{st.st_ino}"


def main(argv: Sequence[str] | None = None) -> int:
    # Before the command's module imports numpy and OpenCV; a value set by the user wins.
    for name, value in (*SINGLE_THREADED_NUMERICS.items(), *QUIET_OPENCV.items()):
        os.environ.setdefault(name, value)
    # The service is signalled by systemd from its first moment: keep what comes while it
    # imports and starts, for its handlers to act on.
    early = EarlySignals().install() if _chosen_command(argv) == "run" else None
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    args.early_signals = early
    journal = _stderr_is_the_journal()
    logging.basicConfig(
        level=getattr(logging, args.log_level or "INFO"),
        format=JOURNAL_FORMAT if journal else CONSOLE_FORMAT,
    )
    if journal:
        for handler_ in logging.getLogger().handlers:
            handler_.setFormatter(_JournalFormatter(JOURNAL_FORMAT))
    # pymavlink says "sig mismatch" at INFO for every message signed with another key (tens a
    # second from an autopilot): the link says it once (drivers/mavlink_link.py).
    logging.getLogger("pymavlink").setLevel(logging.WARNING)
    handler: Handler | None = getattr(args, "handler", None)
    if handler is None:  # no command: a command-line mistake too
        parser.print_help()
        return EXIT_CONFIG
    err = "<3>" if journal else ""  # the service's last line: an error in the journal too
    try:
        return handler(args)
    except ConfigError as exc:
        print(f"{err}netpose: configuration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except CalibrationError as exc:
        print(f"{err}netpose: calibration error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except NetposeError as exc:
        print(f"{err}netpose: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (`netpose estimate ... | head`): not an error of ours. Point
        # stdout at /dev/null so the interpreter's final flush does not complain again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except OSError as exc:
        if _chosen_command(argv) == "run":
            raise  # the service: its traceback (where in the daemon) goes to the journal
        # A file that cannot be read or written (a missing folder, a full disk, stdout on
        # /dev/full): one line naming it, as for any other bad input.
        logging.getLogger("netpose").debug("command failed", exc_info=True)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"netpose: error: {where}{exc.strerror or exc}", file=sys.stderr)
        try:
            sys.stdout.flush()
        except OSError:  # stdout itself failed: the interpreter's last flush would say so again
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    sys.exit(main())
