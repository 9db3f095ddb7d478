"""The web page of the real daemon (`netpose run`, demo source): what BlueOS reads, the safety
rules, live data that no slow page can hold up, settings through the file's validation, a
restart for what a reload cannot change, and recordings that `netpose replay` reproduces.

One daemon serves the module (start-up costs a few seconds on two cores); tests that change
its settings run last.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
import signal
import socket
import statistics
import subprocess
import sys
import tarfile
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import pytest

from drivers.sources.synthetic import builtin_camera
from drivers.web.live import (
    EVENTS_PER_CLIENT,
    HISTORY_STEP_S,
    PENDING_ESTIMATES,
    ClientSlots,
    LiveFeed,
    PlotHistory,
    plot_point,
)
from drivers.web.security import host_trusted, origin_allowed, token_ok
from drivers.web.settings import WebSettings
from service.core.camera import save_camera
from service.core.errors import ConfigError
from service.core.messages import EstimateMessage, FilteredView
from tests.fake_autopilot import FakeAutopilot, UdpServerTransport
from tests.web_harness import REPO, WebDaemon

REQUIRED_SERVICE_KEYS = ("name", "description", "icon", "company", "version", "webpage", "api")


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[WebDaemon]:
    d = WebDaemon(tmp_path_factory.mktemp("web")).start()
    try:
        yield d
    finally:
        code = d.stop()
        assert code == 0, d.log()


def _upload(daemon: WebDaemon, name: str, content: bytes) -> tuple[int, Any]:
    boundary = "netposeboundary"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; "
            f"filename=\"{name}\"\r\n\r\n").encode()
    body = head + content + f"\r\n--{boundary}--\r\n".encode()
    kind = f"multipart/form-data; boundary={boundary}"
    return daemon.request("POST", "/api/calibration", body, token=True,
                          headers={"Content-Type": kind})


# -- rules that need no server --------------------------------------------------------------------
@pytest.mark.parametrize(("origin", "host", "ok"), [
    (None, "vehicle:8780", True),                        # curl, scripts: no Origin
    ("http://vehicle:8780", "vehicle:8780", True),       # the page itself
    ("http://VEHICLE:8780", "vehicle:8780", True),
    ("http://vehicle:8781", "vehicle:8780", False),      # another port of the same host
    ("http://evil.example", "vehicle:8780", False),
    ("null", "vehicle:8780", False),                     # sandboxed frame, file://
    ("http://blueos.local", "blueos.local", True),       # through BlueOS's nginx ($host)
    ("http://blueos.local:8080", "blueos.local", True),  # a tunnel to that nginx
    ("http://other.local", "blueos.local", False),
    ("ftp://vehicle", "vehicle", False),
    ("http://[::1]:8780", "[::1]:8780", True),
])
def test_origin_rule(origin: str | None, host: str, ok: bool) -> None:
    assert origin_allowed(origin, host) is ok


def test_allowed_origins_and_settings_validation() -> None:
    assert origin_allowed("http://topside:9000", "vehicle:8780", ["http://topside:9000"])
    with pytest.raises(ConfigError, match=r"^web\.port: 5777 is used or skipped by BlueOS"):
        WebSettings(port=5777)
    with pytest.raises(ConfigError, match=r"^web\.token: must be at least 8"):
        WebSettings(token="short")
    with pytest.raises(ConfigError, match=r"^web\.allowed_origins"):
        WebSettings(allowed_origins=("http://x/path",))


def test_the_settings_form_offers_what_the_autopilot_is_given(tmp_path: Path) -> None:
    """Which distance the autopilot's rangefinder gets (along the camera axis or to the net
    plane) is what a pilot changes when a net hold or a range hold reads it: the form offers
    it beside the link, as a choice of the two, with the value in force."""
    from service.daemon.settings_editor import SettingsEditor
    from service.daemon.wiring import load_daemon_config

    save_camera(builtin_camera(1280, 720), tmp_path / "camera.yaml")
    config = tmp_path / "netpose.toml"
    config.write_text('[camera]\nurl = "synthetic:"\ncalibration = "camera.yaml"\n'
                      '[mesh]\nbar_length_m = 0.025\n[service]\n'
                      'autopilot_distance = "perpendicular"\n')
    editor = SettingsEditor(config, (), lambda p: load_daemon_config(str(p)), lambda: None,
                            lambda: None)
    snapshot = editor.snapshot()
    autopilot = next(g for g in snapshot["groups"] if g["title"].startswith("Autopilot"))
    field = next(f for f in autopilot["fields"] if f["key"] == "service.autopilot_distance")
    assert field["type"] == "choice"
    assert set(field["choices"]) == {"perpendicular", "optical_axis"}
    assert snapshot["values"]["service.autopilot_distance"] == "perpendicular"


def test_the_settings_page_never_shows_a_camera_password(tmp_path: Path) -> None:
    """GET /api/settings needs no token (the token guards changes): a camera URL's password
    is redacted there as in the log, and sending the redacted text back is refused rather
    than saved as the password."""
    import urllib.request

    import numpy as np

    from drivers.net import free_port
    from drivers.web.page import WebPage
    from service.daemon.settings_editor import SettingsEditor
    from service.daemon.wiring import load_daemon_config

    save_camera(builtin_camera(1280, 720), tmp_path / "camera.yaml")
    url = "rtsp://admin:S3cretPass@192.168.2.10:554/stream1"
    config = tmp_path / "netpose.toml"
    config.write_text(f'[camera]\nurl = "{url}"\ncalibration = "camera.yaml"\n'
                      '[mesh]\nbar_length_m = 0.025\n')
    editor = SettingsEditor(config, (), lambda p: load_daemon_config(str(p)), lambda: None,
                            lambda: None)
    port = free_port()
    page = WebPage[None](WebSettings(enabled=True, host="127.0.0.1", port=port,
                                     token="longtoken123"),
                         lambda f, r: np.zeros((8, 8, 3), np.uint8), editor)
    page.start()
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/settings", timeout=10) as r:
            body = r.read().decode()
    finally:
        page.close()
    assert "S3cretPass" not in body
    shown = json.loads(body)["values"]["camera.url"]
    assert shown == "rtsp://admin:<redacted>@192.168.2.10:554/stream1"
    with pytest.raises(ConfigError, match=r"^camera\.url: holds <redacted>"):
        editor.apply({"camera.url": shown.replace("stream1", "stream2")})
    assert url in config.read_text()


def test_a_save_while_the_daemon_restarts_is_saved_and_does_not_hold_up_the_restart(
    tmp_path: Path,
) -> None:
    """A save that came as the page's Restart was under way waited 15 s for a reload the
    stopping daemon never did, and held the restart (and the autopilot's distance) that long;
    then it answered with an error for a change it had saved. It is saved, said to apply as
    the service restarts, at once."""
    import threading

    from service.daemon.settings_editor import SettingsEditor
    from service.daemon.wiring import load_daemon_config

    save_camera(builtin_camera(1280, 720), tmp_path / "camera.yaml")
    config = tmp_path / "netpose.toml"
    config.write_text('[camera]\nurl = "synthetic:"\ncalibration = "camera.yaml"\n'
                      '[mesh]\nbar_length_m = 0.025\n')
    stopping = threading.Event()
    editor = SettingsEditor(config, (), lambda p: load_daemon_config(str(p)), lambda: None,
                            stopping.set, stopping=stopping.is_set)
    editor.restart()  # nothing reloads from now on: the daemon is on its way down
    started = time.monotonic()
    outcome = editor.apply({"mesh.bar_length_m": 0.03})
    assert time.monotonic() - started < 2.0
    assert outcome["saved"] and "restarts" in outcome["message"], outcome
    assert "bar_length_m = 0.03" in config.read_text()


def _bare_page(tmp_path: Path) -> tuple[Any, int]:
    """A page (not started) with no daemon behind it, over a minimal configuration in
    tmp_path: (page, port)."""
    import numpy as np

    from drivers.net import free_port
    from drivers.web.page import WebPage
    from service.daemon.settings_editor import SettingsEditor
    from service.daemon.wiring import load_daemon_config

    config = tmp_path / "netpose.toml"
    config.write_text("[mesh]\nbar_length_m = 0.025\n")
    editor = SettingsEditor(config, (), lambda p: load_daemon_config(str(p)), lambda: None,
                            lambda: None)
    port = free_port()
    page = WebPage[None](WebSettings(enabled=True, host="127.0.0.1", port=port),
                         lambda f, r: np.zeros((8, 8, 3), np.uint8), editor)
    return page, port


def test_a_change_the_daemon_refuses_leaves_the_file_as_it_was(tmp_path: Path) -> None:
    """The vehicle armed between the page's check and the daemon's reload: the daemon refused
    the new mesh, but the file kept it, and the next restart applied it unannounced. The file
    goes back and the page is told nothing changed."""
    import threading

    from service.daemon.loop import ReloadOutcome
    from service.daemon.settings_editor import SettingsEditor
    from service.daemon.wiring import load_daemon_config

    config = tmp_path / "netpose.toml"
    config.write_text((REPO / "config" / "demo.toml").read_text())
    before = config.read_bytes()
    holder: list[SettingsEditor] = []

    def refuse() -> None:
        outcome = ReloadOutcome(ok=False, error="mesh: not changed while the vehicle is armed")
        threading.Timer(0.05, holder[0].reloaded, [outcome]).start()

    editor = SettingsEditor(config, (), lambda p: load_daemon_config(str(p)), refuse,
                            lambda: None)
    holder.append(editor)
    with pytest.raises(ConfigError, match="not changed: the daemon refused it: mesh: not "
                       "changed while the vehicle is armed"):
        editor.apply({"mesh.bar_length_m": 0.25})
    assert config.read_bytes() == before


def test_live_pages_are_capped_and_a_closed_one_makes_room(tmp_path: Path) -> None:
    """Each live page takes about 1.6 Mbit/s; 200 of them took 789 MB in 20 s, a tether's
    worth. Past MAX_LIVE_CLIENTS a page is refused (503) with the reason; one closed makes
    room for the next."""
    import asyncio

    import aiohttp

    from drivers.web.page import MAX_LIVE_CLIENTS

    page, port = _bare_page(tmp_path)
    url = f"ws://127.0.0.1:{port}/ws"

    async def crowd() -> tuple[int, str, bool]:
        async with aiohttp.ClientSession() as session:
            open_ = [await session.ws_connect(url) for _ in range(MAX_LIVE_CLIENTS)]
            try:
                await session.ws_connect(url)
                refused, why = 0, ""
            except aiohttp.WSServerHandshakeError as exc:
                refused, why = exc.status, exc.message
            await open_.pop().close()
            await asyncio.sleep(0.2)
            again = await session.ws_connect(url)
            taken = not again.closed
            for ws in (*open_, again):
                await ws.close()
            return refused, why, taken

    page.start()
    try:
        refused, _why, taken = asyncio.run(crowd())
    finally:
        page.close()
    assert refused == 503 and taken


def test_clients_that_never_finish_a_request_cannot_take_every_file_descriptor(
    tmp_path: Path,
) -> None:
    """About 1,100 connections that sent half a header and nothing more took the process's
    1,024 descriptors: the page went dark, a reload could not open the configuration, and
    the camera and the MAVLink link would not have reopened either. Past MAX_CONNECTIONS a
    connection is closed as it is accepted; once the others go, the page answers again."""
    from drivers.web.page import MAX_CONNECTIONS

    page, port = _bare_page(tmp_path)

    def descriptors() -> int:
        return len(os.listdir("/proc/self/fd"))

    page.start()
    slow: list[socket.socket] = []
    try:
        before = descriptors()
        for _ in range(MAX_CONNECTIONS + 40):
            s = socket.create_connection(("127.0.0.1", port), timeout=5.0)
            s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nX-a: ")
            slow.append(s)
        # The server accepts (or refuses) them all as its thread gets to them.
        deadline = time.monotonic() + 10.0
        while (served := descriptors() - before - len(slow)) > MAX_CONNECTIONS + 2:
            assert time.monotonic() < deadline, served
            time.sleep(0.1)
        time.sleep(0.5)  # and no more come
        served = descriptors() - before - len(slow)
        assert served <= MAX_CONNECTIONS + 2, served
        for s in slow:
            s.close()
        slow = []
        deadline = time.monotonic() + 10.0
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/register_service",
                                            timeout=5) as reply:
                    assert reply.status == 200
                    break
            except OSError:
                assert time.monotonic() < deadline
                time.sleep(0.2)
        # Short requests one after another (urllib closes each connection), faster than the
        # cap forgets a connection it has not seen connected: none is refused.
        for _ in range(MAX_CONNECTIONS + 16):
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/register_service",
                                        timeout=5) as reply:
                assert reply.status == 200
    finally:
        for s in slow:
            s.close()
        page.close()


def test_connections_that_never_send_a_request_cannot_lock_the_pilot_out(
    tmp_path: Path,
) -> None:
    """Slowloris: MAX_CONNECTIONS connections that send half a header and then nothing held
    every slot, and the pilot's page was refused for as long as they stayed open (aiohttp has
    no header timeout). At the cap, the connection that has waited longest without a request
    in progress is closed for the new one: the page is served while they are all open, and a
    live view opened before them (a request in progress) is not the one closed."""
    import asyncio

    import aiohttp

    from drivers.web.page import MAX_CONNECTIONS

    page, port = _bare_page(tmp_path)

    async def crowd() -> tuple[bool, bool]:
        async with aiohttp.ClientSession() as session:
            live = await session.ws_connect(f"ws://127.0.0.1:{port}/ws")
            slow: list[socket.socket] = []
            try:
                for _ in range(MAX_CONNECTIONS + 8):
                    s = socket.create_connection(("127.0.0.1", port), timeout=5.0)
                    s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nX-a: ")
                    slow.append(s)
                await asyncio.sleep(0.5)  # all accepted by the server's thread
                for _ in range(5):
                    async with session.get(
                        f"http://127.0.0.1:{port}/register_service") as reply:
                        assert reply.status == 200
                # The oldest half-headers went first (closed, or reset where their unread bytes
                # were still queued). (Which of a burst of connections past the cap is closed
                # depends on whether aiohttp had registered the others yet: the newest may be
                # refused instead.)
                try:
                    oldest_gone = slow[0].recv(1, socket.MSG_PEEK) == b""
                except ConnectionResetError:
                    oldest_gone = True
                try:  # a closed view reads its close at once; an open one, a push or nothing
                    message = await live.receive(timeout=0.5)
                    live_open = message.type not in (aiohttp.WSMsgType.CLOSE,
                                                      aiohttp.WSMsgType.CLOSED,
                                                      aiohttp.WSMsgType.ERROR)
                except TimeoutError:
                    live_open = True
                await live.close()
                return oldest_gone, live_open
            finally:
                for s in slow:
                    s.close()

    page.start()
    try:
        oldest_gone, live_open = asyncio.run(crowd())
    finally:
        page.close()
    assert oldest_gone and live_open


@pytest.mark.parametrize(("kind", "path"), [
    ("application/json", "/api/settings"),
    ("multipart/form-data; boundary=b", "/api/calibration"),
    ("multipart/form-data; boundary=b", "/api/settings"),  # labelled so to slip the deadline
])
def test_a_body_sent_a_byte_at_a_time_is_cut_off(tmp_path: Path, kind: str, path: str,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A change whose body trickled in (a byte every few seconds) held its connection for as
    long as it went on, and 64 of them every connection the page has (aiohttp reads a body
    with no deadline). A body not in by BODY_DEADLINE_S gets 408 and its connection ends."""
    from drivers.web import page as page_module

    monkeypatch.setattr(page_module, "BODY_DEADLINE_S", 1.0, raising=False)
    page, port = _bare_page(tmp_path)
    page.start()
    s = socket.create_connection(("127.0.0.1", port), timeout=10.0)
    try:
        s.sendall(f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: {kind}\r\n"
                  "Content-Length: 200\r\n\r\n--b\r\n".encode())
        started = time.monotonic()
        reply = b""
        s.settimeout(0.3)
        while b"\r\n\r\n" not in reply:
            assert time.monotonic() - started < 8.0, reply
            try:
                s.sendall(b"x")  # a trickle that never ends
                reply += s.recv(4096)
            except TimeoutError:
                continue
        waited = time.monotonic() - started
    finally:
        s.close()
        page.close()
    assert reply.startswith(b"HTTP/1.1 408"), reply
    assert 0.9 < waited < 3.0, waited


