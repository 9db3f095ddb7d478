"""The one module that constructs drivers and wires them to the daemon's loop.

Everything is built, and every setting checked, before anything is opened: a configuration
error stops the service before a single message leaves it.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterable

from drivers.mavlink_link import MavlinkLink
from drivers.mavlink_settings import MavlinkSettings
from drivers.sdnotify import NullNotifier, notifier_from_environment
from drivers.sources import FrameSource as DriverFrameSource
from drivers.sources import SourceOptions, create_source
from drivers.telemetry import TelemetrySettings, make_publisher
from service.config import Config, load_config
from service.core.camera import CameraModel, load_camera
from service.core.errors import ConfigError
from service.daemon.loop import Daemon, DaemonParts
from service.daemon.outputs import PreviewSettings
from service.daemon.ports import Notifier
from service.signals import SignalFlags, handle_signals


def driver_sections() -> dict[str, type]:
    """Configuration sections of the drivers this daemon wires (added to the core ones)."""
    return {"mavlink": MavlinkSettings, "telemetry": TelemetrySettings}


def load_daemon_config(
    path: str | None, overrides: Iterable[str] = (), *, check_files: bool = True
) -> Config:
    return load_config(path, overrides, extra_sections=driver_sections(),
                       check_files=check_files)


def build_source(config: Config) -> DriverFrameSource:
    """The frame source for `camera.url`, built but not yet opened. A source that is not there
    at start (the camera manager starts after us) is waited for, like one lost later."""
    # A live source that delivers nothing for stale_after_s is re-opened by the source itself.
    options = SourceOptions(stall_timeout_s=config.camera.stale_after_s, wait_at_start=True)
    return create_source(config.camera.url, options)


def check_simulated(config: Config, source: DriverFrameSource) -> None:
    """A rendered distance (synthetic:, sim:) reaches an autopilot only when the configuration
    says so explicitly: otherwise the service does not start (an installed configuration left
    on the demo source must not feed a real autopilot rendered distances)."""
    if source.rendered and not config.section("mavlink", MavlinkSettings).allow_simulated:
        raise ConfigError(
            "mavlink.allow_simulated",
            "camera.url renders its frames: set it to true to send their distance to an "
            "autopilot (a simulator or a demo), or use a real camera",
        )


def resolve_camera(config: Config, source: DriverFrameSource) -> CameraModel:
    """The calibration file's camera, or the one a rendered source describes."""
    path = config.calibration_path()
    if path is not None:
        return load_camera(path)
    if source.camera is None:
        raise ConfigError(
            "camera.calibration",
            f"required for {source.url.split(':', 1)[0]}: sources (only rendered sources "
            "describe their own camera): give the camera's calibration file",
        )
    return source.camera


def build_parts(config: Config, notifier: Notifier) -> DaemonParts:
    """Every part of the daemon, built and checked, nothing opened: what `run` starts and what
    `run --check` validates are the same objects."""
    source = build_source(config)
    check_simulated(config, source)
    camera = resolve_camera(config, source)
    mavlink = config.section("mavlink", MavlinkSettings)
    telemetry = config.section("telemetry", TelemetrySettings)
    return DaemonParts(
        source=source,
        link=MavlinkLink(mavlink),  # reads and checks the signing key
        telemetry=make_publisher(telemetry),  # builds the Zenoh configuration
        notifier=notifier,
        camera=camera,
        vehicle=telemetry.vehicle,
        preview=PreviewSettings(width=telemetry.preview_width,
                                quality=telemetry.preview_quality),
        telemetry_enabled=telemetry.enabled,
    )


def check_config(config_path: str | None, overrides: Iterable[str] = ()) -> str:
    """`netpose run --check`: the same loading and building as `run`, stopping before anything
    is opened; raises ConfigError/CalibrationError."""
    config = load_daemon_config(config_path, overrides)
    parts = build_parts(config, NullNotifier())
    parts.source.close()
    return f"configuration OK: {config.path or 'defaults'} ({config.digest})"


def main(
    config_path: str | None,
    overrides: Iterable[str] = (),
    duration_s: float | None = None,
    notifier: Notifier | None = None,
) -> int:
    """`netpose run`: load and validate the configuration, run until stopped."""
    overrides = tuple(overrides)
    config = load_daemon_config(config_path, overrides)
    logging.getLogger().setLevel(config.service.log_level)
    notify = notifier or notifier_from_environment(console=sys.stdout)
    try:
        with handle_signals(SignalFlags(), reload=True) as flags:
            daemon = Daemon(config, build_parts(config, notify), flags=flags,
                            load_config=lambda: load_daemon_config(config_path, overrides))
            return daemon.run(duration_s)
    finally:
        notify.close()
