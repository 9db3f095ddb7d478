"""The one module that constructs drivers and wires them to the daemon's loop.

Everything is built, and every setting checked, before anything is opened: a configuration
error stops the service before a single message leaves it.
"""

from __future__ import annotations

import ctypes
import dataclasses
import logging
import os
import re
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.mavlink_link import MavlinkLink
from drivers.mavlink_settings import MavlinkSettings
from drivers.recorder import Recorder, RecordingSetup
from drivers.sdnotify import NullNotifier, notifier_from_environment
from drivers.sources import FrameSource as DriverFrameSource
from drivers.sources import SourceOptions, SourceState, SourceStats, create_source
from drivers.sources.url import OWN_SCHEMES, is_network_url, parse_source_url
from drivers.telemetry import TelemetrySettings, make_publisher
from drivers.web import WebSettings
from service.config import Config, load_config
from service.core.camera import CameraModel, load_camera
from service.core.errors import CalibrationError, ConfigError
from service.daemon.loop import Daemon, DaemonParts
from service.daemon.outputs import PreviewSettings
from service.daemon.ports import AutopilotLink, FrameObserver, FrameSource, Notifier
from service.daemon.settings_editor import (
    RECORDED_SECTIONS,
    SET_UP_MESH_KEY,
    SET_UP_MESH_OVERRIDE,
    SettingsEditor,
    tuning_toml,
)
from service.daemon.setup_mode import run_setup, setup_renderer
from service.pipeline import PipelineResult
from service.signals import RESTART, EarlySignals, SignalFlags, handle_signals
from service.tools.live_view import LiveView

log = logging.getLogger("netpose.daemon")


def driver_sections() -> dict[str, type]:
    """Configuration sections of the drivers this daemon wires (added to the core ones)."""
    return {"mavlink": MavlinkSettings, "telemetry": TelemetrySettings, "web": WebSettings}


# Files the drivers' sections name, by section and key: found beside the configuration file.
_FILE_KEYS = (("mavlink", "signing_key_file"), ("telemetry", "config_file"))


def load_daemon_config(
    path: str | None, overrides: Iterable[str] = (), *, check_files: bool = True,
    drop: Iterable[str] = (),
) -> Config:
    config = load_config(path, overrides, extra_sections=driver_sections(),
                         check_files=check_files, drop=drop)
    sections = dict(config.sections)
    for name, key in _FILE_KEYS:
        value = getattr(sections[name], key)
        if value is None:
            continue
        if not str(value).strip():
            raise ConfigError(f"{name}.{key}", "is empty: name a file, or leave the key out")
        sections[name] = dataclasses.replace(sections[name],
                                             **{key: str(config.file_path(value))})
    return dataclasses.replace(config, sections=sections)


def build_source(config: Config) -> DriverFrameSource:
    """The frame source for `camera.url`, built but not yet opened. A source that is not there
    at start (the camera manager starts after us) is waited for, like one lost later."""
    # A live source that delivers nothing for stale_after_s is re-opened by the source itself.
    options = SourceOptions(stall_timeout_s=config.camera.stale_after_s, wait_at_start=True,
                            realtime_default=True)
    return create_source(_source_url(config), options)


def _source_url(config: Config) -> str:
    """camera.url, with a recorded source (a video file, a folder of stills, a recording)
    found beside the configuration like every file it names, and refused when it is not there:
    a mistyped path was otherwise refused for the wrong key (mavlink.allow_simulated) or, where
    recorded frames are allowed, retried as "no such file" for ever. A camera or a stream may
    appear after the service starts; a file does not."""
    text = config.camera.url.strip()
    if text.startswith("sdp:") or is_network_url(text):
        return text
    scheme, colon, _ = text.partition(":")
    if not (colon and scheme in OWN_SCHEMES):
        # A bare path: what it is (a file, a folder of stills, a recording) is looked up where
        # it is, beside the configuration, not in the service's working directory.
        bare, question, query = text.partition("?")
        if not (bare.isdigit() or bare.startswith("/dev/")):
            text = f"{config.file_path(bare)}{question}{query}"
    parsed = parse_source_url(text)
    if parsed.scheme not in ("file", "images", "recording"):
        return text
    path = config.file_path(parsed.path)
    # images: takes a glob too (frames/*.png, dives/*/frames/*.png): the folder before the
    # first wildcard must be there.
    parts = path.parts
    wild = next((i for i, part in enumerate(parts) if any(c in part for c in "*?[")), None)
    there = path if wild is None else Path(*parts[:wild])
    if not there.exists():
        hint = ""
        if parsed.path.startswith("/dev/"):
            hint = " (a camera is /dev/videoN, or /dev/v4l/by-id/... which keeps its name)"
        elif re.match(r"^[A-Za-z][A-Za-z0-9+.-]*//", config.camera.url.strip()):
            hint = " (a network stream is scheme://host..., with the colon)"
        raise ConfigError("camera.url", f"no such file or folder: {path}{hint}")
    query = text.partition("?")[2]
    return f"{parsed.scheme}:{path}" + (f"?{query}" if query else "")


