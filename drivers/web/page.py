"""The web page the daemon serves: live view, plots, health, set-up and recordings.

`WebPage` is a frame observer (service.daemon.ports.FrameObserver): the loop hands it every
processed frame and status, which it only stores (drivers/web/live.py). It owns one thread
running an asyncio event loop with the aiohttp server, started by `start()` and joined by
`close()`. Work that takes time runs on two small thread pools it also owns: drawing the live
view (one worker: at most one frame is drawn at a time, at `web.live_hz` and only while a page
is open), and file work (settings, calibration, recordings).

What the page may change goes through `SettingsBackend`, which the application provides
(service/daemon/settings_editor.py): this driver never parses or validates the configuration.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import io
import ipaddress
import json
import logging
import re
import shutil
import tarfile
import tempfile
import threading
import time
import uuid
from collections.abc import Awaitable, Callable, Coroutine, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

import cv2
import numpy as np
import numpy.typing as npt
from aiohttp import BodyPartReader, WSCloseCode, WSMsgType, web

from drivers.recorder import ObservedFrame, Recorder, RecorderError
from drivers.web.live import ClientSlots, LiveFeed, PlotHistory
from drivers.web.security import (
    CHANGE_HEADER,
    TOKEN_HEADER,
    host_trusted,
    origin_allowed,
    split_host,
    token_ok,
)
from drivers.web.settings import WebSettings
from service import __version__
from service.core.camera import CameraModel, load_camera
from service.core.errors import (
    CalibrationError,
    ConfigError,
    NetposeError,
    SettingsLockedError,
)
from service.core.messages import DamageMessage, EstimateMessage, StatusMessage, to_json

log = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"
SEND_TIMEOUT_S = 10.0  # a page that takes no data for this long is disconnected
CALIBRATION_SUFFIXES = (".yaml", ".yml", ".xml")
PENDING_CALIBRATIONS = 4
MAX_HOLES = 20  # confirmed holes listed on the page (newest first)
# Live pages at once: each takes about 1.6 Mbit/s (4 frames/s of ~50 KB), so 16 take a third
# of a 80 Mbit/s tether that also carries the video and MAVLink. 200 took 789 MB in 20 s.
MAX_LIVE_CLIENTS = 16
# Connections at once (pages, their requests, downloads, live views): past it a new one is
# closed as it is accepted, so no client can take every file descriptor of the process.
MAX_CONNECTIONS = 64
# A recording download whose client takes nothing for this long is ended (its tar thread is
# one of the two that also serve settings and calibrations).
DOWNLOAD_STALL_S = 60.0
# Recording downloads at once. Each holds a thread of its own for as long as it lasts (minutes
# over a tether): in the two-thread pool for settings and recordings, two downloads kept a
# pilot's "stop recording" and every settings change waiting for 140 s.
MAX_DOWNLOADS = 3
_CANCEL_POLL_S = 0.2
# A change's body (settings, an upload) must have arrived by then: one sent a byte at a time held
# its connection for ever, and 64 of them every connection the page has. A calibration file of
# web.max_upload_kb at the default 1 MB is seconds over the slowest tether.
BODY_DEADLINE_S = 20.0
# What may go into a Content-Security-Policy source as it is: a host name or IPv4 address, an
# origin of one.
_PLAIN_NAME = re.compile(r"[a-z0-9]([a-z0-9.-]{0,252})")
_PLAIN_ORIGIN = re.compile(r"https?://[A-Za-z0-9.-]{1,253}(:[0-9]{1,5})?")

R = TypeVar("R")


class SettingsBackend(Protocol):
    """What the application lets the page do with the configuration."""

    def snapshot(self) -> dict[str, Any]:
        """JSON: the file, whether it can be changed, the editable keys and their values."""
        ...

    def apply(self, changes: Mapping[str, Any], client: str = "") -> dict[str, Any]:
        """Validate `{"section.key": value}` like the file, save, reload; ConfigError names
        the key of the first problem and nothing is changed. `client`: who asked (the log's).
        SettingsLockedError: not now (the vehicle is armed)."""
        ...

    def install_calibration(self, path: Path, client: str = "") -> dict[str, Any]:
        """Copy a validated calibration file next to the configuration and use it."""
        ...

    def restart(self, client: str = "") -> None:
        """Restart the daemon's parts with the saved configuration."""
        ...


# Draws the overlay of one frame: (frame, the pipeline's result) -> BGR image.
Renderer = Callable[[Any, Any], npt.NDArray[np.uint8]]


@dataclass
class _PendingCalibration:
    path: Path
    camera: CameraModel
    preview: bytes
    created: float
    checked: bool = True  # against a camera frame (its aspect ratio; the undistorted view)


class WebPage(Generic[R]):
    """The page's server, fed by the frame loop (`observe`, `observe_status`)."""

    def __init__(
        self,
        settings: WebSettings,
        render: Renderer,
        backend: SettingsBackend,
        recorder: Recorder | None = None,
        vehicle: str = "rov",
    ) -> None:
        self.settings = settings
        self._render = render
        self._backend = backend
        self._recorder = recorder
        self._vehicle = vehicle
        # Said in every hello: an open page tells a restarted daemon (a new instance: its
        # settings and recordings are reloaded) from a reconnect (an unsaved form is kept),
        # and a rebooted computer (another monotonic clock: its plot points are dropped) from
        # a restarted process (the same clock: they are kept).
        self._instance = uuid.uuid4().hex
        self._boot_id = _boot_id()
        self._feed = LiveFeed()
        self._history = PlotHistory(settings.history_s)
        self._clients: set[ClientSlots] = set()
        self._sockets: set[web.WebSocketResponse] = set()
        # Recording downloads under way (their cancel flag, their request): a stop ends them.
        self._downloads: dict[threading.Event, web.Request] = {}
        self._last_texts: dict[str, str] = {}
        self._holes: list[dict[str, Any]] = []
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._started = threading.Event()
        self._draw_pool = ThreadPoolExecutor(1, thread_name_prefix="web draw")
        self._file_pool = ThreadPoolExecutor(2, thread_name_prefix="web files")
        self._download_pool = ThreadPoolExecutor(MAX_DOWNLOADS,
                                                 thread_name_prefix="web downloads")
        self._tmp = Path(tempfile.mkdtemp(prefix="netpose-web-"))
        self._calibrations: dict[str, _PendingCalibration] = {}
        self._last_push = 0.0
        self._push_timer: asyncio.TimerHandle | None = None
        self._drawing = False
        self._last_draw = 0.0
        self._draw_timer: asyncio.TimerHandle | None = None
        self._frame_seq_drawn = -1
        self.port: int | None = None  # the bound port, once listening
        self.draw_ms: list[float] = []  # recent drawing times (status, benchmarks)

    # -- FrameObserver ------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="web page", daemon=True)
        self._thread.start()
        self._started.wait(5.0)

    def observe(self, frame: ObservedFrame, result: R, message: EstimateMessage) -> None:
        self._feed.put_frame(frame, result, message)

    def observe_status(self, message: StatusMessage) -> None:
        self._feed.put_status(message)

    def observe_damage(self, message: DamageMessage) -> None:
        self._feed.put_damage(message)

    def observe_reload(self, changed: frozenset[str]) -> None:
        """The page reads the settings from the editor when asked: nothing to do."""

    def close(self) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            self._thread.join(10.0)
            if self._thread.is_alive():
                log.warning("web page: server thread did not stop within 10 s")
        self._feed.attach(None)
        self._draw_pool.shutdown(wait=True, cancel_futures=True)
        self._file_pool.shutdown(wait=True, cancel_futures=True)
        self._download_pool.shutdown(wait=True, cancel_futures=True)
        shutil.rmtree(self._tmp, ignore_errors=True)

    # -- the server thread -------------------------------------------------------------------
    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._serve())
        except Exception:
            log.exception("web page: server failed")
        finally:
            self._feed.attach(None)  # the frame loop must not wake a loop that is gone
            self._started.set()
            with contextlib.suppress(Exception):
                loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _serve(self) -> None:
        loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()

        def wake() -> None:
            with contextlib.suppress(RuntimeError):  # closed meanwhile: the page is stopping
                loop.call_soon_threadsafe(self._drain)

        self._feed.attach(wake)
        listening = await self._listen()
        if listening is None:
            return  # stopped before the port was ever free
        runner, site = listening
        if not self._stop.is_set():
            server = getattr(site, "_server", None)
            sockets = getattr(server, "sockets", None) or []
            self.port = sockets[0].getsockname()[1] if sockets else self.settings.port
            log.info("web page on http://%s:%d/%s", self.settings.host, self.port,
                     " (changes need web.token)" if self.settings.token else "")
            if not self.settings.token and not _loopback(self.settings.host):
                log.warning("web page open to the network without web.token: anyone who "
                            "reaches port %d can change settings (the mesh size scales every "
                            "distance sent to the autopilot) and delete recordings; set "
                            "web.token", self.port)
            self._started.set()
            await self._stop.wait()
        for timer in (self._push_timer, self._draw_timer):
            if timer is not None:
                timer.cancel()
        await runner.cleanup()

    async def _listen(self) -> tuple[web.AppRunner, web.TCPSite] | None:
        """The page's server, listening; while the port is taken, a new try every 5 s (a site
        that failed to start stays registered with its runner, so each try has its own)."""
        assert self._stop is not None
        failed_logged = False
        while not self._stop.is_set():
            # (No shutdown_timeout: AppRunner takes it only since aiohttp 3.9, and Debian
            # bookworm's 3.8 would hand it to every connection. Open pages are closed on
            # shutdown.)
            runner = web.AppRunner(self._app(), access_log=None, handle_signals=False)
            await runner.setup()
            site = _CappedSite(runner, self.settings.host, self.settings.port,
                               reuse_address=True)
            try:
                await site.start()
                return runner, site
            except OSError as exc:
                await runner.cleanup()
                if not failed_logged:
                    log.error("web page: cannot listen on %s:%d (%s); retrying every 5 s",
                              self.settings.host, self.settings.port, exc.strerror or exc)
                    failed_logged = True
                self._started.set()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._stop.wait(), 5.0)
        return None

    def _app(self) -> web.Application:
        app = web.Application(client_max_size=self.settings.max_upload_kb * 1024,
                              middlewares=[self._guard])
        app.router.add_get("/", self._static_page("index.html"))
        app.router.add_get("/widget", self._static_page("widget.html"))
        app.router.add_get("/register_service", self._register_service)
        app.router.add_get("/cockpit_extras.json", self._cockpit_extras)
        app.router.add_get("/icon.svg", self._static_page("icon.svg"))
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/api/settings", self._get_settings)
        app.router.add_post("/api/settings", self._post_settings)
        app.router.add_post("/api/restart", self._post_restart)
        app.router.add_post("/api/calibration", self._post_calibration)
        app.router.add_get("/api/calibration/{id}/preview.jpg", self._get_calibration_preview)
        app.router.add_post("/api/calibration/{id}/apply", self._post_calibration_apply)
        app.router.add_get("/api/recordings", self._get_recordings)
        app.router.add_post("/api/recordings/start", self._post_recording_start)
        app.router.add_post("/api/recordings/stop", self._post_recording_stop)
        app.router.add_get("/api/recordings/{name}.tar", self._get_recording_tar)
        app.router.add_post("/api/recordings/{name}/delete", self._post_recording_delete)
        app.router.add_static("/static", STATIC, show_index=False)
        app.on_shutdown.append(self._close_clients)
        app.on_response_prepare.append(self._policy_headers)
        return app

    async def _policy_headers(self, request: web.Request, response: web.StreamResponse) -> None:
        """Which pages may frame this one: the full page (its Restart, its recording buttons)
        only the vehicle's own pages (BlueOS's sidebar, Cockpit served by BlueOS: the same host,
        any port) and web.allowed_origins, so a website cannot lay it under its own and have
        the pilot click it; the Cockpit widget (no controls) anywhere."""
        response.headers["X-Content-Type-Options"] = "nosniff"
        if request.path != "/widget":
            response.headers["Content-Security-Policy"] = self._frame_ancestors(request.host)

    # -- safety --------------------------------------------------------------------------------
    @web.middleware
    async def _guard(self, request: web.Request,
                     handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
                     ) -> web.StreamResponse:
        changes = request.method not in ("GET", "HEAD", "OPTIONS")
        upgrade = request.headers.get("Upgrade", "").lower() == "websocket"
        origin = request.headers.get("Origin")
        if (changes or upgrade) and not origin_allowed(
                origin, request.host, self.settings.allowed_origins):
            return _error(403, f"request from another origin ({origin}) refused")
        if changes and origin is not None and CHANGE_HEADER not in request.headers:
            return _error(403, f"a change from a browser needs the {CHANGE_HEADER} header, as "
                          "the page's own requests have (security.py)")
        # The page's data (the live view, settings, recordings) and every change from a
        # browser: only by a name no website can point at the vehicle. A site the topside
        # browser visits, rebound to the vehicle, would otherwise read the cage's video and the
        # dive's recordings (the pages themselves answer any name: they hold no data).
        data = request.path == "/ws" or request.path.startswith("/api/")
        if ((data or (changes and origin is not None))
                and not host_trusted(request.host, self.settings.allowed_origins)):
            return _error(403, f"the page was reached as {request.host}, a name any website "
                          "could point at this vehicle: to use it by that name, list "
                          f"{origin or 'its origin'} in web.allowed_origins (or use the "
                          "vehicle's address)")
        if changes:
            if not token_ok(self.settings.token, request.headers.get(TOKEN_HEADER)):
                return _error(401, "this change needs the token (web.token); enter it on the "
                              "page")
            limit = self.settings.max_upload_kb * 1024
            if request.content_length is not None and request.content_length > limit:
                return _error(413, f"request of {request.content_length} bytes refused: at "
                              f"most {self.settings.max_upload_kb} KB (web.max_upload_kb)")
        try:
            if changes and request.path != "/api/calibration":
                # Read whole before the handler, in time (the upload's handler bounds its own).
                try:
                    await asyncio.wait_for(request.read(), BODY_DEADLINE_S)
                except TimeoutError:
                    return _slow_body()
            return await handler(request)
        except web.HTTPRequestEntityTooLarge:
            return _error(413, f"request refused: at most {self.settings.max_upload_kb} KB "
                          "(web.max_upload_kb)")

    def _frame_ancestors(self, host: str) -> str:
        sources = ["'self'"]
        name, _ = split_host(host)
        if _PLAIN_NAME.fullmatch(name):  # not an IPv6 literal, nor anything odd
            sources += [f"http://{name}:*", f"https://{name}:*"]
        sources += [o for o in self.settings.allowed_origins if _PLAIN_ORIGIN.fullmatch(o)]
        return "frame-ancestors " + " ".join(sources)

    # -- pages and BlueOS ------------------------------------------------------------------------
    def _static_page(self, name: str) -> Callable[[web.Request], Awaitable[web.StreamResponse]]:
        async def handler(request: web.Request) -> web.StreamResponse:
            return web.FileResponse(STATIC / name, headers={"Cache-Control": "no-cache"})
        return handler

    async def _register_service(self, request: web.Request) -> web.Response:
        # BlueOS's helper validates these into its ServiceMetadata: the first seven keys are
        # required. works_in_relative_paths: the page is served under /extensionv2/netpose/
        # (also through BlueOS Cloud), so every URL in it is relative.
        return web.json_response({
            "name": "netpose",
            "description": "Distance and orientation to the net, from the camera",
            "icon": "mdi-fishbowl-outline",
            "company": "netpose",
            "version": __version__,
            "webpage": "",
            "api": "",
            "new_page": False,
            "works_in_relative_paths": True,
            "extras": {"cockpit": "/cockpit_extras.json"},
        })

    async def _cockpit_extras(self, request: web.Request) -> web.Response:
        # Cockpit's ExtrasJsonSchema: offered as a widget in its edit mode. Both icon keys:
        # Cockpit before 1.18 requires `iframeIcon` (and rejects the file without it), later
        # ones read `iconUrl`.
        return web.json_response({
            "targetSystem": "Cockpit",
            "targetCockpitApiVersion": "1.0.0",
            "widgets": [{
                "name": "netpose", "iframeUrl": "/widget", "iconUrl": "/icon.svg",
                "iframeIcon": "/icon.svg",
                "useExtensionPathAsBaseUrl": True, "collapsibleContainerName": "netpose",
                "startCollapsed": False, "version": __version__, "contentZoom": 1,
                "scaleContentWithWidget": True,
            }],
            "actions": [],
        })

    # -- live data -----------------------------------------------------------------------------
    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        if len(self._sockets) >= MAX_LIVE_CLIENTS:
            return _error(503, f"{MAX_LIVE_CLIENTS} pages are already open on this vehicle: "
                          "close one (the live view's bandwidth is shared with the video)")
        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=4096)
        await ws.prepare(request)
        client = ClientSlots()
        client.add_event(json.dumps({"kind": "hello", "version": __version__,
                                     "vehicle": self._vehicle,
                                     "token_required": bool(self.settings.token),
                                     "live_hz": self.settings.live_hz,
                                     "push_hz": self.settings.push_hz,
                                     "history_s": self.settings.history_s,
                                     "instance": self._instance, "boot_id": self._boot_id}))
        client.add_event(json.dumps({"kind": "history", "points": self._history.points()}))
        for text in self._last_texts.values():
            client.set_text(json.loads(text)["kind"], text)
        self._clients.add(client)
        self._sockets.add(ws)
        self._schedule_draw()
        sender = asyncio.create_task(self._send_to(ws, client))
        try:
            async for msg in ws:  # the page sends nothing; this notices it going away
                if msg.type in (WSMsgType.ERROR, WSMsgType.CLOSE):
                    break
        finally:
            self._clients.discard(client)
            self._sockets.discard(ws)
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender
        return ws

    async def _send_to(self, ws: web.WebSocketResponse, client: ClientSlots) -> None:
        try:
            while not ws.closed:
                await client.wake.wait()
                texts, jpeg = client.take()
                for text in texts:
                    await asyncio.wait_for(ws.send_str(text), SEND_TIMEOUT_S)
                if jpeg is not None:
                    await asyncio.wait_for(ws.send_bytes(jpeg), SEND_TIMEOUT_S)
                    client.frames_sent += 1
        except (TimeoutError, ConnectionError, RuntimeError):
            await ws.close()

    async def _close_clients(self, app: web.Application) -> None:
        self._clients.clear()
        # A download to a client that reads slowly (or not at all) would hold the server's
        # shutdown, and the tar thread the file pool's, for a minute: cut it off instead.
        for cancelled, request in list(self._downloads.items()):
            cancelled.set()
            if request.transport is not None:
                request.transport.abort()
        for ws in list(self._sockets):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(code=WSCloseCode.GOING_AWAY,
                                                message=b"netpose is stopping"), 2.0)

    def _drain(self) -> None:
        """On the event loop: take what the frame loop handed over and pass it on."""
        estimates, status, _frame = self._feed.take()
        holes = self._feed.take_damage()
        if holes:
            # The page lists the holes confirmed in this run, newest first (a bounded list).
            self._holes = ([to_json(h) for h in reversed(holes)] + self._holes)[:MAX_HOLES]
            self._publish("damage", json.dumps({"kind": "damage", "holes": self._holes},
                                               allow_nan=False))
        for message in estimates:
            self._history.add(message)
        if status is not None:
            self._publish("status", json.dumps(to_json(status), allow_nan=False))
            if self._recorder is not None:
                self._publish("recording", json.dumps(self._recorder.status().to_json()))
        if estimates:
            self._schedule_push()
            self._schedule_draw()

    def _publish(self, kind: str, text: str) -> None:
        self._last_texts[kind] = text
        for client in self._clients:
            client.set_text(kind, text)

    def _schedule_push(self) -> None:
        if self._push_timer is not None:
            return
        assert self._loop is not None
        wait = self._last_push + 1.0 / self.settings.push_hz - time.monotonic()
        self._push_timer = self._loop.call_later(max(0.0, wait), self._push_estimate)

    def _push_estimate(self) -> None:
        self._push_timer = None
        newest = self._feed.newest_frame()
        if newest is None:
            return
        self._last_push = time.monotonic()
        self._publish("estimate", json.dumps(to_json(newest[2]), allow_nan=False))

    def _schedule_draw(self) -> None:
        if not self._clients or self._drawing or self._draw_timer is not None:
            return
        assert self._loop is not None
        wait = self._last_draw + 1.0 / self.settings.live_hz - time.monotonic()
        self._draw_timer = self._loop.call_later(max(0.0, wait), self._start_draw)

    def _start_draw(self) -> None:
        self._draw_timer = None
        newest = self._feed.newest_frame()
        if newest is None or not self._clients or newest[2].seq == self._frame_seq_drawn:
            return
        self._drawing = True
        self._last_draw = time.monotonic()
        self._frame_seq_drawn = newest[2].seq
        assert self._loop is not None
        future = self._loop.run_in_executor(self._draw_pool, self._draw, newest[0], newest[1])
        future.add_done_callback(self._drawn)

    def _draw(self, frame: Any, result: Any) -> bytes:
        t0 = time.perf_counter()
        image = self._render(frame, result)
        ok, data = cv2.imencode(".jpg", image, [int(cv2.IMWRITE_JPEG_QUALITY),
                                                self.settings.live_quality])
        if not ok:
            raise NetposeError("OpenCV cannot encode the live view as JPEG")
        self.draw_ms = [*self.draw_ms[-99:], (time.perf_counter() - t0) * 1e3]
        return bytes(data.tobytes())

    def _drawn(self, future: asyncio.Future[bytes]) -> None:
        self._drawing = False
        if future.cancelled():
            return
        exc = future.exception()
        if exc is not None:
            log.warning("web page: cannot draw the live view: %s", exc)
        else:
            jpeg = future.result()
            for client in self._clients:
                client.set_jpeg(jpeg)
        self._schedule_draw()

    # -- settings ------------------------------------------------------------------------------
    async def _in_files(self, fn: Callable[..., Any], *args: Any) -> Any:
        return await asyncio.get_running_loop().run_in_executor(self._file_pool, fn, *args)

    async def _get_settings(self, request: web.Request) -> web.Response:
        snapshot = await self._in_files(self._backend.snapshot)
        return web.json_response({**snapshot, "token_required": bool(self.settings.token)})

    async def _post_settings(self, request: web.Request) -> web.Response:
        body = await _json_body(request)
        changes = body.get("changes")
        if not isinstance(changes, dict) or not changes:
            return _error(400, "expected {\"changes\": {\"section.key\": value, ...}}")
        try:
            outcome = await self._in_files(self._backend.apply, changes, _client(request))
        except SettingsLockedError as exc:
            return _error(409, str(exc))
        except NetposeError as exc:
            return _error(400, _config_text(exc))
        self._broadcast_event({"kind": "settings", **outcome})
        return web.json_response(outcome)

    async def _post_restart(self, request: web.Request) -> web.Response:
        try:
            self._backend.restart(_client(request))
        except SettingsLockedError as exc:
            return _error(409, str(exc))
        return web.json_response({"restarting": True})

    def _broadcast_event(self, payload: dict[str, Any]) -> None:
        text = json.dumps(payload)
        for client in self._clients:
            client.add_event(text)

    # -- calibration ---------------------------------------------------------------------------
    async def _post_calibration(self, request: web.Request) -> web.Response:
        if not request.content_type.startswith("multipart/"):
            return _error(400, "upload the calibration file as multipart/form-data (field file)")
        try:
            upload = await asyncio.wait_for(self._read_calibration(request), BODY_DEADLINE_S)
        except TimeoutError:
            return _slow_body()
        if isinstance(upload, web.Response):
            return upload
        data, filename, suffix = upload
        ident = uuid.uuid4().hex[:12]
        path = self._tmp / f"{ident}{suffix}"
        path.write_bytes(data)
        try:
            pending = await self._in_files(self._check_calibration, path, filename)
        except NetposeError as exc:
            path.unlink(missing_ok=True)
            return _error(400, f"camera.calibration: {exc}")
        self._calibrations[ident] = pending
        while len(self._calibrations) > PENDING_CALIBRATIONS:
            oldest = min(self._calibrations, key=lambda k: self._calibrations[k].created)
            self._calibrations.pop(oldest).path.unlink(missing_ok=True)
        cam = pending.camera
        k1 = cam.distortion[0] if cam.distortion else 0.0
        unchecked = "" if pending.checked else (
            "; not checked against the camera (no frame yet): the daemon checks it when "
            "the camera runs")
        return web.json_response({
            "id": ident, "file": filename, "preview": f"api/calibration/{ident}/preview.jpg",
            "summary": f"{cam.width}x{cam.height}, fx {cam.fx:.1f} fy {cam.fy:.1f} px, "
                       f"centre ({cam.cx:.1f}, {cam.cy:.1f}), k1 {k1:+.3f}{unchecked}",
            "checked": pending.checked,
        })

    async def _read_calibration(self, request: web.Request
                                ) -> tuple[bytes, str, str] | web.Response:
        """The upload's file: (content, file name, suffix), or the answer that refuses it."""
        # Counted here: aiohttp 3.8 (Debian bookworm's, the BlueOS image's) bounds a body by
        # client_max_size only when it states its length, and a chunked upload of 1.5 GB went
        # to memory and disk (4.7 GB RSS, a daemon that no longer stopped). The parts skipped
        # count as well (a 5 MB one passed a 256 KB limit).
        limit = self.settings.max_upload_kb * 1024
        too_large = _error(413, f"upload refused: more than {self.settings.max_upload_kb} KB "
                           "(web.max_upload_kb)")
        size = 0
        reader = await request.multipart()
        part = await reader.next()
        while part is not None and getattr(part, "name", None) != "file":
            if not isinstance(part, BodyPartReader):
                # A nested multipart would be read through uncounted: no calibration has one.
                return _error(400, "a nested multipart part in the upload: send the "
                              "calibration file alone (form field 'file')")
            while chunk := await part.read_chunk(64 * 1024):
                size += len(chunk)
                if size > limit:
                    return too_large
            part = await reader.next()
        if not isinstance(part, BodyPartReader) or not part.filename:
            return _error(400, "no file in the upload (form field 'file')")
        suffix = Path(part.filename).suffix.lower()
        if suffix not in CALIBRATION_SUFFIXES:
            return _error(400, f"{part.filename}: a calibration is a ROS camera_info YAML or an "
                          "OpenCV FileStorage file (.yaml, .yml or .xml)")
        chunks: list[bytes] = []
        while chunk := await part.read_chunk(64 * 1024):
            size += len(chunk)
            if size > limit:
                return too_large
            chunks.append(bytes(chunk))
        return b"".join(chunks), part.filename, suffix

    def _check_calibration(self, path: Path, filename: str) -> _PendingCalibration:
        try:
            camera = load_camera(path)
        except CalibrationError as exc:
            # The message names our temporary file; the user knows theirs by its name.
            raise CalibrationError(str(exc).replace(str(path), filename)) from None
        newest = self._feed.newest_frame()
        setting_up = getattr(self._backend, "setting_up", None)
        if newest is None and not (setting_up is not None and setting_up.is_set()):
            raise CalibrationError("no camera frame yet to check it against; try again when "
                                   "the live view shows the camera")
        if newest is None:
            # Set-up mode with the camera not working yet (a stream still to be made): the
            # file is taken unchecked, or set-up could not be finished from the page. The
            # daemon checks it against every frame when it runs (frames of another aspect
            # ratio give no distance, and the log and status name camera.calibration).
            return _PendingCalibration(path, camera, _unchecked_preview(
                camera, self.settings.live_width), time.monotonic(), checked=False)
        image = np.asarray(newest[0].image)
        h, w = image.shape[:2]
        scaled = camera.scaled_to(w, h)  # CalibrationError for another aspect ratio
        return _PendingCalibration(path, camera, undistorted_preview(image, scaled,
                                                                     self.settings.live_width),
                                   time.monotonic())

    async def _get_calibration_preview(self, request: web.Request) -> web.Response:
        pending = self._calibrations.get(request.match_info["id"])
        if pending is None:
            return _error(404, "no such calibration upload (uploads are kept until 4 newer)")
        return web.Response(body=pending.preview, content_type="image/jpeg")

    async def _post_calibration_apply(self, request: web.Request) -> web.Response:
        pending = self._calibrations.get(request.match_info["id"])
        if pending is None:
            return _error(404, "no such calibration upload: upload the file again")
        try:
            outcome = await self._in_files(self._backend.install_calibration, pending.path,
                                           _client(request))
        except SettingsLockedError as exc:
            return _error(409, str(exc))
        except NetposeError as exc:
            return _error(400, _config_text(exc))
        self._broadcast_event({"kind": "settings", **outcome})
        return web.json_response(outcome)

    # -- recordings ----------------------------------------------------------------------------
    def _need_recorder(self) -> Recorder:
        if self._recorder is None:
            raise web.HTTPNotFound(text='{"error": "recording is not available"}',
                                   content_type="application/json")
        return self._recorder

    async def _get_recordings(self, request: web.Request) -> web.Response:
        recorder = self._need_recorder()
        listing = await self._in_files(recorder.recordings)
        return web.json_response({"recordings": listing, "status": recorder.status().to_json()})

    async def _post_recording_start(self, request: web.Request) -> web.Response:
        recorder = self._need_recorder()
        try:
            status = await self._in_files(recorder.begin)
        except NetposeError as exc:
            return _error(409, str(exc))
        self._publish("recording", json.dumps(status.to_json()))
        return web.json_response(status.to_json())

    async def _post_recording_stop(self, request: web.Request) -> web.Response:
        recorder = self._need_recorder()
        status = await self._in_files(recorder.stop)
        self._publish("recording", json.dumps(status.to_json()))
        return web.json_response(status.to_json())

    async def _post_recording_delete(self, request: web.Request) -> web.Response:
        recorder = self._need_recorder()
        name = request.match_info["name"]
        if name not in {r["name"] for r in await self._in_files(recorder.recordings)}:
            return _error(404, f"no recording named {name!r}")
        if any(r.match_info.get("name") == name for r in self._downloads.values()):
            return _error(409, f"{name} is being downloaded: delete it when that has finished")
        try:
            size = await self._in_files(recorder.delete, name)
        except RecorderError as exc:  # being recorded, or the card refused
            return _error(409, str(exc))
        log.info("recording %s deleted from the web page by %s", name, _client(request))
        return web.json_response({"deleted": name, "bytes": size})

    async def _get_recording_tar(self, request: web.Request) -> web.StreamResponse:
        recorder = self._need_recorder()
        name = request.match_info["name"]
        try:
            folder = recorder.folder_of(name)
        except RecorderError as exc:
            return _error(404, str(exc))
        if len(self._downloads) >= MAX_DOWNLOADS:
            return _error(503, f"{MAX_DOWNLOADS} downloads are under way: try again when one "
                          "has finished")
        response = web.StreamResponse(headers={
            "Content-Type": "application/x-tar",
            "Content-Disposition": f'attachment; filename="{name}.tar"',
            # BlueOS's nginx would spool up to 1 GB of it to the card and stop reading us
            # while it drains that: the stall limit below then cut a download the client was
            # still reading. Unbuffered, the limit meets the real client.
            "X-Accel-Buffering": "no"})
        await response.prepare(request)
        loop = asyncio.get_running_loop()
        chunks: asyncio.Queue[bytes | None] = asyncio.Queue(maxsize=8)
        cancelled = threading.Event()
        self._downloads[cancelled] = request
        producer = loop.run_in_executor(self._download_pool, _write_tar, folder, name, loop,
                                        chunks, cancelled)
        transport = request.transport

        def cut_if_given_up(done: asyncio.Future[None]) -> None:
            # The handler may be stuck in a write to a client that reads nothing (a paused
            # download, a sleeping laptop): aiohttp's drain has no timeout, so the connection
            # is cut here, which also ends that write.
            if not done.cancelled() and done.exception() is not None and transport is not None:
                transport.abort()

        producer.add_done_callback(cut_if_given_up)
        try:
            while (chunk := await _next_chunk(chunks, producer)) is not None:
                await response.write(chunk)
            await producer
            await response.write_eof()
        except ConnectionError:
            # The client went away, or the page is stopping (`_close_clients` cut it off).
            log.info("web page: download of %s ended before it was complete", name)
        except OSError as exc:  # the tar thread gave up: a client that stopped reading
            log.warning("web page: download of %s stopped: %s", name, exc)
            # Cut the connection: returning would end the response cleanly, and the client
            # (curl's exit 0, a browser's "done") would take the cut tar for the whole one.
            if request.transport is not None:
                request.transport.abort()
        finally:
            self._downloads.pop(cancelled, None)
            cancelled.set()
            while not chunks.empty():
                chunks.get_nowait()
            # The tar thread then ends with "download cancelled": nothing to report.
            producer.add_done_callback(_exception_seen)
        return response



