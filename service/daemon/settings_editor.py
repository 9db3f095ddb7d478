"""Changing the configuration from the web page: the same validation as the file, then a reload.

`SettingsEditor` is what the page's driver calls (drivers.web.page.SettingsBackend, structurally).
A change `{"mesh.bar_length_m": 0.03}` is written into the TOML text with tomlkit (comments and
layout kept), the whole new file is validated exactly as `netpose run` validates it (the same
loader, the calibration file loaded and the parts built as `netpose run --check` builds them),
and only then replaces the old file (atomic rename).
The running daemon re-reads it through its ordinary reload (the flag SIGHUP sets), and the
editor waits for the outcome. A change the running parts cannot take live (camera, MAVLink,
telemetry) is saved and reported as needing a restart; `restart()` restarts the daemon's parts
in-process (service/daemon/wiring.py). Any problem raises ConfigError naming the key, and then
neither the file nor the daemon changed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import os
import threading
import time
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal

import tomlkit
from tomlkit.items import Table

from service.config import Config
from service.core.errors import CalibrationError, ConfigError, SettingsLockedError
from service.core.files import write_atomically
from service.core.redact import REDACTED, redact_config
from service.daemon.loop import ReloadOutcome

log = logging.getLogger(__name__)

# What the page offers, by group. A section whose name contains "hold" (net hold, once it
# exists) is offered whole.
GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Net", ("mesh.bar_length_m", "mesh.opening_angle_deg")),
    ("Camera", ("camera.url", "camera.calibration")),
    ("Autopilot (MAVLink)", ("mavlink.url", "mavlink.orientation", "mavlink.sensor_id",
                             "service.autopilot_distance")),
    ("Telemetry (Zenoh)", ("telemetry.mode", "telemetry.connect", "telemetry.listen",
                           "telemetry.vehicle")),
)
# Only these are changed from the page (it is open to the vehicle's network; the token is off
# by default): not what lets simulated distances reach the autopilot, the filter's gates, or
# keys that name files to read.
OFFERED = frozenset(key for _, keys in GROUPS for key in keys)
# Changed only in the file: the page's own access and address.
LOCKED_SECTIONS = frozenset({"web"})
RELOAD_TIMEOUT_S = 15.0
# Every setting the page offers changes what the autopilot is told or where it goes (the mesh
# size scales every distance; the camera, the link and the sensor's orientation replace them),
# and a restart stops the distances for seconds: none of that mid-dive. The pilot disarms first,
# as ArduPilot itself asks for some of its own parameters. Whoever reaches the page (BlueOS
# ships it without a token) can no longer change the rangefinder of a vehicle in use.
ARMED = ("the vehicle is armed: settings, calibration and restarts from the page wait until it "
         "is disarmed (a change mid-dive changes the distance the autopilot steers by); an "
         "autopilot whose heartbeat is lost stays armed as last heard, until it is heard "
         "disarmed or netpose is restarted")
# How often a wait for the daemon's reload looks whether it is stopping instead.
_STOP_POLL_S = 0.1

Loader = Callable[[Path], Config]

# While set-up mode serves the page, a configuration without a mesh size is loaded with this
# stand-in (service/daemon/wiring.py): the page must show the key as unset, not as this value.
SET_UP_MESH_KEY = "mesh.bar_length_m"
SET_UP_MESH_OVERRIDE = f"{SET_UP_MESH_KEY}=0.0275"


def _field_kind(tp: Any) -> dict[str, Any]:
    """How the page shows a setting of this type."""
    origin = typing.get_origin(tp)
    if origin is Literal:
        return {"type": "choice", "choices": list(typing.get_args(tp))}
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(tp) if a is not type(None)]
        kind = _field_kind(options[0]) if len(options) == 1 else {"type": "text"}
        return {**kind, "optional": True}
    if origin in (tuple, list):
        return {"type": "list"}
    return {"type": {bool: "bool", int: "integer", float: "number"}.get(tp, "text")}


# What a recording's netpose.toml keeps: everything its replay's output depends on.
RECORDED_SECTIONS = ("mesh", "estimator", "filter", "service", "damage")


def tuning_toml(config: Config) -> str:
    """[mesh], [estimator], [filter], [service] and [damage] in force, and the camera's focal
    tolerance (the sigmas sent count it), as TOML (for recordings)."""
    doc = tomlkit.document()
    doc.add(tomlkit.comment("The settings in force when this recording started (netpose "
                            "replay --config)."))
    doc.add("camera", {"focal_tolerance": config.camera.focal_tolerance})
    for name in RECORDED_SECTIONS:
        values = {k: v for k, v in config.effective[name].items() if v is not None}
        doc.add(name, values)
    return tomlkit.dumps(doc)


def _texts_in(value: Any) -> list[str]:
    """Every string in a value sent by the page, nested lists and tables included."""
    if isinstance(value, str):
        return [value]
    if isinstance(value, list | tuple):
        return [t for item in value for t in _texts_in(item)]
    if isinstance(value, dict):
        return [t for k, v in value.items() for t in (*_texts_in(k), *_texts_in(v))]
    return []


def _shown(doc: tomlkit.TOMLDocument, key: str) -> str:
    """A key's value in a parsed file, as the log shows it (a secret left out)."""
    section, _, name = key.partition(".")
    table = doc.get(section)
    value = table.get(name) if isinstance(table, Table | dict) else None
    if value is None:
        return "(default)"
    plain = value.unwrap() if hasattr(value, "unwrap") else value
    return repr(redact_config({name: plain})[name])