def check_simulated(config: Config, source: DriverFrameSource) -> None:
    """A distance that is not the water in front of the vehicle now (a rendered source:
    synthetic:, sim:; a recorded one: a video file, an image folder, a recording) reaches an
    autopilot only when the configuration says so explicitly: otherwise the service does not
    start (an installed configuration left on the demo source, or on a dive video, must not
    steer a real vehicle)."""
    if config.section("mavlink", MavlinkSettings).allow_simulated:
        return
    if source.rendered:
        raise ConfigError(
            "mavlink.allow_simulated",
            "camera.url renders its frames: set it to true to send their distance to an "
            "autopilot (a simulator or a demo), or use a real camera",
        )
    if source.recorded:
        raise ConfigError(
            "mavlink.allow_simulated",
            "camera.url plays recorded frames, not what the camera sees now: set it to true "
            "to send their distance to an autopilot (a bench test or a simulator), or use the "
            "vehicle's camera",
        )


def resolve_camera(config: Config, source: DriverFrameSource) -> CameraModel:
    """The calibration file's camera, or the one a rendered source describes."""
    path = config.calibration_path()
    if path is not None:
        try:
            camera = load_camera(path)
        except CalibrationError as exc:  # the service's errors name the key to fix
            raise ConfigError("camera.calibration", str(exc)) from None
        size = source.stated_size
        if size is not None:
            # A calibration for another frame shape is known wrong before the camera opens:
            # `run --check` passed and the unit ran, refusing every frame, no distance.
            try:
                camera.scaled_to(*size)
            except CalibrationError as exc:
                raise ConfigError("camera.calibration",
                                  f"{exc} (camera.url asks for {size[0]}x{size[1]})") from None
        return camera
    try:
        described = source.camera
    except CalibrationError as exc:  # a recording's own camera.yaml, damaged
        raise ConfigError("camera.calibration", f"the source's own camera: {exc}") from None
    if described is None:
        raise ConfigError(
            "camera.calibration",
            f"required for {source.url.split(':', 1)[0]}: sources (only rendered sources "
            "and recordings with their camera.yaml describe their own camera): give the "
            "camera's calibration file",
        )
    return described


@dataclass(frozen=True)
class WebControls:
    """What the web page needs of `netpose run` besides the configuration."""

    editor: SettingsEditor
    current_config: Callable[[], Config]  # the configuration in force (after reloads)
    pipeline_state: Callable[[], dict[str, Any]]  # the running pipeline's (loop thread only)


def recordings_root(config: Config, web: WebSettings) -> Path:
    return config.file_path(web.recordings_dir)


def build_observers(config: Config, camera: CameraModel, controls: WebControls | None,
                    tell_pilot: Callable[[str], None] | None = None,
                    ) -> tuple[FrameObserver, ...]:
    """The web page and its recorder, when `web.enabled`; `tell_pilot`: where the recorder
    says a recording stopped by itself (the link's STATUSTEXT)."""
    web = config.section("web", WebSettings)
    if not web.enabled or controls is None:
        return ()
    vehicle = config.section("telemetry", TelemetrySettings).vehicle

    def setup() -> RecordingSetup:
        now = controls.current_config()
        return RecordingSetup(camera, tuning_toml(now), now.mesh.bar_length_m,
                              now.mesh.opening_angle_deg, now.digest, now.camera.url)

    from drivers.web.page import WebPage  # aiohttp's weight only when the page is on

    recorder = Recorder(recordings_root(config, web), vehicle, setup,
                        web.max_recording_mb * 1024 * 1024, controls.pipeline_state,
                        frozenset(RECORDED_SECTIONS), tell_pilot)
    page = WebPage[PipelineResult](web, LiveView(camera, web.live_width), controls.editor,
                                   recorder, vehicle)
    return (recorder, page)


