"""Daemon configuration: TOML file + `--set section.key=value` overrides -> validated settings.

Each `[section]` of the file maps onto one frozen settings dataclass; the dataclass's field
defaults are the defaults of the keys. Sections owned by this package are listed in
`core_sections()`; the daemon adds the sections of its drivers (MAVLink, telemetry, ...) by
passing their settings classes, so this module never imports a driver.

Validation happens once, at start-up, and every problem becomes
`ConfigError("section.key", problem)`: unknown sections and keys (typos), wrong types, values
outside their range (checked by each dataclass's own `__post_init__`), a calibration file that
does not exist. The CLI turns that into one line and exit status 78.

`Config.digest` is a SHA-256 digest of the canonical effective configuration (defaults filled
in, keys sorted, secrets left out: the telemetry schema's `config_digest`), published with the
telemetry status and logged at start so a log can be tied to the settings that produced it.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import math
import tomllib
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

from service.core.budget import BudgetSettings
from service.core.damage import DamageSettings
from service.core.errors import ConfigError
from service.core.estimator import EstimatorSettings
from service.core.files import read_small
from service.core.mesh import MeshGeometry
from service.core.redact import redact_config
from service.core.scale import DEFAULT_FOCAL_TOLERANCE, check_tolerance, scale_sigma_fraction
from service.core.tracking import FilterSettings

T = TypeVar("T")

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
# A configuration is a few kilobytes; a larger "file" is something else named by mistake.
MAX_CONFIG_BYTES = 1 << 20
BUILTIN_CALIBRATION = "builtin"


@dataclass(frozen=True)
class CameraSettings:
    """`[camera]`: where frames come from and how the lens is described."""

    # REQUIRED. Frame source URL; the schemes are those of drivers.sources (rtsp://, v4l2:...,
    # file paths, synthetic:). See docs/sources.md.
    url: str
    # ROS camera_info YAML (or OpenCV FileStorage) for this camera at any resolution of the same
    # aspect ratio; relative paths are relative to the configuration file. "builtin" means the
    # source describes its own camera (only the synthetic source does).
    calibration: str = BUILTIN_CALIBRATION
    # How well the calibration's focal length is known in water, one sigma as a fraction of it:
    # an underwater calibration is good to 0.5-1 %, and salinity and temperature move the water's
    # refraction by ~0.3 %. Like the mesh's bar length it scales every distance alike; see
    # mesh.bar_length_tolerance.
    focal_tolerance: float = DEFAULT_FOCAL_TOLERANCE
    # How long one read waits for a frame; also bounds how fast the daemon reacts to a stop.
    read_timeout_s: float = 0.2
    # No frame for this long: the source is reported down and re-opened.
    stale_after_s: float = 2.0

    def __post_init__(self) -> None:
        if not self.url.strip():
            raise ConfigError("camera.url", "must not be empty")
        if not self.calibration.strip():
            raise ConfigError("camera.calibration", "must be a file path or 'builtin'")
        check_tolerance("camera.focal_tolerance", self.focal_tolerance)
        if not 0.01 <= self.read_timeout_s <= 0.5:
            raise ConfigError(
                "camera.read_timeout_s",
                f"must be 0.01..0.5 s (a stop must be honoured within a second), "
                f"got {self.read_timeout_s}",
            )
        if not self.stale_after_s > self.read_timeout_s:
            raise ConfigError("camera.stale_after_s", "must be longer than camera.read_timeout_s")
        if not self.stale_after_s <= 3600.0:
            raise ConfigError("camera.stale_after_s", f"must be at most 3600 s (an hour without "
                              f"a frame is a lost camera), got {self.stale_after_s}")


@dataclass(frozen=True)
class ServiceSettings:
    """`[service]`: logging, status and what the autopilot is told."""

    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    # One summary line (frames, detections, rates, latency) in the log this often.
    summary_interval_s: float = 60.0
    # STATUS line to systemd and status message on telemetry this often.
    status_interval_s: float = 1.0
    # Which distance the autopilot's forward rangefinder receives: "perpendicular" (camera to net
    # plane, what net-following wants) or "optical_axis" (along the camera axis, what a physical
    # forward rangefinder would measure).
    autopilot_distance: Literal["perpendicular", "optical_axis"] = "optical_axis"

    def __post_init__(self) -> None:
        if self.log_level not in LOG_LEVELS:
            raise ConfigError("service.log_level", f"must be one of {', '.join(LOG_LEVELS)}")
        if not 1.0 <= self.summary_interval_s <= 86400.0:
            raise ConfigError("service.summary_interval_s", "must be 1..86400 s")
        if not 0.1 <= self.status_interval_s <= 60.0:
            raise ConfigError("service.status_interval_s", "must be 0.1..60 s")


def core_sections() -> dict[str, type]:
    """The sections this package defines itself (drivers add theirs via `load_config`)."""
    return {
        "camera": CameraSettings,
        "mesh": MeshGeometry,
        "filter": FilterSettings,
        "estimator": EstimatorSettings,
        "service": ServiceSettings,
        "damage": DamageSettings,
        "budget": BudgetSettings,
    }


@dataclass(frozen=True)
class Config:
    """The validated configuration: one settings object per section."""

    sections: Mapping[str, Any]
    effective: Mapping[str, Mapping[str, Any]]  # JSON-ready, defaults filled in
    digest: str
    path: Path | None = None
    overrides: tuple[str, ...] = field(default=())

    def section(self, name: str, cls: type[T]) -> T:
        value = self.sections.get(name)
        if not isinstance(value, cls):
            raise ConfigError(name, f"section is not a {cls.__name__}")
        return value

    @property
    def camera(self) -> CameraSettings:
        return self.section("camera", CameraSettings)

    @property
    def mesh(self) -> MeshGeometry:
        return self.section("mesh", MeshGeometry)

    @property
    def filter(self) -> FilterSettings:
        return self.section("filter", FilterSettings)

    @property
    def estimator(self) -> EstimatorSettings:
        return self.section("estimator", EstimatorSettings)

    @property
    def service(self) -> ServiceSettings:
        return self.section("service", ServiceSettings)

    @property
    def damage(self) -> DamageSettings:
        return self.section("damage", DamageSettings)

    @property
    def budget(self) -> BudgetSettings:
        return self.section("budget", BudgetSettings)

    @property
    def scale_sigma_fraction(self) -> float:
        """The relative one-sigma error every distance carries from the mesh's bar length and
        the camera's focal length (`service.core.scale`)."""
        return scale_sigma_fraction(self.mesh.bar_length_tolerance, self.camera.focal_tolerance)

    def calibration_path(self) -> Path | None:
        """The calibration file to load, or None for a source that describes its own camera."""
        value = self.camera.calibration
        if value == BUILTIN_CALIBRATION:
            return None
        return self.file_path(value)

    def file_path(self, value: str) -> Path:
        """A file or folder the configuration names: relative to the configuration file's
        folder (the service's working directory is not where its configuration lives)."""
        p = Path(value).expanduser()
        if not p.is_absolute() and self.path is not None:
            p = self.path.parent / p
        return p

    def changed_sections(self, other: Config) -> set[str]:
        """Sections whose effective values differ between two configurations (for reloads)."""
        names = set(self.effective) | set(other.effective)
        return {n for n in names if self.effective.get(n) != other.effective.get(n)}