async def _next_chunk(chunks: asyncio.Queue[bytes | None],
                      producer: asyncio.Future[None]) -> bytes | None:
    """The tar's next chunk; None at its end, or once its thread has ended without saying so
    (it gave up while the queue was full: waiting for its end marker would wait for ever)."""
    while True:
        if not chunks.empty():
            return chunks.get_nowait()
        if producer.done():
            return None
        getter = asyncio.ensure_future(chunks.get())
        either: set[asyncio.Future[Any]] = {getter, producer}
        try:
            await asyncio.wait(either, return_when=asyncio.FIRST_COMPLETED)
            if getter.done():
                return getter.result()
        finally:
            getter.cancel()  # not left pending when the handler itself is cancelled


class _QueueWriter(io.RawIOBase):
    """A file object whose writes go to an asyncio queue (the tar is streamed, never stored)."""

    def __init__(self, loop: asyncio.AbstractEventLoop, queue: asyncio.Queue[bytes | None],
                 cancelled: threading.Event) -> None:
        self._loop = loop
        self._queue = queue
        self._cancelled = cancelled

    def writable(self) -> bool:
        return True

    def write(self, data: Any) -> int:
        chunk = bytes(data)
        _hand_over(self._queue.put(chunk), self._loop, self._cancelled)
        return len(chunk)