def build_parts(config: Config, notifier: Notifier,
                controls: WebControls | None = None) -> DaemonParts:
    """Every part of the daemon, built and checked, nothing opened: what `run` starts and what
    `run --check` validates are the same objects."""
    source = build_source(config)
    check_simulated(config, source)
    camera = resolve_camera(config, source)
    mavlink = config.section("mavlink", MavlinkSettings)
    telemetry = config.section("telemetry", TelemetrySettings)
    link = MavlinkLink(mavlink)  # reads and checks the signing key
    return DaemonParts(
        source=source,
        link=link,
        telemetry=make_publisher(telemetry),  # builds the Zenoh configuration
        notifier=notifier,
        camera=camera,
        vehicle=telemetry.vehicle,
        preview=PreviewSettings(width=telemetry.preview_width,
                                quality=telemetry.preview_quality),
        telemetry_enabled=telemetry.enabled,
        observers=build_observers(config, camera, controls, link.notify_pilot),
    )


def check_config(config_path: str | None, overrides: Iterable[str] = ()) -> str:
    """`netpose run --check`: the same loading and building as `run`, stopping before anything
    is opened; raises ConfigError/CalibrationError where `run` would exit. A configuration
    that only lacks what set-up mode asks for on the page (the mesh size, the calibration),
    with the page on, is what `run` starts in set-up mode: said so, not an error."""
    overrides = tuple(overrides)
    try:
        config = checked_config(config_path, overrides)
    except (ConfigError, CalibrationError) as exc:
        problem = _setup_problem(_setup_config(config_path, overrides), exc)
        config = checked_config(config_path, overrides, incomplete_ok=True)
        return (f"configuration incomplete, the service starts in set-up mode (the web page "
                f"asks for it): {config.path or 'defaults'}: {problem}")
    for key, path in _named_files(config):
        hidden = next((h for h in _HIDDEN_BY_THE_UNIT if path.is_relative_to(h[0])), None)
        if hidden is not None:
            log.warning("%s: %s is under %s, which the systemd unit hides from the service "
                        "(%s): it will not find it there; keep it beside the configuration",
                        key, path, hidden[0], hidden[1])
    return f"configuration OK: {config.path or 'defaults'} ({config.digest})"


# What systemd/netpose.service's sandbox gives the service instead of the host's folders.
_HIDDEN_BY_THE_UNIT = ((Path("/tmp"), "PrivateTmp=yes"), (Path("/var/tmp"), "PrivateTmp=yes"),
                       (Path("/home"), "ProtectHome=yes"), (Path("/root"), "ProtectHome=yes"),
                       (Path("/run/user"), "ProtectHome=yes"))


def _named_files(config: Config) -> list[tuple[str, Path]]:
    """The files and folders a configuration names, by key, as the service would look."""
    named: list[tuple[str, Path]] = []
    calibration = config.calibration_path()
    if calibration is not None:
        named.append(("camera.calibration", calibration))
    for section_name, key in _FILE_KEYS:
        value = getattr(dict(config.sections)[section_name], key)
        if value:
            named.append((f"{section_name}.{key}", Path(value)))
    return named


def checked_config(config_path: str | None, overrides: Iterable[str] = (), *,
                   incomplete_ok: bool = False) -> Config:
    """The configuration, and every part `run` builds from it (source, camera, MAVLink link,
    telemetry) built once as a check, nothing opened or kept: a file saved from the web page
    must start the daemon it restarts, or the service would exit on an error only the page
    could have fixed.

    With `incomplete_ok` (set-up mode: the page saves one setting at a time), what set-up mode
    is there to finish (the mesh size, the calibration) may still be missing; everything else
    is checked as ever."""
    overrides = tuple(overrides)
    try:
        config = load_daemon_config(config_path, overrides)
        parts = build_parts(config, NullNotifier())
        parts.source.close()
        return config
    except (ConfigError, CalibrationError) as exc:
        if not (incomplete_ok and _set_up_can_fix(exc)):
            raise
    config = _setup_config(config_path, overrides)
    source = build_source(config)
    try:
        check_simulated(config, source)
    finally:
        source.close()
    MavlinkLink(config.section("mavlink", MavlinkSettings))
    make_publisher(config.section("telemetry", TelemetrySettings))
    return config


