"""`netpose run`: the daemon (frame source -> estimator -> filter -> MAVLink and telemetry)."""

from __future__ import annotations

import argparse
import faulthandler
import logging
import os
import sys

from service.core.errors import ConfigError
from service.daemon.wiring import check_config, main


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "run",
        help="run the service: camera to distance for the autopilot (systemd-ready)",
        description="Run the netpose daemon until SIGTERM/SIGINT; SIGHUP reloads the "
        "configuration. Exit status 78 on a configuration error.",
    )
    p.add_argument("--config", "-c", metavar="FILE", default=None,
                   help="TOML configuration (see config/netpose.toml); default: built-in "
                   "defaults, which need at least --set mesh.bar_length_m=...")
    p.add_argument("--set", dest="overrides", metavar="SECTION.KEY=VALUE", action="append",
                   default=[], help="override one configuration key (TOML value), repeatable")
    p.add_argument("--duration", type=float, metavar="SECONDS", default=None,
                   help="stop cleanly after this many seconds (default: run until stopped)")
    p.add_argument("--check", action="store_true",
                   help="validate the configuration (and load the calibration), print the "
                   "effective settings' digest and exit: 0 when valid, 78 when not")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if getattr(args, "log_level", None) is not None:
        # The command line wins over the file, as --set does (and keeps winning at reloads).
        args.overrides = [*args.overrides, f"service.log_level={args.log_level}"]
    if args.check:
        print(check_config(args.config, args.overrides))
        return 0
    if args.duration is not None and not args.duration > 0:
        raise ConfigError("--duration", "must be a positive number of seconds")
    # systemd's watchdog ends a hung daemon with SIGABRT: every thread's Python stack goes to
    # stderr (the journal) first, the one thing that says where it hung (the unit keeps the
    # core dump, hundreds of MB on an SD card, from being written: LimitCORE=0).
    faulthandler.enable(all_threads=True)
    status = main(args.config, args.overrides, args.duration,
                  early=getattr(args, "early_signals", None))
    # Everything is closed and the final lines are logged. The interpreter's own teardown of
    # numpy, OpenCV and Zenoh (and of a capture thread still inside an FFmpeg open) takes
    # another ~0.5 s that nothing needs, and a stop must fit systemd's budget: leave now.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