def _exception_seen(future: asyncio.Future[Any]) -> None:
    if not future.cancelled():
        future.exception()


def _hand_over(put: Coroutine[Any, Any, None], loop: asyncio.AbstractEventLoop,
               cancelled: threading.Event) -> None:
    """Run `put` on the page's loop and wait for it, but only while the download lasts: a
    client that stopped reading (or a page that stops) must not hold this thread."""
    if cancelled.is_set():
        put.close()
        raise OSError("download cancelled")
    done = asyncio.run_coroutine_threadsafe(put, loop)
    deadline = time.monotonic() + DOWNLOAD_STALL_S
    while True:
        try:
            done.result(_CANCEL_POLL_S)
            return
        except concurrent.futures.TimeoutError:
            stalled = time.monotonic() > deadline
            if cancelled.is_set() or stalled:
                done.cancel()
                raise OSError("download stalled" if stalled else "download cancelled") from None


def _write_tar(folder: Path, name: str, loop: asyncio.AbstractEventLoop,
               queue: asyncio.Queue[bytes | None], cancelled: threading.Event) -> None:
    writer = _QueueWriter(loop, queue, cancelled)
    try:
        with tarfile.open(fileobj=writer, mode="w|", format=tarfile.PAX_FORMAT) as tar:
            tar.add(folder, arcname=name)
    finally:
        with contextlib.suppress(OSError):
            _hand_over(queue.put(None), loop, cancelled)