def main(
    config_path: str | None,
    overrides: Iterable[str] = (),
    duration_s: float | None = None,
    notifier: Notifier | None = None,
    early: EarlySignals | None = None,
) -> int:
    """`netpose run`: load and validate the configuration, run until stopped. `early`: the
    signals that came while the process started (acted on once the daemon's handlers are in)."""
    overrides = tuple(overrides)
    config, problem = _load_or_setup(config_path, overrides)
    logging.getLogger().setLevel(config.service.log_level)
    single_threaded_opencv()
    fewer_malloc_arenas()
    notify = notifier or notifier_from_environment(console=sys.stdout)
    try:
        with handle_signals(SignalFlags(), reload=True, early=early) as flags:
            restart = threading.Event()

            def request_restart() -> None:
                restart.set()
                flags.request_stop(RESTART)

            # The link of the daemon running now (none in set-up mode, between restarts).
            linked: list[AutopilotLink] = []
            editor = SettingsEditor(
                config.path, overrides, lambda path: checked_config(str(path), overrides),
                flags.reload.set, request_restart,
                load_incomplete=lambda path: checked_config(str(path), overrides,
                                                            incomplete_ok=True),
                stopping=flags.stop.is_set,
                load_shown=lambda path: _load_or_setup(str(path), overrides)[0],
                armed=lambda: linked[-1].status().armed if linked else None)
            running: list[Daemon] = []
            started = time.monotonic()
            controls = WebControls(editor, lambda: running[-1].config if running else config,
                                   lambda: running[-1].pipeline.snapshot())
            while True:
                parts = None
                if problem is None:
                    try:
                        parts = build_parts(config, _RestartAware(notify, restart), controls)
                    except (ConfigError, CalibrationError) as exc:
                        problem = _setup_problem(config, exc,
                                                 rescue=not _overridden(exc, overrides))
                if parts is None:
                    assert problem is not None
                    deadline = None if duration_s is None else started + duration_s
                    editor.setting_up.set()  # the page may save the file piece by piece
                    try:
                        ready = _set_up(config, problem, notify, flags, editor, config_path,
                                        overrides, deadline)
                    finally:
                        editor.setting_up.clear()
                    if ready is None and restart.is_set() and not flags.signalled.is_set():
                        # The page's Restart in set-up mode: set-up again from the saved file
                        # (an exit, status 0, left the service down under systemd's
                        # Restart=on-failure, with no page to finish the set-up on).
                        restart.clear()
                        flags.stop.clear()
                        flags.stop_signal = None
                        if not flags.signalled.is_set():
                            editor.restarted()
                            config, problem = _load_or_setup(config_path, overrides)
                            log.info("restarting with the saved configuration (%s)",
                                     config.digest)
                            continue
                    if ready is None:
                        return 0
                    config, problem = ready, None
                    continue
                daemon = Daemon(config, parts, flags=flags,
                                load_config=lambda: checked_config(config_path, overrides),
                                on_reload=editor.reloaded)
                running[:] = [daemon]
                linked[:] = [parts.link]
                try:
                    status = daemon.run(duration_s)
                finally:
                    linked.clear()
                if not restart.is_set() or flags.signalled.is_set():
                    _say_late_signal(flags, daemon.stopped_for)
                    return status
                # A restart asked for by the web page: the same process, every part rebuilt
                # from the saved configuration (what a reload cannot change live).
                restart.clear()
                flags.stop.clear()
                flags.stop_signal = None
                if flags.signalled.is_set():  # SIGTERM between the check and the clear
                    _say_late_signal(flags, daemon.stopped_for)
                    return status
                editor.restarted()
                config, problem = _load_or_setup(config_path, overrides)
                log.info("restarting with the saved configuration (%s)", config.digest)
    finally:
        notify.close()


def _say_late_signal(flags: SignalFlags, said: str | None) -> None:
    """A signal that came after the daemon had stopped for the page's restart ends the process
    instead: said, as the daemon says a signal it stopped for (it said "restart")."""
    if flags.stop_signal not in (None, RESTART, said):
        log.info("%s received: stopping", flags.stop_signal)