def _by(client: str) -> str:
    return f" by {client}" if client else ""


class SettingsEditor:
    """Validate-and-apply for the page; one per `netpose run` (it outlives restarts)."""

    def __init__(self, path: Path | None, overrides: tuple[str, ...], load: Loader,
                 request_reload: Callable[[], None],
                 request_restart: Callable[[], None],
                 load_incomplete: Loader | None = None,
                 stopping: Callable[[], bool] = lambda: False,
                 load_shown: Loader | None = None,
                 armed: Callable[[], bool | None] = lambda: None) -> None:
        """`load` checks a file as `netpose run` does; `load_incomplete` as set-up mode may save
        it (what set-up is there to finish may still be missing), used while `setting_up`.
        `stopping` says that the daemon is stopping (a signal, a restart): it reloads nothing
        then, and a saved change is not waited for. `armed`: whether the autopilot says it is
        armed now (None: no autopilot heard), which locks every change (ARMED)."""
        self.path = path
        self._overridden = {text.partition("=")[0].strip() for text in overrides}
        self._load = load
        self._load_incomplete = load_incomplete
        # What set-up mode shows of a file with any other error (its broken keys at their
        # defaults): without it the form came up blank and all text, and no save could fix it.
        self._load_shown = load_shown
        self.setting_up = threading.Event()
        self._request_reload = request_reload
        self._request_restart = request_restart
        self._stopping = stopping
        self._armed = armed
        self._lock = threading.Lock()  # one change at a time
        self._outcomes = threading.Condition()
        self._reloads = 0
        self._last_outcome: ReloadOutcome | None = None
        self.restart_pending: set[str] = set()
        self._camera_note = ""  # set-up mode: why the camera shows nothing (set on its thread)

    # -- the daemon's side -----------------------------------------------------------------
    def reloaded(self, outcome: ReloadOutcome) -> None:
        """Daemon(on_reload=...): called on the loop thread after every reload."""
        with self._outcomes:
            self._reloads += 1
            self._last_outcome = outcome
            if outcome.ok:
                # What differs from the running parts now (the daemon compares the file with
                # them): a change undone needs no restart any more.
                self.restart_pending = set(outcome.restart_needed)
            self._outcomes.notify_all()

    def restarted(self) -> None:
        self.restart_pending.clear()

    def note_camera(self, text: str) -> None:
        """Set-up mode: what keeps the live view dark (a camera that cannot be opened, or
        gives no frames), said with the configuration's problem; "" once frames come."""
        self._camera_note = text

    # -- the page's side -------------------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        editable, reason = self._editable()
        if editable and self._armed():
            editable, reason = False, ARMED
        values: dict[str, Any] = {}
        config: Config | None = None
        problem = ""
        if self.path is not None:
            try:
                config = self._load(self.path)
            except (ConfigError, CalibrationError) as exc:
                problem = f"configuration error: {exc}"
                set_up = self._set_up_loader()
                if set_up is not None:  # what is there, to show it
                    for loader in (set_up, self._load_shown):
                        if config is None and loader is not None:
                            with contextlib.suppress(ConfigError, CalibrationError):
                                config = loader(self.path)
        groups = []
        for title, keys in self._groups(config):
            fields = []
            for key in keys:
                section, _, name = key.partition(".")
                field = self._describe(config, section, name)
                fields.append({"key": key, **field,
                               "overridden": key in self._overridden})
                if config is not None:
                    # The page is open to the vehicle's network (the token guards changes,
                    # not reading): a camera URL's password is not shown, as in the log.
                    value = config.effective.get(section, {}).get(name)
                    if key == SET_UP_MESH_KEY and SET_UP_MESH_OVERRIDE in config.overrides:
                        value = None  # the stand-in, not the file's
                    values[key] = redact_config({name: value})[name]
            groups.append({"title": title, "fields": fields})
        problem = "; ".join(p for p in (problem, self._camera_note) if p)
        return {"path": str(self.path) if self.path else None, "editable": editable,
                "reason": reason, "problem": problem, "groups": groups, "values": values,
                "restart_pending": sorted(self.restart_pending)}

    def apply(self, changes: Mapping[str, Any], client: str = "") -> dict[str, Any]:
        """`client`: who asked (the page's peer address), for the log."""
        self._check_disarmed()
        editable, reason = self._editable()
        if not editable:
            raise ConfigError("configuration", reason)
        assert self.path is not None
        for key, value in changes.items():
            for text in [key, *_texts_in(value)]:
                try:
                    text.encode("utf-8")
                except UnicodeEncodeError:  # a lone surrogate (JSON's \ud800): no file text
                    raise ConfigError(ascii(key), "is not valid text (a lone surrogate)"
                                      ) from None
            section, dot, name = key.partition(".")
            if not dot or not section or not name or "." in name:
                raise ConfigError(key, "must look like section.key")
            if section in LOCKED_SECTIONS:
                raise ConfigError(key, f"[{section}] is changed in the configuration file "
                                  f"only ({self.path})")
            if key not in OFFERED and "hold" not in section:
                raise ConfigError(key, "is not one of the settings the page changes: change "
                                  f"it in the configuration file ({self.path})")
            if key in self._overridden:
                raise ConfigError(key, "is set with --set on the command line, which wins over "
                                  "the file: change it there")
            if isinstance(value, dict):
                raise ConfigError(key, f"must be a single value, got {value!r}")
            if isinstance(value, str) and REDACTED in value:
                raise ConfigError(key, f"holds {REDACTED} where a secret was (the page does not "
                                  "show it): type the whole value, secret included")
        with self._lock:
            old_text = self.path.read_text(encoding="utf-8")
            try:
                doc = tomlkit.parse(old_text)
            except tomlkit.exceptions.ParseError as exc:
                raise ConfigError(str(self.path), f"invalid TOML: {exc}") from None
            said = {key: _shown(doc, key) for key in changes}
            for key, value in changes.items():
                section, _, name = key.partition(".")
                table = doc.get(section)
                if table is None:
                    table = tomlkit.table()
                    doc.add(section, table)
                if not isinstance(table, Table | dict):
                    raise ConfigError(section, "must be a table")
                if value is None:
                    table.pop(name, None)  # back to the default
                else:
                    table[name] = value
            new_text = tomlkit.dumps(doc)
            if new_text == old_text:
                return {"saved": False, "message": "nothing to change", "changed": [],
                        "restart_needed": sorted(self.restart_pending)}
            write_atomically(self.path, new_text.encode("utf-8"), check=self._validate)
            # Who changed what, from what: the page is open to the vehicle's network, and an
            # unexpected distance is traced to its cause here.
            log.info("configuration changed from the web page%s: %s", _by(client),
                     "; ".join(f"{key} {said[key]} -> {_shown(doc, key)}"
                               for key in sorted(changes)))
            outcome = self._reload()
            if outcome is not None and not outcome.ok:
                # The daemon refused what the file now says (the vehicle armed between the
                # check above and the reload): the file goes back, or the next restart would
                # apply it unannounced.
                write_atomically(self.path, old_text.encode("utf-8"))
                log.info("configuration change from the web page undone: %s", outcome.error)
        if outcome is None:
            # A restart (or a stop) came while the change was saved: the restarted daemon
            # starts from the file, so the change applies then. Waiting for a reload that a
            # stopping daemon never does held its page, and with it the restart, 15 s.
            return {"saved": True, "message": "saved; applies as the service restarts",
                    "changed": [], "restart_needed": [], "digest": ""}
        if not outcome.ok:
            # Validated a moment ago: the vehicle armed meanwhile, or a file changed under us.
            raise ConfigError("configuration", f"not changed: the daemon refused it: "
                              f"{outcome.error}")
        needs = sorted(self.restart_pending)
        message = "saved and applied" if not needs else (
            f"saved; changes to {', '.join(needs)} take effect after a restart")
        if outcome.pending:
            message = f"saved; set-up not finished: {outcome.pending}"
        return {"saved": True, "message": message, "changed": list(outcome.changed),
                "restart_needed": needs, "digest": outcome.digest}

    def install_calibration(self, path: Path, client: str = "") -> dict[str, Any]:
        """Copy an uploaded calibration (already checked by the page) next to the file."""
        self._check_disarmed()
        editable, reason = self._editable()
        if not editable:
            raise ConfigError("camera.calibration", reason)
        assert self.path is not None
        digest = hashlib.sha256(path.read_bytes()).hexdigest()[:8]
        target = self.path.parent / f"calibration-{digest}{path.suffix.lower()}"
        created = not target.exists()
        if created:
            write_atomically(target, path.read_bytes())
        try:
            return self.apply({"camera.calibration": target.name}, client)
        except ConfigError:
            if created:
                target.unlink(missing_ok=True)
            raise

    def restart(self, client: str = "") -> None:
        self._check_disarmed()
        log.info("restart requested from the web page%s", _by(client))
        self._request_restart()

    # -- internals -------------------------------------------------------------------------

    def _check_disarmed(self) -> None:
        if self._armed():
            raise SettingsLockedError(ARMED)

    def _editable(self) -> tuple[bool, str]:
        if self.path is None:
            return False, "no configuration file: start with --config FILE to change settings"
        if not os.access(self.path, os.W_OK) or not os.access(self.path.parent, os.W_OK):
            return False, f"{self.path} (or its folder) is not writable by the service"
        return True, ""

    def _set_up_loader(self) -> Loader | None:
        return self._load_incomplete if self.setting_up.is_set() else None

    def _validate(self, candidate: Path) -> Config:
        # The loader checks as `netpose run` does, the calibration file loaded too; in set-up
        # mode, as set-up may save a file piece by piece.
        load = self._set_up_loader() or self._load
        try:
            return load(candidate)
        except CalibrationError as exc:
            raise ConfigError("camera.calibration", str(exc)) from None

    def _reload(self) -> ReloadOutcome | None:
        """The daemon's reload of the saved file; None when it is stopping (or restarting)
        instead, which it may start doing while this waits."""
        deadline = time.monotonic() + RELOAD_TIMEOUT_S
        with self._outcomes:
            seen = self._reloads
            self._request_reload()
            while self._reloads <= seen:
                if self._stopping():
                    return None
                left = deadline - time.monotonic()
                if left <= 0.0:
                    raise ConfigError("configuration", "saved, but the daemon did not reload "
                                      f"within {RELOAD_TIMEOUT_S:.0f} s")
                self._outcomes.wait(min(left, _STOP_POLL_S))
            assert self._last_outcome is not None
            return self._last_outcome

    @staticmethod
    def _groups(config: Config | None) -> list[tuple[str, tuple[str, ...]]]:
        groups = list(GROUPS)
        if config is not None:
            for section, values in config.effective.items():
                if "hold" in section:
                    groups.append((f"Net hold ([{section}])",
                                   tuple(f"{section}.{k}" for k in values)))
        return groups

    @staticmethod
    def _describe(config: Config | None, section: str, name: str) -> dict[str, Any]:
        settings = config.sections.get(section) if config is not None else None
        if settings is None or not dataclasses.is_dataclass(settings):
            return {"type": "text"}
        hints = typing.get_type_hints(type(settings))
        return _field_kind(hints.get(name, str))