def _page_with_a_large_recording(tmp_path: Path) -> tuple[Any, int, str]:
    """A started page (no daemon behind it) over one finished recording of 32 MB: more than
    the loopback socket's buffers and the page's queue hold. (page, port, recording name)."""
    import numpy as np

    from drivers.net import free_port
    from drivers.recorder import MANIFEST, Recorder, RecordingSetup
    from drivers.web.page import WebPage

    name = "netpose-rov-20260101T120000Z"
    folder = tmp_path / name
    (folder / "frames").mkdir(parents=True)
    (folder / MANIFEST).write_text(json.dumps({"finished": True}))
    (folder / "frames" / "00000001.png").write_bytes(bytes(32 * 1024 * 1024))
    port = free_port()

    def no_recording() -> RecordingSetup:
        raise AssertionError("this test records nothing")

    no_settings: Any = object()
    page = WebPage[None](WebSettings(enabled=True, host="127.0.0.1", port=port),
                         lambda f, r: np.zeros((8, 8, 3), np.uint8), no_settings,
                         Recorder(tmp_path, "rov", no_recording, 10**9))
    page.start()
    return page, port, name


def test_a_stalled_download_does_not_hold_up_the_pages_stop(tmp_path: Path) -> None:
    """A topside client that stops reading a recording's tar (a slow link, a closed laptop)
    must not keep a stop or a restart waiting: the page cuts the download off and closes at
    once (it waited for the download's one-minute timeouts, about two minutes, before)."""
    page, port, name = _page_with_a_large_recording(tmp_path)
    client = socket.create_connection(("127.0.0.1", port))
    client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        client.sendall(f"GET /api/recordings/{name}.tar HTTP/1.1\r\n"
                       f"Host: 127.0.0.1:{port}\r\n\r\n".encode())
        assert client.recv(64).startswith(b"HTTP/1.1 200")
        time.sleep(1.0)  # the download fills every buffer; the client reads no more
        t0 = time.monotonic()
        page.close()
        closing_s = time.monotonic() - t0
        assert closing_s < 5.0, closing_s
        stalled = [t.name for t in threading.enumerate()
                   if t.name.startswith(("web files", "web downloads"))]
        assert stalled == []
    finally:
        client.close()