def single_threaded_opencv() -> None:
    """OpenCV without its worker threads, as every benchmark runs it.

    The frame loop's OpenCV calls are small (ROIs of 64-256 px, one frame's pyramid): a thread
    pool gains little there and its workers spin while they wait, on a Pi whose four cores the
    camera manager, the video stream and BlueOS share. Measured with `netpose bench soak
    --duration 30` (1280x720, 30 frames/s, a second job on the other core): 62 % of a core
    instead of 69 %, the same 30 frames/s and the same latency (median 44 ms, p99 77-79 ms).
    """
    import cv2

    cv2.setNumThreads(1)


# glibc's mallopt parameter for the most malloc arenas (malloc.h).
_M_ARENA_MAX = -8
_MALLOC_ARENAS = 2


def fewer_malloc_arenas() -> None:
    """Two malloc arenas for the whole process instead of glibc's eight per core.

    glibc gives each thread that allocates an arena of its own while there are fewer than its
    limit, and each arena keeps its freed memory. The capture thread, the link threads and
    Zenoh's runtime each ended up with one: about 2.4 MB of RSS in all (`netpose bench soak`,
    720p: 123 -> 121 MB unconstrained, 121 -> 118 MB under a quarter of a core), for nothing:
    the threads that allocate much (the capture thread's frames, the loop's numpy buffers)
    seldom do so at the same moment (the soak's CPU and latency did not change). The same as
    MALLOC_ARENA_MAX=2, but it holds however the daemon is started (systemd, the BlueOS
    container, a shell); an operator's MALLOC_ARENA_MAX or glibc tunable is left alone. Must run
    before those threads start.
    """
    if not sys.platform.startswith("linux"):
        return
    if "MALLOC_ARENA_MAX" in os.environ or "arena_max" in os.environ.get("GLIBC_TUNABLES", ""):
        return  # the operator's own choice
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return  # a C library without mallopt: its own allocator, nothing to tune
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    if mallopt(_M_ARENA_MAX, _MALLOC_ARENAS) != 1:
        log.debug("mallopt(M_ARENA_MAX) refused; the C library keeps its arenas")


# What a new vehicle's configuration lacks until its owner has set it up, and the page can set:
# the net's mesh size (no default: every distance scales with it) and the camera calibration.
SET_UP_KEYS = frozenset({SET_UP_MESH_KEY, "camera.calibration"})


def _set_up_can_fix(exc: Exception) -> bool:
    return isinstance(exc, CalibrationError) or (
        isinstance(exc, ConfigError) and exc.key in SET_UP_KEYS)


def _setup_problem(config: Config, exc: Exception, *, rescue: bool = False) -> str:
    """The problem set-up mode can fix from the page (the mesh size or the calibration
    missing or unusable, with the page enabled); with `rescue`, any configuration error but
    the page's own (see `_rescue`). Anything else is raised again (exit status 78)."""
    fixable = _set_up_can_fix(exc) or (rescue and isinstance(exc, ConfigError)
                                       and _rescuable(exc.key))
    if not fixable or not config.section("web", WebSettings).enabled:
        raise exc
    return f"configuration error: camera.calibration: {exc}" if isinstance(
        exc, CalibrationError) else f"configuration error: {exc}"


# Broken keys a rescue looks past to serve the page: a file with more needs more than a page.
_RESCUE_MAX_KEYS = 8
_KEY_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*(\.[A-Za-z_][A-Za-z0-9_-]*)?")


def _overridden(exc: Exception, overrides: tuple[str, ...]) -> bool:
    """Is what is wrong set with --set? Neither the page (it refuses overridden keys) nor the
    file (--set wins) can fix that: set-up mode would never end."""
    key = getattr(exc, "key", None)
    return key is not None and any(text.partition("=")[0].strip() == key
                                   for text in overrides)


def _rescuable(key: str) -> bool:
    """A key (or section) of the file that set-up mode can serve the page without: not the
    page's own settings, not a file's name (a file that is not TOML at all)."""
    return _KEY_NAME.fullmatch(key) is not None and key.partition(".")[0] != "web"


