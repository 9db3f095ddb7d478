"""`[web]`: the page the daemon serves (live view, plots, health, set-up, recordings).

Off by default: a plain Pi serves nothing it was not asked to. config/blueos.toml turns it on,
since BlueOS finds extension pages by scanning for listening ports (docs/blueos.md).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from service.core.errors import ConfigError

# Ports BlueOS uses itself or skips when it scans for extension pages (its helper service's
# SKIP_PORTS and BLUEOS_SYSTEM_SERVICES_PORTS), and the Water Linked DVL's 9001.
BLUEOS_PORTS = frozenset({
    22, 80, 81, 2748, 2770, 5201, 5555, 5777, 6020, 6021, 6030, 6040, 7000, 7777, 8000, 8081,
    8088, 8554, 9000, 9001, 9002, 9090, 9100, 9101, 9110, 9111, 9120, 9134, 9150, 9152, 27353,
})
DEFAULT_PORT = 8780
_ORIGIN = re.compile(r"^https?://[A-Za-z0-9.\-\[\]:]+$")


@dataclass(frozen=True)
class WebSettings:
    """Section [web] of the configuration; the field names are the TOML keys."""

    enabled: bool = False
    # 0.0.0.0: reachable on the vehicle's network, and found by BlueOS's port scan, which only
    # considers sockets listening on all addresses.
    host: str = "0.0.0.0"
    port: int = DEFAULT_PORT
    # When set, changing settings, restarting and starting a recording need this token (the
    # page asks for it once). Reading is always open.
    token: str = ""
    # Annotated camera frames per second sent to each open page, and their width in pixels.
    live_hz: float = 4.0
    live_width: int = 640
    live_quality: int = 75
    # Estimates per second pushed to each open page (the newest wins; the plots use them).
    push_hz: float = 10.0
    # Plot history kept for pages that open later, seconds.
    history_s: float = 300.0
    # Largest accepted request body (calibration upload, settings), kilobytes.
    max_upload_kb: int = 256
    # Where recordings go; relative paths are relative to the configuration file's folder.
    recordings_dir: str = "recordings"
    # A recording stops by itself at this size, megabytes.
    max_recording_mb: int = 2000
    # Other origins allowed to change settings (e.g. "http://topside.local:8080"); the page's
    # own origin always is.
    allowed_origins: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        def bad(key: str, problem: str) -> ConfigError:
            return ConfigError(f"web.{key}", problem)

        if not self.host.strip():
            raise bad("host", "must be an address to listen on, e.g. 0.0.0.0")
        if not 1 <= self.port <= 65535:
            raise bad("port", f"must be 1..65535, got {self.port}")
        if self.port in BLUEOS_PORTS:
            raise bad("port", f"{self.port} is used or skipped by BlueOS; the default is "
                      f"{DEFAULT_PORT}")
        if self.token and (len(self.token) < 8 or not self.token.isprintable()):
            raise bad("token", "must be at least 8 printable characters (or empty: no token)")
        for key, low, high in (("live_hz", 0.2, 15.0), ("push_hz", 1.0, 30.0)):
            value = getattr(self, key)
            if not (math.isfinite(value) and low <= value <= high):
                raise bad(key, f"must be {low:g}..{high:g} per second, got {value}")
        if not 160 <= self.live_width <= 1920:
            raise bad("live_width", f"must be 160..1920 px, got {self.live_width}")
        if not 10 <= self.live_quality <= 95:
            raise bad("live_quality", f"must be 10..95, got {self.live_quality}")
        if not (math.isfinite(self.history_s) and 10.0 <= self.history_s <= 3600.0):
            raise bad("history_s", f"must be 10..3600 s, got {self.history_s}")
        if not 4 <= self.max_upload_kb <= 65536:
            raise bad("max_upload_kb", f"must be 4..65536 KB, got {self.max_upload_kb}")
        if not self.recordings_dir.strip():
            raise bad("recordings_dir", "must be a folder path")
        if not 1 <= self.max_recording_mb <= 1_000_000:
            raise bad("max_recording_mb", f"must be 1..1000000 MB, got {self.max_recording_mb}")
        for origin in self.allowed_origins:
            if not _ORIGIN.match(origin):
                raise bad("allowed_origins", f"{origin!r} is not an origin like "
                          "http://host:port (scheme, host and port only)")