def test_a_download_the_page_gave_up_on_does_not_look_complete(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A client that stops reading for longer than the stall limit (BlueOS's proxy spooling a
    large recording to its card does) got a response that ended cleanly, cut short: HTTP 200,
    curl's exit 0, and `tar: Unexpected EOF` only when the file was opened. The page now cuts
    the connection, so the client sees an incomplete transfer; and a download cut at its end
    no longer waits for ever for the end that never came. The response also asks a proxy not
    to buffer it (X-Accel-Buffering: no), so the stall limit meets the real client."""
    import http.client

    import drivers.web.page as page_module

    monkeypatch.setattr(page_module, "DOWNLOAD_STALL_S", 1.0)
    page, port, name = _page_with_a_large_recording(tmp_path)
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=20)
    try:
        conn.request("GET", f"/api/recordings/{name}.tar")
        reply = conn.getresponse()
        assert reply.status == 200 and reply.getheader("X-Accel-Buffering") == "no"
        reply.read(1024)
        time.sleep(3.0)  # past the stall limit: the page gives up
        t0 = time.monotonic()
        with pytest.raises((http.client.IncompleteRead, ConnectionError)):
            reply.read()  # the rest: cut, not a clean end
        assert time.monotonic() - t0 < 10.0
        # A client that never reads again (a paused download): cut all the same, so it holds
        # no download slot, and its recording can be deleted.
        paused = http.client.HTTPConnection("127.0.0.1", port, timeout=20)
        paused.request("GET", f"/api/recordings/{name}.tar")
        assert paused.getresponse().status == 200
        deadline = time.monotonic() + 15.0
        while page._downloads:  # the page's own count of downloads under way
            assert time.monotonic() < deadline, "a paused download was never cut"
            time.sleep(0.2)
        paused.close()
    finally:
        conn.close()
        page.close()


def test_a_recording_is_deleted_from_the_page_unless_it_is_being_downloaded(
    tmp_path: Path,
) -> None:
    """Recordings of up to 2 GB each filled the card BlueOS shares with its updates and other
    extensions, and the page could not delete one. It can now, with the change header (and
    the token where one is set); not one that is being downloaded or recorded, nor a name
    that is not a recording."""
    import http.client

    page, port, name = _page_with_a_large_recording(tmp_path)
    folder = tmp_path / name

    def delete(which: str, change: bool = True) -> tuple[int, dict[str, Any]]:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        headers = {"Origin": f"http://127.0.0.1:{port}", "Content-Type": "application/json"}
        if change:
            headers["X-Netpose-Change"] = "1"
        conn.request("POST", f"/api/recordings/{which}/delete", body=b"{}", headers=headers)
        reply = conn.getresponse()
        body = json.loads(reply.read() or b"{}")
        conn.close()
        return reply.status, body

    try:
        assert delete(name, change=False)[0] == 403  # a browser's change needs the header
        assert delete("netpose-rov-20990101T000000Z")[0] == 404
        assert delete("..")[0] == 404
        downloading = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        downloading.request("GET", f"/api/recordings/{name}.tar")
        reply = downloading.getresponse()
        reply.read(1024)  # under way, not finished
        status, body = delete(name)
        assert status == 409 and "being downloaded" in body["error"], body
        downloading.close()
        deadline = time.monotonic() + 10.0
        while (answer := delete(name))[0] == 409:  # once the page has seen it go
            assert time.monotonic() < deadline, answer
            time.sleep(0.2)
        assert answer[0] == 200 and answer[1]["deleted"] == name, answer
        assert answer[1]["bytes"] >= 32 * 1024 * 1024
        assert not folder.exists()
    finally:
        page.close()


def test_downloads_under_way_do_not_hold_up_recording_and_settings(tmp_path: Path) -> None:
    """Two recordings downloading over a slow tether held both threads of the pool that also
    starts and stops recordings and saves settings: "stop recording" waited 140 s while the
    card filled. Downloads have threads of their own (and a limit)."""
    from drivers.web.page import MAX_DOWNLOADS

    page, port, name = _page_with_a_large_recording(tmp_path)
    clients = []
    try:
        for _ in range(MAX_DOWNLOADS + 1):
            client = socket.create_connection(("127.0.0.1", port))
            client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            client.sendall(f"GET /api/recordings/{name}.tar HTTP/1.1\r\n"
                           f"Host: 127.0.0.1:{port}\r\n\r\n".encode())
            clients.append(client)
            time.sleep(0.3)  # each fills its buffers; nobody reads
        heads = [c.recv(64) for c in clients]
        assert all(h.startswith(b"HTTP/1.1 200") for h in heads[:MAX_DOWNLOADS]), heads
        assert heads[-1].startswith(b"HTTP/1.1 503"), heads[-1]  # one too many, said so
        t0 = time.monotonic()
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/recordings",
                                    timeout=10) as reply:
            listing = json.loads(reply.read())
        assert time.monotonic() - t0 < 2.0
        assert [r["name"] for r in listing["recordings"]] == [name]
    finally:
        for client in clients:
            client.close()
        page.close()


def _estimate(seq: int, t: float, detected: bool = True, valid: bool = True,
              along: str = "optical_axis") -> EstimateMessage:
    """A frame of a net tilted 35 deg: 1.0 m along the axis, 0.82 m perpendicular (raw 1.1 m
    along the axis, 0.9 m perpendicular); the autopilot gets the distance `along` names."""
    sent = (1.0 if along == "optical_axis" else 0.82) if valid else None
    filtered = FilteredView(valid=valid, autopilot="good" if valid else "none",
                            autopilot_distance_m=sent, autopilot_along=along,
                            state="tracking" if valid else "lost", measurement="accepted",
                            distance_m=0.82 if valid else None, range_m=1.0 if valid else None,
                            normal=(0.0, 0.5736, -0.8192) if valid else None)
    return EstimateMessage(vehicle="v", time_unix=t, time_mono=t, seq=seq, frame_time_mono=t,
                           detected=detected, distance_m=0.9 if detected else None,
                           range_m=1.1 if detected else None,
                           tilt_deg=35.0 if detected else None, filtered=filtered)


def test_a_busy_page_port_costs_the_page_not_the_distance(tmp_path: Path) -> None:
    """Something else on the page's port (a stale daemon, a BlueOS port clash): the page
    retried once, then failed for good ("Site is already registered in runner") and its dead
    event loop took the frame loop down with it ("Event loop is closed"), exit 1: the
    autopilot lost its distance for a web page. The loop goes on; the page comes up once the
    port is free."""
    page = WebDaemon(tmp_path)
    squatter = socket.socket()
    squatter.bind(("127.0.0.1", page.port))
    squatter.listen()
    env = {k: v for k, v in os.environ.items() if k != "NOTIFY_SOCKET"}
    with page.log_path.open("wb") as log:
        page.proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "run", "--config", str(page.config)],
            cwd=REPO, env={**env, "PYTHONUNBUFFERED": "1"}, stdout=log,
            stderr=subprocess.STDOUT)
    try:
        time.sleep(12.0)  # two retries
        assert page.proc.poll() is None, page.log()
        squatter.close()
        deadline = time.monotonic() + 15.0
        while True:
            try:
                if page.request("GET", "/register_service", timeout_s=2.0)[0] == 200:
                    break
            except OSError:
                pass
            assert time.monotonic() < deadline, page.log()
            time.sleep(0.3)
        assert page.collect(1.5)[1]  # live frames: the loop ran all along
    finally:
        squatter.close()
        status = page.stop()
    log_text = page.log()
    assert status == 0, log_text
    assert log_text.count("cannot listen") == 1 and "server failed" not in log_text
    assert "Event loop is closed" not in log_text


def test_what_waits_for_a_page_is_bounded_and_the_newest_wins() -> None:
    feed = LiveFeed()
    wakes = []
    feed.attach(lambda: wakes.append(1))
    for seq in range(10_000):  # an event loop that never runs
        feed.put_frame(object(), None, _estimate(seq, seq / 30))
    estimates, _, newest = feed.take()
    assert len(wakes) == 1  # one wake-up per batch, not per frame
    assert len(estimates) == PENDING_ESTIMATES and estimates[-1].seq == 9999
    assert newest is not None and newest[2].seq == 9999
    slots = ClientSlots()
    for i in range(100):
        slots.set_jpeg(bytes([i]))
        slots.set_text("estimate", str(i))
        slots.add_event(str(i))
    texts, jpeg = slots.take()
    assert jpeg == bytes([99]) and slots.frames_replaced == 99
    assert texts == [str(i) for i in range(100 - EVENTS_PER_CLIENT, 100)] + ["99"]


def test_plot_history_thins_but_keeps_the_gaps() -> None:
    history = PlotHistory(span_s=10.0)
    for i in range(600):  # 20 s at 30 frames/s; no net from 5 s to 6 s
        t = i / 30
        history.add(_estimate(i, t, detected=not 5.0 <= t < 6.0, valid=not 5.0 <= t < 6.5))
    times = [float(p[0] or 0.0) for p in history.points()]
    assert times[0] >= 20 - 10.0 - 0.05  # the last 10 s only
    assert len(times) <= 10 / HISTORY_STEP_S + 5
    history = PlotHistory(span_s=60.0)
    for i in range(600):
        t = i / 30
        history.add(_estimate(i, t, detected=not 5.0 <= t < 6.0, valid=not 5.0 <= t < 6.5))
    gap = [float(p[0] or 0.0) for p in history.points() if p[1] is None]
    assert gap and abs(gap[0] - 5.0) < 1 / 30 + 1e-9  # the gap starts where it did
    resumed = [float(p[0] or 0.0) for p in history.points()
               if float(p[0] or 0.0) >= 6.0 and p[1] is not None]
    assert abs(resumed[0] - 6.0) < 1 / 30 + 1e-9


def test_plot_points_show_the_distance_the_autopilot_gets() -> None:
    """The plot's line is the distance handed to the autopilot, its dots the raw estimate of the
    same kind: along the camera axis by default, perpendicular when so configured. It plotted
    the perpendicular distance as "what the autopilot gets" whatever the setting (0.82 m
    drawn, 100 cm sent at 35 deg). A change of kind (a reload) is kept in the history."""
    axis = plot_point(_estimate(1, 1.0))
    assert axis[1] == 1.1 and axis[3] == 1.0 and axis[6] == "optical_axis"
    square = plot_point(_estimate(2, 2.0, along="perpendicular"))
    assert square[1] == 0.9 and square[3] == 0.82 and square[6] == "perpendicular"
    assert plot_point(_estimate(3, 3.0, valid=False))[3] is None  # nothing sent: a gap
    history = PlotHistory(span_s=60.0)
    for i in range(90):  # 3 s at 30 frames/s; the setting changes at 1.5 s
        t = i / 30
        history.add(_estimate(i, t, along="optical_axis" if t < 1.5 else "perpendicular"))
    changed = [float(p[0] or 0.0) for p in history.points() if p[6] == "perpendicular"]
    assert changed and abs(changed[0] - 1.5) < 1 / 30 + 1e-9


def test_plot_points_carry_a_net_seen_without_a_distance() -> None:
    """A frame whose net was seen but refused as too uncertain: no raw distance, its refused
    range in the sixth place (drawn hollow by the page), and the history keeps where such a
    stretch starts and ends as it keeps the gaps."""
    import dataclasses

    seen = dataclasses.replace(_estimate(1, 1.0, detected=False, valid=False), net_seen=True,
                               approx_range_m=0.83, approx_sigma_range_m=0.03)
    point = plot_point(seen)
    assert point[1] is None and point[3] is None and point[5] == 0.83
    assert plot_point(_estimate(2, 2.0))[5] is None  # measured: a raw distance, no seen range
    history = PlotHistory(span_s=60.0)
    for i in range(300):  # 10 s at 30 frames/s; seen only from 4 s to 5 s
        t = i / 30
        e = _estimate(i, t, detected=not 4.0 <= t < 5.0, valid=True)
        if 4.0 <= t < 5.0:
            e = dataclasses.replace(e, net_seen=True, approx_range_m=0.8)
        history.add(e)
    marked = [float(p[0] or 0.0) for p in history.points() if p[5] is not None]
    assert marked and abs(marked[0] - 4.0) < 1 / 30 + 1e-9


# -- what BlueOS and Cockpit read -----------------------------------------------------------------
def test_register_service_has_what_blueos_requires(daemon: WebDaemon) -> None:
    status, body = daemon.request("GET", "/register_service")
    assert status == 200
    for key in REQUIRED_SERVICE_KEYS:
        assert isinstance(body[key], str), key
    assert body["works_in_relative_paths"] is True
    status, extras = daemon.request("GET", body["extras"]["cockpit"])
    assert status == 200 and extras["targetSystem"] == "Cockpit"
    widget = extras["widgets"][0]
    assert widget["name"] and widget["useExtensionPathAsBaseUrl"] is True
    for path in (widget["iframeUrl"], widget["iconUrl"], widget["iframeIcon"]):
        assert daemon.request("GET", path)[0] == 200, path


def test_pages_use_only_relative_urls(daemon: WebDaemon) -> None:
    # Under BlueOS the page lives at /extensionv2/netpose/: an absolute /path would miss it.
    for path in ("/", "/widget", "/static/app.js"):
        status, raw = daemon.request("GET", path)
        assert status == 200
        text = raw.decode()
        assert not re.search(r"""(src|href|action)=["']/""", text), path
        assert not re.search(r"""fetch\(\s*["'`]/""", text), path
    assert b"<title>netpose</title>" in daemon.request("GET", "/")[1]


# -- safety ---------------------------------------------------------------------------------------
def test_a_page_open_to_the_network_without_a_token_is_warned_of(tmp_path: Path) -> None:
    """The Pi profile's page turned on with an empty token said only "web page on
    http://0.0.0.0:8780/" at INFO: anyone on the network could change the mesh size."""
    d = WebDaemon(tmp_path, token="", host="0.0.0.0").start()
    try:
        line = next((line for line in d.log().splitlines() if "without web.token" in line), "")
        assert "WARNING" in line and f"port {d.port}" in line, d.log()
    finally:
        assert d.stop() == 0, d.log()
    (tmp_path / "loopback").mkdir()
    quiet = WebDaemon(tmp_path / "loopback", token="").start()  # 127.0.0.1: this machine only
    try:
        assert "without web.token" not in quiet.log()
    finally:
        assert quiet.stop() == 0, quiet.log()


def test_changes_without_the_token_are_refused(daemon: WebDaemon) -> None:
    before = daemon.config.read_bytes()
    for path, body in (("/api/settings", {"changes": {"mesh.bar_length_m": 0.03}}),
                       ("/api/recordings/start", {}), ("/api/restart", {})):
        status, reply = daemon.request("POST", path, body)
        assert status == 401, (path, reply)
        assert "token" in reply["error"]
        status, reply = daemon.request("POST", path, body,
                                       headers={"X-Netpose-Token": "wrong-token-123"})
        assert status == 401
    assert daemon.config.read_bytes() == before
    assert daemon.request("GET", "/api/recordings")[1]["status"]["active"] is False
    # Reading stays open.
    assert daemon.request("GET", "/api/settings")[0] == 200


def test_the_page_changes_only_the_settings_it_offers(daemon: WebDaemon) -> None:
    """The page is open to the vehicle's network, its token off by default. It saved any key
    outside [web]: one request set a rendered camera and `mavlink.allow_simulated`, and the
    service sent rendered distances to the autopilot (268 in 20 s); others loosened the
    filter's gates live, or named /dev/zero as a key file to read. Only what the form shows
    is changed from the page; the rest is the file's."""
    before = daemon.config.read_bytes()
    for changes in ({"mavlink.allow_simulated": True},
                    {"camera.url": "synthetic:?trajectory=approach",
                     "mavlink.allow_simulated": True},
                    {"filter.min_confidence": 0.0}, {"filter.gate_sigma": 1e6},
                    {"mavlink.max_age_s": 2.0}, {"mavlink.signing_key_file": "/dev/zero"},
                    {"telemetry.config_file": "/etc/hostname"}):
        status, reply = daemon.request("POST", "/api/settings", {"changes": changes},
                                       token=True)
        assert status == 400, (changes, reply)
        assert "is not one of the settings the page changes" in reply["error"]
    assert daemon.config.read_bytes() == before
    offered = {f["key"] for g in daemon.request("GET", "/api/settings")[1]["groups"]
               for f in g["fields"]}
    assert "mavlink.allow_simulated" not in offered and "mesh.bar_length_m" in offered


def test_requests_from_another_origin_are_refused(daemon: WebDaemon) -> None:
    before = daemon.config.read_bytes()
    status, reply = daemon.request("POST", "/api/settings",
                                   {"changes": {"mesh.bar_length_m": 0.03}},
                                   headers={"Origin": "http://evil.example"}, token=True)
    assert status == 403 and "another origin" in reply["error"]
    assert daemon.config.read_bytes() == before
    with pytest.raises(Exception, match="403"):
        daemon.collect(1.0, origin="http://evil.example")
    texts, _ = daemon.collect(1.0, origin=daemon.base)  # its own origin is fine
    assert texts and texts[0]["kind"] == "hello"


@pytest.mark.parametrize(("host", "ok"), [
    ("192.168.2.2:8780", True), ("[fe80::1]:8780", True), ("localhost:8780", True),
    ("blueos.local", True), ("raspberrypi:8780", True),  # mDNS, the LAN's own names
    ("blueos.local.", True), ("raspberrypi.lan:8780", True), ("rov.home.arpa", True),
    ("evil.example:8780", False), ("other.farm.example", False),
    ("rov.fritz.box", False),  # .box is a public top-level domain
    ("ROV.FARM.EXAMPLE:8780", True),  # listed in web.allowed_origins below
])
def test_host_rule(host: str, ok: bool) -> None:
    assert host_trusted(host, ["http://rov.farm.example:8780"]) is ok


def test_a_rebound_name_cannot_change_settings(daemon: WebDaemon) -> None:
    """DNS rebinding: a site the topside browser visits points its own name at the vehicle,
    and its script is then "the page's own origin" (Host and Origin agree). With no token, as
    BlueOS ships, it could rewrite what the autopilot gets. Changes are taken only from a name
    no website can be served under."""
    port = daemon.base.rsplit(":", 1)[1]
    before = daemon.config.read_bytes()
    status, reply = daemon.request(
        "POST", "/api/settings", {"changes": {"service.autopilot_distance": "perpendicular"}},
        token=True, headers={"Host": f"evil.example:{port}",
                             "Origin": f"http://evil.example:{port}",
                             "X-Netpose-Change": "1"})  # a script that asked: not even then
    assert status == 403 and "web.allowed_origins" in reply["error"], (status, reply)
    assert daemon.config.read_bytes() == before
    # Nor read the page's data: the live view, the settings (camera and link addresses), the
    # recordings of the dive. The page itself answers any name (it holds no data).
    rebound = {"Host": f"evil.example:{port}"}
    for path in ("/api/settings", "/api/recordings"):
        status, reply = daemon.request("GET", path, headers=rebound)
        assert status == 403 and "web.allowed_origins" in reply["error"], (path, status)
    status, reply = daemon.request("GET", "/ws", headers={
        **rebound, "Upgrade": "websocket", "Connection": "Upgrade",
        "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==", "Sec-WebSocket-Version": "13"})
    assert status == 403, status
    assert daemon.request("GET", "/", headers=rebound)[0] == 200
    assert daemon.request("GET", "/api/settings", headers={"Host": "blueos.local"})[0] == 200


def test_only_the_vehicles_own_pages_may_frame_the_page(daemon: WebDaemon) -> None:
    """Clickjacking: any website could lay the full page (Restart, recording) under its own.
    It may be framed by the vehicle's own pages only (BlueOS's sidebar, Cockpit served by
    BlueOS: the same host, any port); the Cockpit widget, which has no controls, anywhere.
    (Chromium enforcing it: tests/test_web_browser.py.)"""
    req = urllib.request.Request(daemon.base + "/", headers={"Host": "blueos.local"})
    with urllib.request.urlopen(req, timeout=10) as reply:
        policy = reply.headers["Content-Security-Policy"]
        assert reply.headers["X-Content-Type-Options"] == "nosniff"
    assert policy == ("frame-ancestors 'self' http://blueos.local:* https://blueos.local:*"
                      ), policy
    # A Host header is the client's word: nothing odd in it reaches the policy.
    req = urllib.request.Request(daemon.base + "/", headers={"Host": "x; frame-ancestors *"})
    with urllib.request.urlopen(req, timeout=10) as reply:
        assert reply.headers["Content-Security-Policy"] == "frame-ancestors 'self'"
    with urllib.request.urlopen(daemon.base + "/widget", timeout=10) as reply:
        assert reply.headers["Content-Security-Policy"] is None


def test_a_page_on_another_port_of_the_vehicle_cannot_change_settings(daemon: WebDaemon) -> None:
    """Behind BlueOS's proxy the Host has no port, so the Origin check compares host names
    only: any page served from the vehicle's name on another port (another extension, a tool)
    passed it, and a "simple" POST (JSON labelled text/plain: no preflight) changed the
    settings. A browser's change must carry a header that another page cannot send without a
    preflight, which this server never grants; the page's own requests carry it."""
    before = daemon.config.read_bytes()
    headers = {"Host": "blueos.local", "Origin": "http://blueos.local:6040",
               "Content-Type": "text/plain"}
    body = json.dumps({"changes": {"mesh.opening_angle_deg": 80.0}}).encode()
    status, reply = daemon.request("POST", "/api/settings", body, token=True, headers=headers)
    assert status == 403 and "X-Netpose-Change" in reply["error"], reply
    assert daemon.request("POST", "/api/restart", b"", token=True, headers=headers)[0] == 403
    assert daemon.config.read_bytes() == before
    # The page's own request, as app.js sends it, is taken.
    status, reply = daemon.request(
        "POST", "/api/settings", {"changes": {"mesh.opening_angle_deg": 80.0}}, token=True,
        headers={"Host": "blueos.local", "Origin": "http://blueos.local",
                 "X-Netpose-Change": "1"})
    assert status == 200 and reply["saved"], reply


def test_oversized_upload_is_refused(daemon: WebDaemon) -> None:
    before = daemon.config.read_bytes()
    status, reply = _upload(daemon, "camera.yaml", b"x" * (65 * 1024))  # max_upload_kb: 64
    assert status == 413 and "64 KB" in reply["error"]
    # Sent chunked (no length to refuse it by), 1 MB in a field before the file: the parts the
    # page skips count too (a 5 MB one went through a 256 KB limit).
    import http.client

    boundary = "netposeboundary"
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"junk\"\r\n\r\n".encode()
            + b"x" * (1 << 20) + f"\r\n--{boundary}\r\nContent-Disposition: form-data; "
            f"name=\"file\"; filename=\"camera.yaml\"\r\n\r\nimage_width: 640\r\n"
            f"--{boundary}--\r\n".encode())
    conn = http.client.HTTPConnection(daemon.base.split("//")[1], timeout=30)
    conn.request("POST", "/api/calibration", body=iter([body[i:i + 65536] for i in range(
        0, len(body), 65536)]), encode_chunked=True, headers={
            "Content-Type": f"multipart/form-data; boundary={boundary}",
            "X-Netpose-Token": daemon.token})
    response = conn.getresponse()
    assert response.status == 413 and "64 KB" in json.loads(response.read())["error"]
    conn.close()
    # A nested multipart part would be read through uncounted: refused.
    nested = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"junk\"\r\n"
              "Content-Type: multipart/mixed; boundary=inner\r\n\r\n--inner\r\n\r\nx\r\n"
              f"--inner--\r\n--{boundary}--\r\n").encode()
    status, reply = daemon.request("POST", "/api/calibration", nested, token=True, headers={
        "Content-Type": f"multipart/form-data; boundary={boundary}"})
    assert status == 400 and "nested multipart" in reply["error"], reply
    assert daemon.config.read_bytes() == before
    assert not list(daemon.folder.glob("calibration-*"))