# -- parsing ---------------------------------------------------------------------------------
def parse_override(text: str) -> tuple[str, str, Any]:
    """'section.key=value' -> (section, key, value). The value is read as a TOML value
    (1, 0.5, true, "text", [1, 2]); anything that is not valid TOML is taken as a plain string,
    so `--set camera.url=rtsp://host/stream` needs no quotes."""
    name, sep, raw = text.partition("=")
    name = name.strip()
    section, dot, key = name.partition(".")
    if not sep or not dot or not section or not key or "." in key:
        raise ConfigError(name or text, "override must look like section.key=value")
    raw = raw.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return section, key, value


def read_toml(path: Path) -> dict[str, Any]:
    try:
        # utf-8-sig: a file saved by an editor that writes a byte-order mark reads the same.
        text = read_small(path, MAX_CONFIG_BYTES).decode("utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(str(path), "configuration file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(str(path), f"cannot read configuration file ({exc})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(path), f"invalid TOML: {exc}") from None
    except RecursionError:  # Python's parser recurses per nested array or table
        raise ConfigError(str(path), "invalid TOML: nested too deeply") from None


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp) if a is not type(None))
    if origin in (tuple, list):
        return "a list"
    if isinstance(tp, type):
        return {"float": "a number", "int": "an integer", "bool": "true or false",
                "str": "a string"}.get(tp.__name__, tp.__name__)
    return str(tp)


