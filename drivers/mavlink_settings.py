"""Configuration and input values of the MAVLink autopilot link (no I/O apart from the key file).

service.config builds `MavlinkSettings` from the TOML section `[mavlink]` (same key names, see
docs/mavlink.md); every problem is reported as ConfigError('mavlink.<key>', problem).
The link's inputs are the core's plain values (service.core.readings): the link knows nothing
about the estimator.
"""

from __future__ import annotations

import logging
import math
import re
import stat
from dataclasses import dataclass
from pathlib import Path

from service.core.errors import ConfigError
from service.core.files import read_small

log = logging.getLogger(__name__)

# Component ids a BlueOS vehicle already uses (191 = MAVLink2Rest/onboard computer, 194 = the
# camera manager, 100-105 = cameras), plus ids that are never valid for a companion service:
# 0 (broadcast) and 1 (the autopilot itself).
RESERVED_COMPONENT_IDS = frozenset({0, 1, 191, 194, *range(100, 106)})

# MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY: a camera-based pose/range source, not used by BlueOS.
DEFAULT_COMPONENT_ID = 197

# ArduPilot drops a MAVLink rangefinder 500 ms after its last message; the send period must
# stay well below that so one lost datagram does not flip the rangefinder to "no data".
AUTOPILOT_RANGEFINDER_TIMEOUT_S = 0.5

_URL_PATTERN = re.compile(r"^(udpout|udpin|tcp):([^:\s]+):(\d{1,5})$")
# A serial device written with its baud rate, as pymavlink and MAVProxy take it
# (/dev/ttyACM0:921600, /dev/serial0,921600): here the rate is mavlink.baud.
_BAUD_SUFFIX = re.compile(r"[:,](\d{4,7})$")
# The lowest minimum distance: "too close" goes out at the minimum, and at 0 cm an autopilot
# whose own RNGFNDn_MIN is 0 reads it as a Good reading of 0.00 m (its test is strict).
MIN_MIN_DISTANCE_M = 0.01
# A key file is 32 bytes, or 64 hex characters and a line end: room for a comment, not more.
_MAX_KEY_FILE_BYTES = 4096


def _is_serial_url(url: str) -> bool:
    return url.startswith("/dev/") or url.startswith("serial:")


def serial_device(url: str) -> str:
    """The device path of a serial URL ('/dev/ttyACM0' or 'serial:/dev/ttyACM0')."""
    return url[len("serial:") :] if url.startswith("serial:") else url