def test_malformed_requests_get_a_clear_error_not_a_500(daemon: WebDaemon) -> None:
    """A body nested beyond json's depth raised RecursionError (500, a traceback in the log);
    a token header of bytes that are not UTF-8 failed to encode (500)."""
    before = daemon.config.read_bytes()
    status, reply = daemon.request("POST", "/api/settings", b"[" * 30_000 + b"]" * 30_000,
                                   token=True, headers={"Content-Type": "application/json"})
    assert status == 400 and "not JSON" in reply["error"]
    assert daemon.config.read_bytes() == before
    assert token_ok("secret", "\udcff\udcfe") is False  # how aiohttp hands such bytes over
    assert token_ok("secret", "secret") and not token_ok("secret", None)


def test_a_chunked_upload_is_bounded_too(daemon: WebDaemon) -> None:
    """A chunked upload states no length: aiohttp 3.8 (Debian bookworm's, what the BlueOS
    image runs) then let the whole part through, 1.5 GB to memory and disk. Counted as it
    comes, it is refused past web.max_upload_kb like any other."""
    boundary = "netposeboundary"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; "
            f"filename=\"camera.yaml\"\r\n\r\n").encode()

    def body() -> Iterator[bytes]:
        yield head
        for _ in range(64):  # 4 MB in 64 KB chunks, against a 64 KB limit
            yield b"#" * (64 * 1024)
        yield f"\r\n--{boundary}--\r\n".encode()

    before = daemon.config.read_bytes()
    status, reply = daemon.request(
        "POST", "/api/calibration", cast(bytes, body()), token=True,
        headers={"Content-Type": f"multipart/form-data; boundary={boundary}",
                 "Transfer-Encoding": "chunked"})
    assert status == 413 and "64 KB" in reply["error"], (status, reply)
    assert daemon.config.read_bytes() == before
    assert not list(daemon.folder.glob("calibration-*"))