def _coerce(key: str, value: Any, tp: Any) -> Any:
    """Check a TOML value against a dataclass field type; returns the value to pass on."""
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(key, f"must be {_type_name(tp)}, got {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(tp) if a is not type(None)]
        for option in options:
            try:
                return _coerce(key, value, option)
            except ConfigError:
                continue
        raise ConfigError(key, f"must be {_type_name(tp)}, got {value!r}")
    if origin in (tuple, list):
        if not isinstance(value, list | tuple):
            raise ConfigError(key, f"must be a list, got {value!r}")
        args = typing.get_args(tp)
        homogeneous = (origin is list and len(args) == 1) or (
            origin is tuple and len(args) == 2 and args[1] is Ellipsis
        )
        inner = args[0] if homogeneous else Any
        items = [_coerce(key, v, inner) for v in value]
        return tuple(items) if origin is tuple else items
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise ConfigError(key, f"must be a table, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, f"must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, f"must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(key, f"must be a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ConfigError(key, f"must be finite, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(key, f"must be a string, got {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, str):
            raise ConfigError(key, f"must be a path string, got {value!r}")
        return Path(value)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        try:
            return tp(value)
        except ValueError:
            allowed = ", ".join(repr(m.value) for m in tp)
            raise ConfigError(key, f"must be one of {allowed}, got {value!r}") from None
    return value


def build_section(name: str, cls: type[T], values: Mapping[str, Any]) -> T:
    """Instantiate a settings dataclass from one TOML table, naming the key on any problem."""
    if not isinstance(values, Mapping):
        raise ConfigError(name, "must be a table ([" + name + "])")
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    hints = typing.get_type_hints(cls)
    for key in values:
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise ConfigError(f"{name}.{key}", f"unknown key (known keys: {known})")
    kwargs: dict[str, Any] = {}
    for fname, f in fields.items():
        key = f"{name}.{fname}"
        if fname in values:
            kwargs[fname] = _coerce(key, values[fname], hints.get(fname, Any))
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(key, "is required")
    try:
        settings = cls(**kwargs)
        # Some settings classes validate in an explicit method rather than __post_init__.
        validate = getattr(settings, "validate", None)
        if callable(validate):
            validate()
        return settings
    except ConfigError as exc:
        if exc.key.partition(".")[0] == name:
            raise
        raise ConfigError(f"{name}.{exc.key}", exc.problem) from None
    except (ValueError, TypeError) as exc:
        raise ConfigError(name, str(exc)) from None


def _jsonable(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return _jsonable(value.value)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, tuple | list):
        return [_jsonable(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    return value


def _effective(settings: Any) -> dict[str, Any]:
    return {
        f.name: _jsonable(getattr(settings, f.name))
        for f in dataclasses.fields(settings)
        if f.init
    }


def config_digest(effective: Mapping[str, Any]) -> str:
    """Short stable digest of the effective configuration: 'sha256:' + 16 hex digits of its
    canonical JSON, secrets redacted, so equal digests mean equal settings and the digest
    reveals nothing about the secrets."""
    canonical = json.dumps(redact_config(effective), sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(canonical.encode("utf-8")).hexdigest()[:16]


def load_config(
    path: str | Path | None,
    overrides: Iterable[str] = (),
    extra_sections: Mapping[str, type] | None = None,
    *,
    check_files: bool = True,
    drop: Iterable[str] = (),
) -> Config:
    """Read, merge overrides, validate. `path=None` means defaults plus overrides only.
    `drop`: keys ('section.key') or whole sections of the file left out, as if not written
    (their defaults hold; the overrides still apply)."""
    sections = core_sections()
    sections.update(extra_sections or {})
    cfg_path = None if path is None else Path(path).expanduser().resolve()
    doc: dict[str, Any] = {} if cfg_path is None else read_toml(cfg_path)
    for dropped in drop:
        section_name, dot, key = dropped.partition(".")
        table = doc.get(section_name)
        if not dot:
            doc.pop(section_name, None)
        elif isinstance(table, dict):
            table.pop(key, None)
    override_list = tuple(overrides)
    for text in override_list:
        section, key, value = parse_override(text)
        table = doc.setdefault(section, {})
        if not isinstance(table, dict):
            raise ConfigError(section, "must be a table")
        table[key] = value
    for name in doc:
        if name not in sections:
            raise ConfigError(name, f"unknown section (known: {', '.join(sorted(sections))})")
    built: dict[str, Any] = {}
    effective: dict[str, dict[str, Any]] = {}
    for name, cls in sections.items():
        built[name] = build_section(name, cls, doc.get(name, {}))
        effective[name] = _effective(built[name])
    config = Config(
        sections=built,
        effective=effective,
        digest=config_digest(effective),
        path=cfg_path,
        overrides=override_list,
    )
    if check_files:
        calibration = config.calibration_path()
        if calibration is not None and not calibration.is_file():
            raise ConfigError("camera.calibration", f"file not found: {calibration}"
                              if not calibration.exists() else
                              f"{calibration} is not a regular file")
    return config
