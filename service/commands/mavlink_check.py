"""`netpose mavlink-check`: the first thing to run on a new vehicle.

Connects like the daemon would, prints the autopilot's identity and rangefinder parameters, and
lists what to change so ArduSub uses netpose's DISTANCE_SENSOR. Exit status: 0 = ready,
3 = changes needed, 1 = no autopilot / link error, 78 = bad arguments.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from drivers.mavlink_link import import_mavutil
from drivers.mavlink_probe import (
    NET_HOLD_PARAMS,
    RANGEFINDER_INSTANCES,
    RNGFND_TYPE_NONE,
    AutopilotReport,
    advise,
    instance_params,
    probe_autopilot,
)
from drivers.mavlink_settings import MavlinkSettings
from service.config import build_section, read_toml
from service.core.errors import ConfigError

EXIT_CHANGES_NEEDED = 3


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "mavlink-check",
        help="check the autopilot link and its rangefinder parameters",
        description="Connect to the autopilot, print its identity and rangefinder parameters, "
        "and say what to change. Exit 0 = ready, 3 = changes needed, 1 = no autopilot, "
        "78 = bad arguments.",
    )
    p.add_argument("--config", "-c", default=None,
                   help="take the link settings from this netpose configuration's [mavlink] "
                   "(the options below override them)")
    p.add_argument("--url", default=None,
                   help="udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT or a serial device "
                   "(default: the configuration's, else the BlueOS router, tcp:127.0.0.1:5777)")
    p.add_argument("--baud", type=int, default=None, help="serial baud rate (default 115200)")
    p.add_argument("--source-system", type=int, default=None, help="our system id (default 1)")
    p.add_argument("--source-component", type=int, default=None,
                   help="our component id (default 197)")
    p.add_argument("--orientation", type=int, default=None,
                   help="MAV_SENSOR_ORIENTATION netpose will send (0 forward, 25 down)")
    p.add_argument("--min-distance", type=float, default=None, help="netpose minimum, metres")
    p.add_argument("--max-distance", type=float, default=None, help="netpose maximum, metres")
    p.add_argument("--net-hold", action="store_true",
                   help="also check Lua scripting and the net-hold applet (docs/net-hold.md)")
    p.add_argument("--signing-key", default=None, help="MAVLink 2 signing key file")
    p.add_argument("--timeout", type=float, default=5.0,
                   help="seconds to wait for the autopilot heartbeat (default 5)")
    p.set_defaults(handler=run)


def _settings(args: argparse.Namespace) -> MavlinkSettings:
    """The daemon's [mavlink] settings when --config names its file (so the check asks the
    autopilot about what the service will send), then the options given."""
    values: dict[str, Any] = {}
    if args.config is not None:
        path = Path(args.config).expanduser().resolve()
        section = build_section("mavlink", MavlinkSettings, read_toml(path).get("mavlink", {}))
        values = {f.name: getattr(section, f.name) for f in dataclasses.fields(section)}
        key_file = section.signing_key_file
        if key_file and not Path(key_file).expanduser().is_absolute():
            values["signing_key_file"] = str(path.parent / Path(key_file).expanduser())
    for key, value in (
        ("url", args.url),
        ("baud", args.baud),
        ("source_system", args.source_system),
        ("source_component", args.source_component),
        ("orientation", args.orientation),
        ("min_distance_m", args.min_distance),
        ("max_distance_m", args.max_distance),
        ("signing_key_file", args.signing_key),
    ):
        if value is not None:
            values[key] = value
    return MavlinkSettings(**values)


def _enum_name(enum: str, value: int) -> str:
    entry = import_mavutil().mavlink.enums.get(enum, {}).get(value)
    return f"{entry.name} ({value})" if entry is not None else str(value)


def _shown_params(report: AutopilotReport, instance: str | None,
                  net_hold: bool) -> list[str]:
    """The parameters worth printing: every setting of the instance netpose uses (or should),
    the type and orientation of the other instances that hold a sensor, not the empty ones."""
    chosen = instance or RANGEFINDER_INSTANCES[0]
    names: list[str] = []
    for n in RANGEFINDER_INSTANCES:
        if n == chosen:
            names.extend(instance_params(n))
        elif report.params.get(f"RNGFND{n}_TYPE", RNGFND_TYPE_NONE) != RNGFND_TYPE_NONE:
            names.extend(instance_params(n)[:2])
    names.append("RNGFND_SQ_MIN")
    if net_hold:
        names.extend(NET_HOLD_PARAMS)
    return names


def run(args: argparse.Namespace) -> int:
    if not args.timeout > 0:
        raise ConfigError("--timeout", f"must be > 0, got {args.timeout}")
    settings = _settings(args)
    print(f"Connecting to {settings.url} as {settings.source_system}/"
          f"{settings.source_component} ...", flush=True)
    report = probe_autopilot(settings, timeout_s=args.timeout)
    firmware = report.firmware or "unknown (no AUTOPILOT_VERSION)"
    print(f"Autopilot: system {report.sysid} component {report.compid}, "
          f"{_enum_name('MAV_TYPE', report.mav_type)}, "
          f"{_enum_name('MAV_AUTOPILOT', report.autopilot)}, MAVLink {report.mavlink_version}, "
          f"firmware {firmware}")
    advice = advise(report, settings, net_hold=args.net_hold)
    print("Parameters:")
    for name in _shown_params(report, advice.instance, args.net_hold):
        value = report.params.get(name)
        shown = "(not on this firmware)" if value is None else f"{value:g}"
        print(f"  {name:<16} {shown}")
    for note in advice.notes:
        print(f"Note: {note}")
    if not advice.changes:
        print("Ready: the autopilot will use netpose's DISTANCE_SENSOR.")
        return 0
    print("To change:")
    for change in advice.changes:
        print(f"  - {change}")
    return EXIT_CHANGES_NEEDED