def test_bad_calibration_gets_a_clear_error_and_changes_nothing(daemon: WebDaemon) -> None:
    before = daemon.config.read_bytes()
    status, reply = _upload(daemon, "camera.yaml", b"image_width: 640\nimage_height: [\n")
    assert status == 400 and reply["error"].startswith("camera.calibration: camera.yaml:")
    status, reply = _upload(daemon, "notes.txt", b"hello")
    assert status == 400 and ".yaml" in reply["error"]
    wrong_aspect = (b"image_width: 640\nimage_height: 640\ncamera_matrix: {rows: 3, cols: 3, "
                    b"data: [500, 0, 320, 0, 500, 320, 0, 0, 1]}\ndistortion_coefficients: "
                    b"{rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}\n")
    status, reply = _upload(daemon, "square.yaml", wrong_aspect)
    assert status == 400 and "aspect ratio" in reply["error"]
    assert daemon.config.read_bytes() == before


def test_good_calibration_is_previewed_undistorted(daemon: WebDaemon) -> None:
    good = (b"image_width: 1280\nimage_height: 720\ncamera_matrix: {rows: 3, cols: 3, "
            b"data: [736, 0, 639.5, 0, 736, 359.5, 0, 0, 1]}\ndistortion_coefficients: "
            b"{rows: 1, cols: 5, data: [-0.3, 0.1, 0, 0, 0]}\n")
    status, reply = _upload(daemon, "camera.yaml", good)
    assert status == 200, reply
    assert "1280x720" in reply["summary"] and "k1 -0.300" in reply["summary"]
    status, jpeg = daemon.request("GET", "/" + reply["preview"])
    assert status == 200 and jpeg[:3] == b"\xff\xd8\xff"


# -- live data ------------------------------------------------------------------------------------
def test_live_data_is_pushed_at_the_configured_rates(daemon: WebDaemon) -> None:
    texts, frames = daemon.collect(6.0)
    kinds = [t["kind"] for t in texts]
    assert kinds[:2] == ["hello", "history"]
    estimates = [t for t in texts if t["kind"] == "estimate"]
    statuses = [t for t in texts if t["kind"] == "status"]
    # push_hz 10 and live_hz 4 are upper bounds; the demo renders ~5-25 frames/s here.
    assert 6 <= len(estimates) <= 6 * 10 + 2, len(estimates)
    assert 2 <= len(frames) <= 6 * 4 + 2, len(frames)
    assert len(statuses) >= 4
    assert all(f[:3] == b"\xff\xd8\xff" for _, f in frames)
    seqs = [e["seq"] for e in estimates]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert {"filtered", "latency_ms", "truth"} <= set(estimates[-1])  # the telemetry payload