def _rescue(config_path: str | None, overrides: tuple[str, ...], exc: ConfigError
            ) -> tuple[Config, str]:
    """Set-up mode for a configuration error that set-up was not made for (a bad camera or
    MAVLink URL, a mistyped key, a value out of range).

    With the page on (BlueOS), `run` exited 78 on such a file and the container engine started
    it again, for ever, with no page to say why (only the extension's log did). Now the page
    comes up and says what is wrong, naming the key; its settings, or the file, fix it. The
    broken keys are left out (their defaults hold) only to serve the page: set-up mode sends
    nothing and publishes nothing, and it ends only once the file itself is valid. Raised
    again (exit 78, as ever) when the page is off, or when what is wrong is the page's own
    settings, a file that is not TOML, or a required key that has no default."""
    drop: list[str] = []
    extra: tuple[str, ...] = ()
    error: ConfigError = exc
    for _ in range(_RESCUE_MAX_KEYS):
        if error.key == SET_UP_MESH_KEY and not extra:
            extra = (SET_UP_MESH_OVERRIDE,)  # set-up's own stand-in
        elif _rescuable(error.key) and error.key not in drop:
            drop.append(error.key)
        else:
            raise exc
        try:
            config = load_daemon_config(config_path, (*overrides, *extra), check_files=False,
                                        drop=drop)
        except ConfigError as again:
            error = again
            continue
        if not config.section("web", WebSettings).enabled:
            raise exc
        return config, f"configuration error: {exc}"
    raise exc


def _setup_config(config_path: str | None, overrides: tuple[str, ...]) -> Config:
    """The configuration as far as set-up mode needs it (the page, the camera's frames): the
    calibration file not looked at, a missing or unusable mesh size stood in for (set-up mode
    estimates nothing, and it ends only once the file itself has the key)."""
    try:
        return load_daemon_config(config_path, overrides, check_files=False)
    except ConfigError as exc:
        if exc.key != SET_UP_MESH_KEY:
            raise
    return load_daemon_config(config_path, (*overrides, SET_UP_MESH_OVERRIDE), check_files=False)


def _load_or_setup(config_path: str | None, overrides: tuple[str, ...]
                   ) -> tuple[Config, str | None]:
    try:
        return load_daemon_config(config_path, overrides), None
    except ConfigError as exc:
        if not _set_up_can_fix(exc):
            return _rescue(config_path, overrides, exc)
        try:
            config = _setup_config(config_path, overrides)
        except ConfigError:  # something else is wrong besides
            return _rescue(config_path, overrides, exc)
        return config, _setup_problem(config, exc)


def _set_up(config: Config, problem: str, notify: Notifier, flags: SignalFlags,
            editor: SettingsEditor, config_path: str | None, overrides: tuple[str, ...],
            deadline: float | None) -> Config | None:
    from drivers.web.page import WebPage  # aiohttp's weight only when the page is on

    web = config.section("web", WebSettings)
    vehicle = config.section("telemetry", TelemetrySettings).vehicle
    page = WebPage[None](web, setup_renderer(problem, web.live_width), editor, None, vehicle)
    source: FrameSource
    try:
        source = build_source(config)
    except ConfigError as exc:  # camera.url is what is wrong: the page says so
        source = _NoCamera(exc)
    return run_setup(source=source, page=page, notifier=notify, flags=flags,
                     problem=problem, validate=lambda: checked_config(config_path, overrides),
                     on_reload=editor.reloaded, vehicle=vehicle, deadline=deadline,
                     note_camera=editor.note_camera)


class _NoCamera:
    """Set-up mode's camera when `camera.url` itself is what is wrong: it never opens, and
    says why (set-up mode shows it beside the problem)."""

    def __init__(self, problem: ConfigError) -> None:
        self._problem = problem

    def open(self) -> None:
        raise self._problem

    def read(self, timeout_s: float) -> None:
        return None

    def stats(self) -> SourceStats:
        return SourceStats(SourceState.DOWN, 0, 0, 0, 0, 0, 0.0, error=str(self._problem))

    def close(self) -> None:
        """Nothing was opened."""


class _RestartAware:
    """The notifier, except that a restart is a reload to systemd, not a stop."""

    def __init__(self, inner: Notifier, restart: threading.Event) -> None:
        self._inner = inner
        self._restart = restart

    @property
    def watchdog_interval_s(self) -> float | None:
        return self._inner.watchdog_interval_s

    def ready(self, status: str | None = None) -> bool:
        return self._inner.ready(status)

    def status(self, text: str) -> bool:
        return self._inner.status(text)

    def stopping(self) -> bool:
        return self._inner.reloading() if self._restart.is_set() else self._inner.stopping()

    def reloading(self) -> bool:
        return self._inner.reloading()

    def watchdog(self, now: float | None = None) -> bool:
        return self._inner.watchdog(now)

    def close(self) -> None:
        """The inner notifier is closed by main(), after the last restart."""