def undistorted_preview(image: npt.NDArray[Any], camera: CameraModel, width: int
                        ) -> bytes:
    """The frame as it is and as the calibration undistorts it, side by side, as JPEG."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    h, w = grey.shape[:2]
    new_matrix, _ = cv2.getOptimalNewCameraMatrix(camera.matrix, camera.dist_coeffs, (w, h), 0.0)
    straight = cv2.undistort(grey, camera.matrix, camera.dist_coeffs, None, new_matrix)
    half = max(80, width // 2)
    size = (half, max(1, round(h * half / w)))
    pair = [cv2.cvtColor(cv2.resize(img, size, interpolation=cv2.INTER_AREA), cv2.COLOR_GRAY2BGR)
            for img in (grey, straight)]
    for img, label in zip(pair, ("as recorded", "undistorted"), strict=True):
        cv2.putText(img, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                    cv2.LINE_AA)
    ok, data = cv2.imencode(".jpg", np.hstack(pair), [int(cv2.IMWRITE_JPEG_QUALITY), 80])
    if not ok:
        raise CalibrationError("cannot draw the undistorted preview")
    return bytes(data.tobytes())


def _unchecked_preview(camera: CameraModel, width: int) -> bytes:
    """What the upload shows when there is no camera frame to undistort: a plain card."""
    height = max(60, round(width * camera.height / max(camera.width, 1) / 2))
    card = np.full((height, width, 3), 48, np.uint8)
    for row, text in enumerate(("no camera frame yet:", "the calibration is not checked",
                                "against the camera until it runs")):
        cv2.putText(card, text, (10, 24 + 20 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (255, 255, 255), 1, cv2.LINE_AA)
    ok, data = cv2.imencode(".jpg", card, [int(cv2.IMWRITE_JPEG_QUALITY), 80])
    if not ok:
        raise CalibrationError("cannot draw the calibration's card")
    return bytes(data.tobytes())


class _CappedSite(web.TCPSite):
    """aiohttp's TCP site (its stop closes the open connections and runs the shutdown hooks:
    on aiohttp 3.8 only the site's stop does), listening through `_CappedConnections`, so
    clients that never finish their requests cannot take every file descriptor of the process,
    which the camera and the MAVLink link need too."""

    async def start(self) -> None:
        await web.BaseSite.start(self)  # registers the site with its runner
        loop = asyncio.get_running_loop()
        server = self._runner.server
        assert server is not None
        capped = _CappedConnections(server, MAX_CONNECTIONS)
        self._server = await loop.create_server(capped, self._host, self._port,
                                                reuse_address=self._reuse_address)
        capped.listening = self._server


class _CappedConnections:
    """aiohttp's protocol factory, holding the open connections to `limit`.

    About 1,100 connections that never finished their headers once took the process's 1,024
    descriptors: the page went dark, a SIGHUP's reload failed to open the configuration, and
    asyncio logged a traceback per accept, 3.7 MB/s.

    At the limit, the connection that has waited longest without a request in progress (half
    a header, or an idle keep-alive) is closed to make room: `limit` such connections held
    every slot otherwise, and aiohttp has no header timeout, so the pilot's page was refused
    for as long as they stayed open (slowloris). A connection whose request is being answered
    (a download, a live view) is never closed for it; when every one is busy, the newest is
    refused instead (closed as it is accepted, its descriptor freed at once). So is one of a
    burst accepted in one pass of the loop, before aiohttp has registered the others.

    Open connections are counted by the listening server's transports (asyncio attaches each
    one as it is made, before its protocol is told, and detaches it when it is gone): aiohttp's
    own list learns of a connection a loop pass later, and a burst of 100 accepts all saw it
    empty. Where that count is not there, aiohttp's list is used."""

    def __init__(self, server: Any, limit: int) -> None:
        self._server = server
        self._limit = limit
        self._refused = 0
        self._evicted = 0
        self.listening: asyncio.AbstractServer | None = None  # set once it listens

    def open_connections(self) -> int:
        active = getattr(self.listening, "_active_count", None)
        return active if isinstance(active, int) else len(self._server.connections)

    def __call__(self) -> asyncio.BaseProtocol:
        open_now = self.open_connections()
        if open_now >= self._limit and not self._close_longest_waiting():
            self._refused += 1
            if self._refused in (1, 10, 100) or self._refused % 1000 == 0:
                log.warning("web page: %d connections open, at most %d: refused the newest "
                            "(%d so far)", open_now, self._limit, self._refused)
            return _Refused()
        protocol: asyncio.BaseProtocol = self._server()
        return protocol

    def _close_longest_waiting(self) -> bool:
        """Close the oldest connection with no request in progress; False when there is none.
        aiohttp keeps its connections in the order they were made; a handler whose request
        is being answered holds it in `_current_request`, and parsed requests not yet begun
        wait in `_messages`, and one waiting for its next request awaits `_waiter` (all three
        private, on aiohttp 3.8 to 3.14: where they are missing, nothing is closed and the
        newest is refused as before)."""
        for handler in list(getattr(self._server, "connections", ())):
            busy = getattr(handler, "_current_request", True)
            queued = getattr(handler, "_messages", True)
            # aiohttp waits on `_waiter` for the next request: not while a response is still
            # being sent (`_current_request` is cleared before that), nor between a parsed
            # request and its handler's start.
            waiter = getattr(handler, "_waiter", None)
            waiting = waiter is not None and not waiter.done()
            transport = getattr(handler, "transport", None)
            if busy is None and not queued and waiting and transport is not None and (
                not transport.is_closing()  # one closed moments ago, in this burst of accepts
            ):
                transport.close()
                self._evicted += 1
                if self._evicted in (1, 10, 100) or self._evicted % 1000 == 0:
                    log.warning("web page: %d connections open, at most %d: closed the one "
                                "waiting longest without a request (%d so far)",
                                self.open_connections(), self._limit, self._evicted)
                return True
        return False