def _stalled_client(daemon: WebDaemon) -> socket.socket:
    """A WebSocket client that completes the handshake and then never reads."""
    s = socket.create_connection(("127.0.0.1", daemon.port))
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.sendall((f"GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{daemon.port}\r\nUpgrade: websocket\r\n"
               "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
               "Sec-WebSocket-Version: 13\r\n\r\n").encode())
    assert b" 101 " in s.recv(1024)
    return s


def test_a_stalled_page_holds_up_neither_the_daemon_nor_other_pages(daemon: WebDaemon) -> None:
    def median_fps(texts: list[dict[str, Any]]) -> float:
        return statistics.median(t["estimator"]["fps"] for t in texts if t["kind"] == "status")

    texts, frames_before = daemon.collect(8.0)
    fps_before = median_fps(texts)
    stalled = [_stalled_client(daemon) for _ in range(3)]
    try:
        texts, frames = daemon.collect(8.0)
    finally:
        for s in stalled:
            s.close()
    estimates = [t for t in texts if t["kind"] == "estimate"]
    # The loop keeps its pace (the shared cores are noisy: half of it at worst) and the page
    # that reads gets its data: every live frame of 8 s at 4 per second, estimates at ~10.
    assert median_fps(texts) >= 0.5 * fps_before, (fps_before, median_fps(texts))
    assert len(frames) >= 0.75 * min(32, len(frames_before)), (len(frames_before), len(frames))
    assert len(estimates) >= 30


# -- settings -------------------------------------------------------------------------------------
def test_a_bad_setting_names_the_key_and_changes_nothing(daemon: WebDaemon) -> None:
    before = daemon.config.read_bytes()
    cases = {
        "mesh.bar_length_m": ("wide", "configuration error: mesh.bar_length_m: must be a number"),
        "mavlink.url": ("serial", "configuration error: mavlink.url: 'serial' is not"),
        "mesh.colour": ("red", "configuration error: mesh.colour: is not one of the "
                               "settings the page changes"),
        "web.token": ("", "configuration error: web.token: [web] is changed in the "
                          "configuration file only"),
        # Valid as settings, refused by the parts a restart builds from them: saved, they
        # would stop the service on the restart the page then offers.
        "camera.url": ("synthetic:?foo=1", "configuration error: camera.url: "),
        "camera.calibration": (str(daemon.folder / "absent.yaml"),
                               "configuration error: camera.calibration: "),
    }
    for key, (value, error) in cases.items():
        status, reply = daemon.request("POST", "/api/settings", {"changes": {key: value}},
                                       token=True)
        assert status == 400 and reply["error"].startswith(error), reply
    # Text that is no text: JSON's lone surrogates (a 500 and a traceback in the log before).
    for changes in ({"service.\ud800": 1}, {"camera.url": "rtsp://\udcff"},
                    {"telemetry.connect": ["tcp/\ud800:7447"]},
                    {"telemetry.connect": [["tcp/\ud800:7447"]]}):
        status, reply = daemon.request("POST", "/api/settings", {"changes": changes},
                                       token=True)
        assert status == 400 and "not valid text" in reply["error"], reply
    # Two changes, one bad: neither is applied.
    status, reply = daemon.request("POST", "/api/settings", {"changes": {
        "mesh.opening_angle_deg": 80.0, "mesh.bar_length_m": -1}}, token=True)
    assert status == 400 and "mesh.bar_length_m" in reply["error"]
    assert daemon.config.read_bytes() == before
    assert not list(daemon.folder.glob(".*.new"))


def test_a_changed_endpoint_needs_a_restart_which_the_page_does(daemon: WebDaemon) -> None:
    new_url = f"udpout:127.0.0.1:{daemon.port + 1}"
    status, reply = daemon.request("POST", "/api/settings",
                                   {"changes": {"mavlink.url": new_url}}, token=True)
    assert status == 200 and reply["restart_needed"] == ["mavlink"], reply
    assert f'url = "{new_url}"' in daemon.config.read_text()
    status, settings = daemon.request("GET", "/api/settings")
    assert settings["restart_pending"] == ["mavlink"]
    texts, _ = daemon.collect(2.0)
    assert [t for t in texts if t["kind"] == "status"][-1]["autopilot"]["url"] != new_url
    status, _ = daemon.request("POST", "/api/restart", {}, token=True)
    assert status == 200
    deadline = time.monotonic() + 60.0
    while True:  # the page goes away and comes back with the restarted parts
        time.sleep(1.0)
        try:
            texts, _ = daemon.collect(2.5)
        except OSError:
            texts = []
        urls = [t["autopilot"]["url"] for t in texts if t["kind"] == "status"]
        if urls and urls[-1] == new_url:
            break
        assert time.monotonic() < deadline, daemon.log()
    assert daemon.proc is not None and daemon.proc.poll() is None
    assert daemon.request("GET", "/api/settings")[1]["restart_pending"] == []
    assert "restarting with the saved configuration" in daemon.log()


def test_a_change_needing_a_restart_that_is_undone_needs_none(daemon: WebDaemon) -> None:
    """The endpoint changed and changed back: the running link is the file's again, yet the
    page went on saying "restart needed" for it, after every later save too."""
    old_url = daemon.request("GET", "/api/settings")[1]["values"]["mavlink.url"]
    other_url = f"udpout:127.0.0.1:{daemon.port + 2}"
    assert other_url != old_url
    status, reply = daemon.request("POST", "/api/settings",
                                   {"changes": {"mavlink.url": other_url}}, token=True)
    assert status == 200 and reply["restart_needed"] == ["mavlink"], reply
    status, reply = daemon.request("POST", "/api/settings",
                                   {"changes": {"mavlink.url": old_url}}, token=True)
    assert status == 200 and reply["restart_needed"] == [], reply
    assert daemon.request("GET", "/api/settings")[1]["restart_pending"] == []
    status, reply = daemon.request("POST", "/api/settings",
                                   {"changes": {"mesh.bar_length_m": 0.026}}, token=True)
    assert status == 200 and reply["restart_needed"] == [], reply


def test_nothing_is_changed_from_the_page_while_the_vehicle_is_armed(tmp_path: Path) -> None:
    """With no token (BlueOS's default) one request from anyone on the vehicle's network
    doubled the distance the autopilot steered by (mesh.bar_length_m), swapped the camera or
    redirected the link mid-dive. While the autopilot says it is armed, settings, calibration
    and restarts from the page are refused (409, the reason said) and the file is untouched;
    disarmed, the same change is taken, and the log says who changed what from what."""
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        autopilot.armed = True
        d = WebDaemon(tmp_path, token="", sections={"mavlink": {"url": autopilot.url}})
        d.start()
        try:
            autopilot.wait_for("DISTANCE_SENSOR", count=3, timeout=30.0)
            deadline = time.monotonic() + 10.0
            while not d.request("GET", "/api/settings")[1]["reason"].startswith("the vehicle "
                                                                                "is armed"):
                assert time.monotonic() < deadline, d.log()
                time.sleep(0.2)
            before = d.config.read_bytes()
            status, reply = d.request("POST", "/api/settings",
                                      {"changes": {"mesh.bar_length_m": 0.05}})
            assert status == 409 and "armed" in reply["error"], reply
            status, reply = d.request("POST", "/api/restart", {})
            assert status == 409 and "armed" in reply["error"], reply
            assert d.config.read_bytes() == before
            before_cm = statistics.median(
                r.msg.current_distance for r in autopilot.received("DISTANCE_SENSOR")[-5:])
            autopilot.clear()
            # Still sending, at the scale it had (the demo's net moves slowly: not double).
            after = autopilot.wait_for("DISTANCE_SENSOR", count=5)
            after_cm = statistics.median(r.msg.current_distance for r in after)
            assert abs(after_cm / before_cm - 1.0) < 0.2, (before_cm, after_cm)

            # The heartbeat lost (a tether glitch) is not a disarmed vehicle: still locked.
            autopilot.heartbeats_enabled = False
            deadline = time.monotonic() + 10.0
            while "autopilot heartbeat lost" not in d.log():
                assert time.monotonic() < deadline, d.log()
                time.sleep(0.2)
            status, reply = d.request("POST", "/api/settings",
                                      {"changes": {"mesh.bar_length_m": 0.25}})
            assert status == 409 and "armed" in reply["error"], reply
            assert d.config.read_bytes() == before
            autopilot.heartbeats_enabled = True

            autopilot.armed = False
            deadline = time.monotonic() + 10.0
            while not d.request("GET", "/api/settings")[1]["editable"]:
                assert time.monotonic() < deadline, d.log()
                time.sleep(0.2)
            status, reply = d.request("POST", "/api/settings",
                                      {"changes": {"mesh.bar_length_m": 0.026}},
                                      headers={"X-Forwarded-For": "192.168.2.1"})
            assert status == 200 and reply["saved"], reply
        finally:
            assert d.stop() == 0, d.log()
    assert re.search(r"configuration changed from the web page by 127\.0\.0\.1 \(for "
                     r"'192\.168\.2\.1'\): mesh\.bar_length_m 0\.025 -> 0\.026", d.log()), d.log()


