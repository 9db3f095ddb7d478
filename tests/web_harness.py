"""The real daemon (`netpose run`) with its web page on, on the demo's synthetic source.

The configuration is the demo's, written to a temporary folder with a [web] section (a file the
page may change, not --set overrides, which it must not), with every port chosen at runtime on
loopback: the page, Zenoh (peer, listening) and MAVLink (udpout to a port nobody reads).
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import aiohttp
import tomlkit

from drivers.net import free_port

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "config" / "demo.toml"
TOKEN = "correct-horse-battery"


def demo_config(path: Path, web: Mapping[str, Any], **sections: Mapping[str, Any]) -> Path:
    doc = tomlkit.parse(DEMO.read_text(encoding="utf-8"))
    doc["telemetry"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    doc["mavlink"]["url"] = f"udpout:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
    for name, values in sections.items():
        for key, value in values.items():
            doc[name][key] = value
    for key, value in web.items():
        doc["web"][key] = value
    path.write_text(tomlkit.dumps(doc), encoding="utf-8")
    return path


class PageClient:
    """HTTP and WebSocket requests to a netpose page on loopback."""

    def __init__(self, port: int, token: str = "") -> None:
        self.port = port
        self.token = token

    @property
    def base(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def request(self, method: str, path: str, body: bytes | dict[str, Any] | None = None,
                headers: Mapping[str, str] | None = None, token: bool = False,
                timeout_s: float = 30.0) -> tuple[int, Any]:
        data = json.dumps(body).encode() if isinstance(body, dict) else body
        all_headers = dict(headers or {})
        if isinstance(body, dict):
            all_headers.setdefault("Content-Type", "application/json")
        if token:
            all_headers["X-Netpose-Token"] = self.token
        req = urllib.request.Request(self.base + path, data=data, method=method,
                                     headers=all_headers)
        try:
            with urllib.request.urlopen(req, timeout=timeout_s) as response:
                status, raw = response.status, response.read()
                kind = response.headers.get_content_type()
        except urllib.error.HTTPError as exc:
            status, raw, kind = exc.code, exc.read(), exc.headers.get_content_type()
        return status, json.loads(raw) if kind == "application/json" else raw

    def collect(self, seconds: float, origin: str | None = None
                ) -> tuple[list[dict[str, Any]], list[tuple[float, bytes]]]:
        """What the live WebSocket sends for `seconds`: JSON messages, and (arrival, JPEG).
        A page that went away meanwhile (a restart) is a ConnectionError, as urllib's is: a
        server that dropped the connection mid-handshake raised aiohttp's own error, which is
        not an OSError, and failed the tests that wait for the page to come back."""
        import aiohttp

        try:
            return asyncio.run(_collect(self.base.replace("http", "ws") + "/ws", seconds,
                                        origin))
        except aiohttp.ClientConnectionError as exc:
            raise ConnectionError(f"the page dropped the connection: {exc!r}") from exc


class WebDaemon(PageClient):
    def __init__(self, folder: Path, token: str = TOKEN,
                 sections: Mapping[str, Mapping[str, Any]] | None = None, **web: Any) -> None:
        super().__init__(free_port(), token)
        self.folder = folder
        settings = {"enabled": True, "host": "127.0.0.1", "port": self.port, "token": token,
                    "max_upload_kb": 64, **web}
        self.config = demo_config(folder / "netpose.toml", settings, **(sections or {}))
        self.log_path = folder / "daemon.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = 60.0, frames: bool = True) -> WebDaemon:
        """Run the daemon; ready when the page answers and (`frames`) the first frame has
        reached it."""
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop("NOTIFY_SOCKET", None)
        with self.log_path.open("wb") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "service.cli", "run", "--config", str(self.config)],
                cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout_s
        while True:
            if self.proc.poll() is not None:
                raise AssertionError(f"daemon exited {self.proc.returncode}:\n{self.log()}")
            try:
                status, _ = self.request("GET", "/register_service")
                # Up when the page answers and the first frame has reached it.
                if status == 200 and (not frames or self.collect(1.5)[1]):
                    return self
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise AssertionError(f"page not answering within {timeout_s} s:\n{self.log()}")
            time.sleep(0.2)

    def stop(self) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    def log(self) -> str:
        return self.log_path.read_text(encoding="utf-8", errors="replace")


async def _collect(url: str, seconds: float, origin: str | None
                   ) -> tuple[list[dict[str, Any]], list[tuple[float, bytes]]]:
    texts: list[dict[str, Any]] = []
    frames: list[tuple[float, bytes]] = []
    headers = {"Origin": origin} if origin else {}
    async with aiohttp.ClientSession() as session, session.ws_connect(url, headers=headers) as ws:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = await ws.receive(timeout=left)
            except TimeoutError:
                break
            if msg.type == aiohttp.WSMsgType.TEXT:
                texts.append(json.loads(msg.data))
            elif msg.type == aiohttp.WSMsgType.BINARY:
                frames.append((time.monotonic(), msg.data))
            else:
                break
    return texts, frames