class _Refused(asyncio.Protocol):
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        transport.close()


def _config_text(exc: NetposeError) -> str:
    """The CLI's one line for a configuration error."""
    if isinstance(exc, ConfigError):
        return f"configuration error: {exc}"
    return str(exc)


def _error(status: int, text: str) -> web.Response:
    return web.json_response({"error": text}, status=status)


async def _json_body(request: web.Request) -> dict[str, Any]:
    try:
        body = await request.json()
    except (ValueError, UnicodeDecodeError, RecursionError):  # nested beyond json's depth
        raise web.HTTPBadRequest(text='{"error": "the request body is not JSON"}',
                                 content_type="application/json") from None
    if not isinstance(body, dict):
        raise web.HTTPBadRequest(text='{"error": "expected a JSON object"}',
                                 content_type="application/json")
    return body


def _slow_body() -> web.Response:
    return _error(408, f"the request's body did not arrive within {BODY_DEADLINE_S:.0f} s")


def _client(request: web.Request) -> str:
    """Who sent a request, for the log: its address, and the one a proxy (BlueOS's nginx) says
    it forwarded."""
    forwarded = request.headers.get("X-Forwarded-For", "").split(",")[0].strip()
    peer = request.remote or "?"
    return f"{peer} (for {forwarded[:64]!r})" if forwarded else peer


def _loopback(host: str) -> bool:
    """Whether `host` (web.host) is reachable from this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a name: it may well resolve to the network


def _boot_id() -> str | None:
    """This boot of the computer (Linux): the daemon's monotonic clock is this boot's."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text(encoding="ascii").strip()
    except OSError:
        return None