def test_a_stop_during_a_restart_ends_the_service(tmp_path: Path) -> None:
    """`systemctl stop` while the page's restart is closing the old parts: the process ends
    (a stop is final), it does not come back with new parts and go on sending distances."""
    d = WebDaemon(tmp_path).start()
    assert d.proc is not None
    try:
        status, _ = d.request("POST", "/api/restart", {}, token=True)
        assert status == 200
        d.proc.send_signal(signal.SIGTERM)
        try:
            code = d.proc.wait(timeout=30.0)
        except subprocess.TimeoutExpired:
            raise AssertionError("still running 30 s after SIGTERM:\n" + d.log()) from None
    finally:
        if d.proc.poll() is None:
            d.proc.kill()
            d.proc.wait()
    assert code == 0, d.log()
    assert "SIGTERM received: stopping" in d.log()


# -- recordings -----------------------------------------------------------------------------------
def _number(text: str) -> float | None:
    return float(text) if text else None


def test_a_recording_the_daemon_never_finished_is_listed_and_downloads(tmp_path: Path) -> None:
    """The power went (SIGKILL here) mid-recording. After the restart the page listed the
    recording as 0 frames, 0 bytes, unfinished, and hid it: no download of the dive that
    mattered most. It is listed as interrupted with what it holds, and downloads."""
    d = WebDaemon(tmp_path).start()
    assert d.proc is not None
    try:
        assert d.request("POST", "/api/recordings/start", {}, token=True)[0] == 200
        time.sleep(4.0)
        d.proc.kill()
        d.proc.wait()
        d.start()
        listing = d.request("GET", "/api/recordings")[1]["recordings"]
    finally:
        d.stop()
    assert len(listing) == 1 and not listing[0]["finished"] and listing[0]["interrupted"]
    name = listing[0]["name"]
    lines = (tmp_path / "recordings" / name / "frames.jsonl").read_text().splitlines()
    assert listing[0]["frames"] == len(lines) >= 10 and listing[0]["bytes"] > 0
    d.start()
    try:
        status, tar_bytes = d.request("GET", f"/api/recordings/{name}.tar")
    finally:
        d.stop()
    assert status == 200 and len(tar_bytes) > listing[0]["bytes"] // 2