@dataclass(frozen=True)
class MavlinkSettings:
    """Everything the link needs; validated on construction.

    url: 'udpout:HOST:PORT' (we send first; the usual BlueOS choice is a UDP server endpoint),
    'udpin:HOST:PORT' (we listen and answer the last sender), 'tcp:HOST:PORT' (BlueOS router:
    tcp:127.0.0.1:5777), or a serial device '/dev/ttyXXX' / 'serial:/dev/ttyXXX' at `baud`.
    """

    url: str = "tcp:127.0.0.1:5777"
    baud: int = 115200
    source_system: int = 1
    source_component: int = DEFAULT_COMPONENT_ID
    rate_hz: float = 10.0
    # The oldest reading ever repeated; below it, the link's limit follows the measured frame
    # interval and latency (drivers.distance_gate).
    max_age_s: float = 0.8
    orientation: int = 0
    min_distance_m: float = 0.3
    max_distance_m: float = 8.0
    sensor_id: int = 0
    fov_horizontal_deg: float = 0.0
    fov_vertical_deg: float = 0.0
    # Send the net plane (DEBUG_VECT "NET_PLANE") for the autopilot's net-hold applet.
    send_net_plane: bool = True
    # Distances measured in rendered frames (synthetic:, sim: sources) are not facts about the
    # water: the service starts with such a source only when this says so (SITL, a demo).
    allow_simulated: bool = False
    signing_key_file: str | None = None
    heartbeat_timeout_s: float = 3.0
    retry_initial_s: float = 0.5
    retry_max_s: float = 10.0

    def __post_init__(self) -> None:
        self._check_url()
        if _is_serial_url(self.url) and self.baud <= 0:
            self._fail("baud", f"must be a positive baud rate, got {self.baud}")
        if not 1 <= self.source_system <= 254:
            # 255 is the ground station's id by convention; 0 is broadcast.
            self._fail("source_system", f"must be 1..254 (use the vehicle's id), got "
                       f"{self.source_system}")
        if not 0 <= self.source_component <= 255 or (
            self.source_component in RESERVED_COMPONENT_IDS or self.source_component == 255
        ):
            self._fail(
                "source_component",
                f"{self.source_component} is reserved or already used on a BlueOS vehicle "
                f"(0, 1, 100-105, 191, 194, 255); the default is {DEFAULT_COMPONENT_ID}",
            )
        min_rate = 2.0 / AUTOPILOT_RANGEFINDER_TIMEOUT_S  # two messages per autopilot timeout
        if not min_rate <= self.rate_hz <= 50.0:
            self._fail("rate_hz", f"must be between {min_rate:g} and 50 Hz (the autopilot "
                       f"drops the rangefinder after {AUTOPILOT_RANGEFINDER_TIMEOUT_S} s "
                       f"without a message), got {self.rate_hz}")
        if not 0.1 <= self.max_age_s <= 2.0:
            # Below 0.1 s no camera's reading is ever fresh enough (capture to send takes
            # longer): the link would send nothing, for a reason nobody sees.
            self._fail("max_age_s", f"must be 0.1..2 seconds, got {self.max_age_s}")
        if not 0 <= self.orientation <= 40:
            self._fail("orientation", "must be a MAV_SENSOR_ORIENTATION 0..40 (0 forward, "
                       f"25 down), got {self.orientation}")
        if math.isfinite(self.min_distance_m) and 0.0 <= self.min_distance_m < MIN_MIN_DISTANCE_M:
            self._fail("min_distance_m", f"must be at least {MIN_MIN_DISTANCE_M} m: 'too close' "
                       "is sent at the minimum, and at 0 the autopilot may read it as a good "
                       f"0.00 m, got {self.min_distance_m}")
        if not (
            math.isfinite(self.min_distance_m)
            and math.isfinite(self.max_distance_m)
            and 0.0 <= self.min_distance_m < self.max_distance_m <= 655.0
        ):
            self._fail("max_distance_m" if self.min_distance_m >= 0 else "min_distance_m",
                       "need 0 <= min_distance_m < max_distance_m <= 655 m, got "
                       f"{self.min_distance_m}..{self.max_distance_m}")
        if not 0 <= self.sensor_id <= 255:
            self._fail("sensor_id", f"must be 0..255, got {self.sensor_id}")
        for key in ("fov_horizontal_deg", "fov_vertical_deg"):
            value = getattr(self, key)
            if not (math.isfinite(value) and 0.0 <= value <= 180.0):
                self._fail(key, f"must be 0..180 degrees (0 = unknown), got {value}")
        if not self.heartbeat_timeout_s > 0:
            self._fail("heartbeat_timeout_s", f"must be > 0, got {self.heartbeat_timeout_s}")
        if not 0.0 < self.retry_initial_s <= self.retry_max_s:
            self._fail("retry_initial_s", "need 0 < retry_initial_s <= retry_max_s, got "
                       f"{self.retry_initial_s}, {self.retry_max_s}")

    @staticmethod
    def _fail(key: str, problem: str) -> None:
        raise ConfigError(f"mavlink.{key}", problem)

    def _check_url(self) -> None:
        if _is_serial_url(self.url):
            if not serial_device(self.url).startswith("/"):
                self._fail("url", f"serial device must be an absolute path, got {self.url!r}")
            suffix = _BAUD_SUFFIX.search(serial_device(self.url))
            if suffix is not None:
                self._fail("url", f"{self.url!r} ends in a baud rate: give the device alone and "
                           f"the rate as mavlink.baud = {suffix.group(1)}")
            return
        match = _URL_PATTERN.match(self.url)
        if match is None:
            self._fail("url", f"{self.url!r} is not udpout:HOST:PORT, udpin:HOST:PORT, "
                       "tcp:HOST:PORT or a serial device path like /dev/ttyACM0")
        elif not 0 < int(match.group(3)) < 65536:
            self._fail("url", f"port out of range in {self.url!r}")

    @property
    def is_serial(self) -> bool:
        return _is_serial_url(self.url)

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


def load_signing_key(path: str) -> bytes:
    """Read a MAVLink 2 signing key: 32 raw bytes, or 64 hexadecimal characters (one line).

    Raises ConfigError('mavlink.signing_key_file', ...) so a bad key stops start-up instead of
    silently sending unsigned messages that a signing autopilot would drop.
    """
    key = "mavlink.signing_key_file"
    try:
        data = read_small(path, _MAX_KEY_FILE_BYTES)
        mode = Path(path).stat().st_mode
    except OSError as exc:
        raise ConfigError(key, f"cannot read {path}: {exc.strerror or exc}") from exc
    if mode & stat.S_IROTH:
        # Anyone on the companion computer could sign commands to the autopilot with it.
        log.warning("%s: %s is readable by every user; chmod 600 it (or 640 for the "
                    "service's group)", key, path)
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise ConfigError(key, f"{path} must hold 32 raw bytes or 64 hex characters, "
                      f"found {len(data)} bytes")