def test_a_recording_downloads_and_replays_to_the_daemons_output(
        daemon: WebDaemon, tmp_path: Path) -> None:
    status, started = daemon.request("POST", "/api/recordings/start", {}, token=True)
    assert status == 200 and started["active"], started
    status, again = daemon.request("POST", "/api/recordings/start", {}, token=True)
    assert status == 409 and "already recording" in again["error"]
    time.sleep(6.0)
    status, stopped = daemon.request("POST", "/api/recordings/stop", {}, token=True)
    assert status == 200 and not stopped["active"] and stopped["frames"] >= 10, stopped
    name = stopped["name"]
    listing = daemon.request("GET", "/api/recordings")[1]["recordings"]
    assert listing[0]["name"] == name and listing[0]["finished"]

    status, tar_bytes = daemon.request("GET", f"/api/recordings/{name}.tar")
    assert status == 200
    with tarfile.open(fileobj=io.BytesIO(tar_bytes)) as tar:
        tar.extractall(tmp_path, filter="data")
    folder = tmp_path / name
    rows = [json.loads(line) for line in (folder / "frames.jsonl").read_text().splitlines()]
    assert len(rows) == stopped["frames"] and stopped["dropped"] == 0
    # The recording names the configuration (the digest its log and status carry) and the
    # source it was made from: a recording is joined to the dive's telemetry by them.
    manifest = json.loads((folder / "recording.json").read_text())
    statuses = [m for m in daemon.collect(2.5)[0] if m.get("kind") == "status"]
    assert statuses and manifest["config_digest"] == statuses[-1]["config_digest"], manifest
    assert manifest["source"].startswith("synthetic:"), manifest
    out = tmp_path / "replay"
    done = subprocess.run([sys.executable, "-m", "service.cli", "replay", str(folder), "--out",
                           str(out), "--filter", "--no-video", "--progress", "off"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    with (out / "estimates.csv").open() as f:
        replayed = list(csv.DictReader(f))
    assert [int(r["frame"]) for r in replayed] == [row["index"] for row in rows]
    worst = 0.0
    for row, rep in zip(rows, replayed, strict=True):
        daemon_est = row["estimate"]
        filtered = daemon_est["filtered"]
        assert rep["filter_state"] == filtered["state"]
        assert (rep["filter_valid"] == "1") == filtered["valid"]
        sent = filtered["distance_m"] if filtered["valid"] else None  # the CSV's, too
        for theirs, ours in ((daemon_est["distance_m"], _number(rep["distance_m"])),
                             (sent, _number(rep["filtered_distance_m"]))):
            assert (theirs is None) == (ours is None)
            if theirs is not None and ours is not None:
                worst = max(worst, abs(theirs - ours))
    # The daemon's messages carry 6 decimals: equal to that rounding.
    assert worst <= 1e-6 + 1e-12, worst
    assert math.isclose(float(rows[1]["t_mono"]) - float(rows[0]["t_mono"]),
                        float(replayed[1]["time_s"]) - float(replayed[0]["time_s"]),
                        abs_tol=2e-6)


# -- set-up mode ----------------------------------------------------------------------------------
def _use_the_synthetic_camera(d: WebDaemon, tmp_path: Path) -> None:
    """Upload the camera the synthetic source renders with, as a calibration file, and use it."""
    path = tmp_path / "upload.yaml"
    save_camera(builtin_camera(1280, 720), path)
    status, reply = _upload(d, "camera.yaml", path.read_bytes())
    assert status == 200, reply
    status, reply = d.request("POST", f"/api/calibration/{reply['id']}/apply", {}, token=True)
    assert status == 200 and reply["saved"], reply


def test_a_first_start_without_mesh_size_or_calibration_is_set_up_on_the_page(
    tmp_path: Path,
) -> None:
    """config/blueos.toml as shipped: neither the mesh size (no default) nor a calibration.
    The service must not exit (the container engine would restart it forever, with no page);
    set-up mode serves the page, which saves the two one at a time, and the daemon starts."""
    d = WebDaemon(tmp_path, sections={"camera": {"calibration": "camera.yaml"}})
    text = d.config.read_text()
    d.config.write_text("\n".join(line for line in text.splitlines()
                                  if not line.startswith("bar_length_m")) + "\n")
    d.start()
    try:
        _, settings = d.request("GET", "/api/settings")
        assert settings["problem"].startswith("configuration error: "), settings
        assert settings["values"]["mesh.bar_length_m"] is None  # shown unset, not a stand-in
        status, reply = d.request("POST", "/api/settings",
                                  {"changes": {"mesh.bar_length_m": 0.025}}, token=True)
        assert status == 200 and reply["saved"], reply  # saved while the calibration lacks
        assert "bar_length_m = 0.025" in d.config.read_text()
        assert "set-up mode" in d.log() and "leaving set-up mode" not in d.log()
        _use_the_synthetic_camera(d, tmp_path)
        deadline = time.monotonic() + 60.0
        while "leaving set-up mode" not in d.log():
            assert time.monotonic() < deadline, d.log()
            time.sleep(0.5)
        texts: list[dict[str, Any]] = []
        while not any(t["kind"] == "estimate" and t["detected"] for t in texts):
            assert time.monotonic() < deadline, d.log()
            try:
                texts, _ = d.collect(2.0)
            except OSError:
                texts = []
    finally:
        assert d.stop() == 0, d.log()


def test_set_up_says_why_the_camera_shows_nothing_and_takes_a_calibration_anyway(
    tmp_path: Path,
) -> None:
    """A stock BlueOS streams its camera over UDP, with no RTSP endpoint: the page in set-up
    mode said only "no status from the daemon yet" and asked for the calibration, whose upload
    was then refused ("no camera frame yet"), so set-up could not be finished from the page.
    The page now says what the camera does, and takes the calibration unchecked."""
    from drivers.net import free_port

    nothing_there = f"rtsp://127.0.0.1:{free_port()}/video_stream__dev_video2"
    d = WebDaemon(tmp_path, sections={"camera": {"calibration": "camera.yaml",
                                                 "url": nothing_there}}).start(frames=False)
    try:
        deadline = time.monotonic() + 20.0
        while True:
            _, settings = d.request("GET", "/api/settings")
            if "check camera.url" in settings["problem"]:
                break
            assert time.monotonic() < deadline, settings
            time.sleep(0.2)
        assert settings["problem"].startswith("configuration error: camera.calibration")
        path = tmp_path / "upload.yaml"
        save_camera(builtin_camera(1280, 720), path)
        status, reply = _upload(d, "camera.yaml", path.read_bytes())
        assert status == 200 and reply["checked"] is False, reply
        assert "not checked against the camera" in reply["summary"]
        status, preview = d.request("GET", "/" + reply["preview"])
        assert status == 200 and preview[:2] == b"\xff\xd8"  # a JPEG card, not an error
        status, applied = d.request("POST", f"/api/calibration/{reply['id']}/apply", {},
                                    token=True)
        assert status == 200 and applied["saved"], applied
        deadline = time.monotonic() + 30.0
        while "leaving set-up mode" not in d.log():
            assert time.monotonic() < deadline, d.log()
            time.sleep(0.2)
        # Set-up's camera note ends with it (the daemon's status says what the camera does).
        while True:  # the daemon's own page takes over from set-up's
            try:
                _, settings = d.request("GET", "/api/settings")
                break
            except OSError:
                assert time.monotonic() < deadline, d.log()
                time.sleep(0.2)
        assert "check camera.url" not in settings["problem"], settings["problem"]
    finally:
        assert d.stop() == 0, d.log()


def test_a_reload_in_set_up_mode_names_what_is_still_wrong_in_the_log(tmp_path: Path) -> None:
    """An operator who fixes the file over SSH and runs `systemctl reload` in set-up mode must
    read in the journal what is still wrong, as after any other reload: the rejected key was
    only on the page and in the unit's status line."""
    d = WebDaemon(tmp_path, sections={"camera": {"calibration": "camera.yaml"}}).start()
    try:
        assert d.proc is not None and "set-up mode" in d.log()
        d.config.write_text(d.config.read_text() + "\n[estimator]\nbogus_key = 1\n")
        d.proc.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 20.0
        while "bogus_key" not in d.log():
            assert time.monotonic() < deadline, d.log()
            time.sleep(0.2)
        line = next(line for line in d.log().splitlines() if "bogus_key" in line)
        assert "set-up mode" in line and "reload" in line, line
    finally:
        assert d.stop() == 0, d.log()


def test_restart_in_set_up_mode_comes_back_in_set_up_mode(tmp_path: Path) -> None:
    """The page's Restart in set-up mode ended the process with status 0: under systemd's
    Restart=on-failure the service then stayed down, with no page to finish the set-up on.
    It sets up again from the saved file, in the same process."""
    d = WebDaemon(tmp_path, sections={"camera": {"calibration": "camera.yaml"}}).start()
    try:
        assert d.proc is not None and "set-up mode" in d.log()
        status, _ = d.request("POST", "/api/restart", {}, token=True)
        assert status == 200
        deadline = time.monotonic() + 30.0
        while "restarting with the saved configuration" not in d.log():
            assert d.proc.poll() is None, d.log()
            assert time.monotonic() < deadline, d.log()
            time.sleep(0.2)
        while True:  # the page comes back, still setting up
            assert d.proc.poll() is None, d.log()
            assert time.monotonic() < deadline, d.log()
            try:
                status, settings = d.request("GET", "/api/settings", timeout_s=2.0)
            except OSError:
                time.sleep(0.3)
                continue
            if status == 200:
                break
        assert settings["problem"].startswith("configuration error: "), settings
        assert d.log().count("set-up mode, nothing is sent") == 2
    finally:
        assert d.stop() == 0, d.log()


def test_any_configuration_error_serves_the_page_that_names_and_fixes_it(
    tmp_path: Path,
) -> None:
    """A mistyped MAVLink URL in the file of a vehicle with the page on: `run` exited 78 and
    the container engine restarted it for ever, with no page to say why (BlueOS review). Now
    set-up mode serves the page, naming the key; nothing reaches the autopilot; the page's
    settings fix it and the daemon starts, sending to the fixed URL."""
    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    autopilot.bind(("127.0.0.1", 0))
    autopilot.settimeout(3.0)
    url = f"udpout:127.0.0.1:{autopilot.getsockname()[1]}"
    d = WebDaemon(tmp_path, sections={"mavlink": {"url": url.replace(":", "//", 1)}})
    try:
        d.start()
        assert d.proc is not None and d.proc.poll() is None
        _, settings = d.request("GET", "/api/settings")
        assert settings["problem"].startswith("configuration error: mavlink.url"), settings
        assert "set-up mode, nothing is sent" in d.log() and "mavlink.url" in d.log()
        texts, frames = d.collect(3.0)  # the camera is shown, with the problem
        reasons = {t["reason"] for t in texts if t["kind"] == "estimate"}
        assert frames and reasons and all(r.startswith("set-up mode: configuration error: "
                                                       "mavlink.url") for r in reasons)
        with pytest.raises(TimeoutError):
            autopilot.recv(1024)
        # The form shows what the file has (the broken key at its default), typed: it came up
        # blank and all text, and the group's Save was refused field by field.
        values = settings["values"]
        assert values["mavlink.sensor_id"] is not None and values["telemetry.vehicle"]
        kinds = {f["key"]: f["type"] for g in settings["groups"] for f in g["fields"]}
        assert kinds["mavlink.orientation"] != "text", kinds
        # Another setting cannot be saved past the error: the page says which key is wrong.
        status, reply = d.request("POST", "/api/settings",
                                  {"changes": {"mavlink.sensor_id": 3}}, token=True)
        assert status == 400 and "mavlink.url" in reply["error"], reply
        # The whole group as the page's Save sends it, the URL fixed.
        group = next(g for g in settings["groups"] if g["title"].startswith("Autopilot"))
        changes = {f["key"]: values[f["key"]] for f in group["fields"]}
        changes["mavlink.url"] = url
        status, reply = d.request("POST", "/api/settings", {"changes": changes}, token=True)
        assert status == 200 and reply["saved"], reply
        deadline = time.monotonic() + 60.0
        while "leaving set-up mode" not in d.log():
            assert time.monotonic() < deadline, d.log()
            time.sleep(0.3)
        assert autopilot.recv(1024)[:1] in (b"\xfd", b"\xfe")  # the daemon proper's MAVLink
    finally:
        autopilot.close()
        assert d.stop() == 0, d.log()


def test_a_camera_url_the_page_cannot_open_is_set_up_with_the_reason(tmp_path: Path) -> None:
    """camera.url itself wrong (a scheme no source knows) and a key no section has: the page
    comes up all the same, saying both what the file has wrong and why the view is dark."""
    d = WebDaemon(tmp_path, sections={"camera": {"url": "vl42:/dev/video0"},
                                      "telemetry": {"vehicel": "rov1"}})
    try:
        d.start(frames=False)
        assert d.proc is not None
        deadline = time.monotonic() + 20.0
        while True:
            _, settings = d.request("GET", "/api/settings")
            if "check camera.url" in settings["problem"]:
                break
            assert d.proc.poll() is None, d.log()
            assert time.monotonic() < deadline, settings
            time.sleep(0.2)
        assert settings["problem"].startswith("configuration error: telemetry.vehicel")
        assert "vl42" in settings["problem"], settings["problem"]
    finally:
        assert d.stop() == 0, d.log()


def test_without_a_calibration_the_page_sets_up_and_nothing_is_sent(tmp_path: Path) -> None:
    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    autopilot.bind(("127.0.0.1", 0))
    autopilot.settimeout(3.0)
    url = f"udpout:127.0.0.1:{autopilot.getsockname()[1]}"
    d = WebDaemon(tmp_path, sections={"camera": {"calibration": "camera.yaml"},
                                      "mavlink": {"url": url}}).start()
    try:
        _, settings = d.request("GET", "/api/settings")
        assert settings["problem"].startswith(
            "configuration error: camera.calibration: file not found"), settings
        texts, frames = d.collect(4.0)
        reasons = {t["reason"] for t in texts if t["kind"] == "estimate"}
        assert frames and reasons and all(r.startswith("set-up mode:") for r in reasons)
        with pytest.raises(TimeoutError):
            autopilot.recv(1024)  # no link at all in set-up mode
        _use_the_synthetic_camera(d, tmp_path)
        deadline = time.monotonic() + 60.0
        while True:  # the daemon proper starts: estimates with the net, MAVLink to the autopilot
            time.sleep(1.0)
            try:
                texts, _ = d.collect(2.0)
            except OSError:
                texts = []
            if any(t["kind"] == "estimate" and t["detected"] for t in texts):
                break
            assert time.monotonic() < deadline, d.log()
        assert autopilot.recv(1024)[:1] in (b"\xfd", b"\xfe")  # a MAVLink frame
        assert "leaving set-up mode" in d.log()
    finally:
        autopilot.close()
        assert d.stop() == 0, d.log()


def test_a_recording_being_finished_is_neither_deletable_nor_listed_as_interrupted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A recording a reload rolled over is finished on a thread of its own (its writer drains
    to the card): it was listed as interrupted, with a Delete button, and a delete then made
    its finish fail ("cannot finish the recording's manifest")."""
    from drivers.recorder import Recorder, RecorderError, RecordingSetup, _Session
    from drivers.sources.synthetic import builtin_camera

    release = threading.Event()
    real_close = _Session.close

    def slow_close(self: Any, *args: Any, **kwargs: Any) -> Any:
        release.wait(10.0)  # a slow card
        return real_close(self, *args, **kwargs)

    monkeypatch.setattr(_Session, "close", slow_close)
    recorder = Recorder(tmp_path, "rov", lambda: RecordingSetup(builtin_camera(640, 360), "",
                                                                 0.025, 90.0), 1 << 30)
    first = recorder.begin().name
    time.sleep(1.1)  # the next one gets another name (one-second stamps)
    recorder.observe_reload(frozenset({"filter"}))  # `first` is finished on its own thread
    listed = {r["name"]: r for r in recorder.recordings()}
    assert not listed[first]["interrupted"] and not listed[first]["finished"]
    with pytest.raises(RecorderError, match="being finished"):
        recorder.delete(first)
    release.set()
    recorder.stop()
    assert {r["name"]: r for r in recorder.recordings()}[first]["finished"]
    assert recorder.delete(first) > 0 and not (tmp_path / first).exists()
