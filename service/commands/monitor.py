"""`netpose monitor`: topside view of a vehicle's telemetry over Zenoh.

Subscribes to `<prefix>/<vehicle>/**`, shows live values, rates and link state (a full-screen
redraw on a terminal; one line per second when stdout is a file or pipe), can save the stream as
JSON lines, plot distance and confidence over time, or ask the vehicle's queryable once.
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import math
import queue
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import IO, Any

import numpy as np
import zenoh

from drivers.telemetry import (
    TelemetrySettings,
    build_zenoh_config,
    token_change,
    zenoh_error_text,
)
from service.core.backoff import Backoff
from service.core.errors import ConfigError, NetposeError
from service.core.files import write_atomically
from service.core.messages import ALIVE_SUFFIX, ESTIMATE_SUFFIX, STATE_SUFFIX
from service.signals import SignalFlags, handle_signals
from service.tools.monitor_view import MonitorState, Received, sigma_of

log = logging.getLogger(__name__)

REDRAW_S = 0.5  # terminal redraw and plot update period
LINE_S = 1.0  # one summary line per second when stdout is not a terminal
PLOT_HISTORY_S = 120.0
# Telemetry silent for longer than this is a gap in the plot, not a line across it.
PLOT_GAP_S = 1.0


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "monitor",
        help="topside view of a vehicle's telemetry (Zenoh)",
        description="Subscribe to netpose telemetry and show live values, rates and link state.",
    )
    p.add_argument("--connect", metavar="ENDPOINT", action="append", default=None,
                   help="Zenoh endpoint to connect to, e.g. tcp/192.168.2.2:7447 (repeatable; "
                   "default tcp/127.0.0.1:7447 unless --listen is given)")
    p.add_argument("--listen", metavar="ENDPOINT", action="append", default=None,
                   help="Zenoh endpoint to listen on (repeatable)")
    p.add_argument("--mode", choices=("client", "peer"), default=None,
                   help="Zenoh mode (default: client when connecting, peer when only listening)")
    p.add_argument("--scouting", action="store_true", help="enable multicast scouting")
    p.add_argument("--zenoh-config", metavar="FILE", default=None,
                   help="Zenoh configuration file (JSON5) to start from, e.g. for TLS")
    p.add_argument("--prefix", default="netpose", help="key-expression prefix (default netpose)")
    p.add_argument("--vehicle", default="*",
                   help="vehicle name to watch (default *: every vehicle)")
    p.add_argument("--stale-after", type=float, default=3.0, metavar="SECONDS",
                   help="link shown as stale after this long without data (default 3)")
    p.add_argument("--save", type=Path, metavar="FILE", default=None,
                   help="append every received message to FILE as JSON lines")
    p.add_argument("--save-preview", type=Path, metavar="FILE", default=None,
                   help="keep the latest preview JPEG in FILE")
    p.add_argument("--plot", action="store_true",
                   help="live plot of distance and confidence (matplotlib)")
    p.add_argument("--plot-png", type=Path, metavar="FILE", default=None,
                   help="draw the plot into a PNG file instead of a window (implies --plot)")
    p.add_argument("--duration", type=float, metavar="SECONDS", default=None,
                   help="stop after this many seconds (default: until Ctrl-C)")
    p.add_argument("--query", action="store_true",
                   help="ask the vehicle for its status and configuration once, print, exit")
    p.set_defaults(handler=run)


def _zenoh_config(args: argparse.Namespace) -> zenoh.Config:
    connect = args.connect
    if connect is None and args.listen is None and args.zenoh_config is None:
        connect = ["tcp/127.0.0.1:7447"]
    mode = args.mode
    if mode is None and args.zenoh_config is None:
        mode = "client" if connect else "peer"
    try:
        settings = TelemetrySettings(
            vehicle="monitor",
            mode=mode,
            listen=None if args.listen is None else tuple(args.listen),
            connect=None if connect is None else tuple(connect),
            scouting=True if args.scouting else (None if args.zenoh_config else False),
            config_file=args.zenoh_config,
        )
    except ConfigError as exc:  # name the option, not the daemon's TOML key
        raise ConfigError(_option_of(exc.key), exc.problem) from None
    try:
        return build_zenoh_config(settings)
    except ConfigError as exc:
        raise ConfigError(_option_of(exc.key), exc.problem) from None


def _option_of(key: str) -> str:
    """The monitor's option for a telemetry key (its Zenoh file is --zenoh-config)."""
    name = key.removeprefix("telemetry.")
    return "--zenoh-config" if name == "config_file" else "--" + name.replace("_", "-")


def _open_session(config: zenoh.Config, deadline: float, stop: threading.Event) -> zenoh.Session:
    """Open, retrying (a client fails while its router is away) until `deadline` or stop."""
    backoff = Backoff(initial_s=0.5, max_s=5.0)
    announced = False
    while True:
        try:
            return zenoh.open(config)
        except zenoh.ZError as exc:
            if not announced:
                print(f"monitor: no Zenoh link yet ({zenoh_error_text(exc)}); retrying",
                      file=sys.stderr, flush=True)
                announced = True
        delay = backoff.next_delay(time.monotonic())
        if time.monotonic() + delay > deadline or stop.wait(delay):
            raise NetposeError("no Zenoh link: is the vehicle (or its router) reachable?")


def run(args: argparse.Namespace) -> int:
    if args.duration is not None and not args.duration > 0:
        raise ConfigError("--duration", "must be a positive number of seconds")
    if not args.stale_after > 0:
        raise ConfigError("--stale-after", "must be a positive number of seconds")
    for chunk, option in ((args.prefix, "--prefix"), (args.vehicle, "--vehicle")):
        if not chunk or "/" in chunk or any(c in chunk for c in "?#$ "):
            raise ConfigError(option, f"{chunk!r} must be one key chunk (no '/')")
    png: Path | None = args.plot_png
    if png is not None and (png.is_dir() or not png.parent.is_dir()):
        # Said now, not at the first redraw after the link is up.
        raise ConfigError("--plot-png", f"{png}: not a file in an existing folder")
    config = _zenoh_config(args)
    start = time.monotonic()
    deadline = math.inf if args.duration is None else start + args.duration
    with handle_signals(SignalFlags()) as flags:
        stop = flags.stop
        session = _open_session(config, deadline, stop)
        try:
            if args.query:
                return _query_once(session, args)
            return _watch(session, args, deadline, stop)
        finally:
            session.close()


def _query_once(session: zenoh.Session, args: argparse.Namespace) -> int:
    """Print each vehicle's answer (status and configuration) as one JSON document per line."""
    selector = f"{args.prefix}/{args.vehicle}/{STATE_SUFFIX}"
    timeout = 5.0 if args.duration is None else args.duration
    answers = 0
    for reply in session.get(selector, timeout=timeout):
        sample = reply.ok
        if sample is None:
            error = reply.err
            print(f"monitor: error reply: {error.payload.to_string() if error else '?'}",
                  file=sys.stderr)
            continue
        print(sample.payload.to_string(), flush=True)
        answers += 1
    if answers == 0:
        print(f"monitor: nobody answered {selector} within {timeout:g} s", file=sys.stderr)
        return 1
    return 0


def _watch(
    session: zenoh.Session, args: argparse.Namespace, deadline: float, stop: threading.Event
) -> int:
    # Zenoh calls back on its own threads; hand samples to the main thread, which owns all
    # state, files and the screen. The callback does no more than copy bytes.
    inbox: queue.SimpleQueue[tuple[str, bytes, bytes | None, float, float]] = queue.SimpleQueue()

    def on_sample(sample: zenoh.Sample) -> None:
        attachment = sample.attachment
        inbox.put((
            str(sample.key_expr),
            sample.payload.to_bytes(),
            None if attachment is None else attachment.to_bytes(),
            time.monotonic(),
            time.time(),
        ))

    def on_token(sample: zenoh.Sample) -> None:
        # The daemon's liveliness token came or went: its sample kind stands in for the data.
        inbox.put((str(sample.key_expr), token_change(sample).encode(), None,
                   time.monotonic(), time.time()))

    key = f"{args.prefix}/{args.vehicle}/**"
    subscriber = session.declare_subscriber(key, on_sample)
    try:
        tokens: Any = session.liveliness().declare_subscriber(
            f"{args.prefix}/{args.vehicle}/{ALIVE_SUFFIX}", on_token, history=True)
    except AttributeError:  # zenoh 1.0.0 has no liveliness: stopped/gone is not told
        tokens = None
    state = MonitorState(stale_after_s=args.stale_after)
    tty = sys.stdout.isatty()
    plot = LivePlot(args.plot_png) if (args.plot or args.plot_png) else None
    save: IO[str] | None = None
    try:
        if args.save is not None:
            try:
                save = args.save.open("a", encoding="utf-8")
            except OSError as exc:
                raise NetposeError(f"cannot write {args.save}: {exc}") from exc
        print(f"monitor: watching {key}", file=sys.stderr, flush=True)
        next_draw = next_line = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            if now >= deadline:
                break
            timeout = max(0.0, min(next_draw, next_line, deadline) - now)
            try:
                item = inbox.get(timeout=min(timeout, 0.1))
            except queue.Empty:
                item = None
            while item is not None:
                _handle(state, item, save, plot, args.save_preview)
                try:
                    item = inbox.get_nowait()
                except queue.Empty:
                    item = None
            now = time.monotonic()
            if tty and now >= next_draw:
                sys.stdout.write("\x1b[H\x1b[2J" + "\n".join(state.render(now)) + "\n")
                sys.stdout.flush()
            if not tty and now >= next_line:
                print(time.strftime("%H:%M:%S ") + state.summary(now), flush=True)
                next_line += LINE_S
            if now >= next_draw:
                if plot is not None:
                    plot.update()
                next_draw = now + REDRAW_S
    finally:
        if tokens is not None:
            tokens.undeclare()
        subscriber.undeclare()
        if save is not None:
            save.close()
        if plot is not None:
            plot.close()
    return 0


def _handle(
    state: MonitorState,
    item: tuple[str, bytes, bytes | None, float, float],
    save: IO[str] | None,
    plot: LivePlot | None,
    preview_path: Path | None,
) -> None:
    key, data, attachment, recv_mono, recv_unix = item
    received = state.ingest(key, data, recv_mono, attachment)
    if received is None:
        return
    if save is not None:
        save.write(json.dumps(received.record(recv_unix), separators=(",", ":")) + "\n")
        save.flush()  # a monitor killed by the pilot keeps everything it showed
    if plot is not None and received.kind == ESTIMATE_SUFFIX and received.payload is not None:
        plot.add(recv_mono, received)
    if preview_path is not None and received.kind == "preview":
        _write_preview(preview_path, data)


def _write_preview(path: Path, data: bytes) -> None:
    try:
        write_atomically(path, data, durable=False)  # a viewer's picture, not a record
    except OSError as exc:
        log.warning("cannot write preview %s: %s", path, exc)


class LivePlot:
    """Distance (raw, filtered, +/- 1 sigma) and confidence against time, last two minutes.

    With a PNG path the figure is drawn off-screen (Agg) into that file at every update, so it
    works without a display; otherwise it opens a matplotlib window.
    """

    def __init__(self, png: Path | None) -> None:
        try:
            import matplotlib
        except ImportError as exc:  # an optional extra; say how to get it
            raise NetposeError("--plot needs matplotlib: pip install 'netpose[plot]'") from exc

        self.png = png
        self._write_failed = False
        if png is not None:
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure

            self.figure = Figure(figsize=(8, 5), dpi=100)
            FigureCanvasAgg(self.figure)
            self.pyplot = None
        else:
            import matplotlib.pyplot as plt

            if matplotlib.get_backend().lower() == "agg":
                log.warning("no display for --plot; use --plot-png FILE to draw into a file")
            plt.ion()
            self.figure = plt.figure(figsize=(8, 5))
            self.pyplot = plt
        self.distance_axes, self.confidence_axes = self.figure.subplots(2, 1, sharex=True)
        self.samples: deque[tuple[float, float, float, float, float]] = deque()
        self.t0: float | None = None
        self.dirty = True

    def add(self, recv_mono: float, received: Received) -> None:
        payload = received.payload or {}
        filtered = payload.get("filtered") or {}

        def number(value: Any) -> float:
            return float(value) if isinstance(value, int | float) else math.nan

        if self.t0 is None:
            self.t0 = recv_mono
        t = recv_mono - self.t0
        if self.samples and t - self.samples[-1][0] > PLOT_GAP_S:
            # Nothing came (the tether, the daemon): a break in every line, not a straight
            # line across the outage that looks as if the net was tracked throughout.
            gap = math.nan
            self.samples.append((self.samples[-1][0] + 1e-3, gap, gap, gap, gap))
        detected = bool(payload.get("detected"))
        self.samples.append((
            t,
            number(payload.get("distance_m")) if detected else math.nan,
            number(sigma_of(payload, "distance")) if detected else math.nan,
            number(filtered.get("distance_m")) if filtered.get("valid") else math.nan,
            number(payload.get("confidence")),
        ))
        while self.samples and self.samples[-1][0] - self.samples[0][0] > PLOT_HISTORY_S:
            self.samples.popleft()
        self.dirty = True

    def update(self) -> None:
        if not self.dirty:
            if self.pyplot is not None:
                self.pyplot.pause(0.001)  # keep the window responsive
            return
        data = np.array(self.samples, dtype=float).reshape(-1, 5)
        t, distance, sigma, filtered, confidence = data.T
        ax = self.distance_axes
        ax.clear()
        ax.fill_between(t, distance - sigma, distance + sigma, color="tab:blue", alpha=0.2,
                        label="+/- 1 sigma (with the scale's)")
        ax.plot(t, distance, ".", color="tab:blue", markersize=3, label="estimate")
        ax.plot(t, filtered, "-", color="tab:orange", label="filtered")
        ax.set_ylabel("distance to net [m]")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize="small")
        ax = self.confidence_axes
        ax.clear()
        ax.plot(t, confidence, "-", color="tab:green")
        ax.set_ylim(0.0, 1.05)
        ax.set_ylabel("confidence")
        ax.set_xlabel("time since first estimate [s]")
        ax.grid(True, alpha=0.3)
        self.figure.tight_layout()
        if self.png is not None:
            try:
                image = io.BytesIO()
                self.figure.savefig(image, format="png")
                write_atomically(self.png, image.getvalue(), durable=False)
            except OSError as exc:  # a full disk must not end the pilot's topside view
                if not self._write_failed:
                    log.warning("--plot-png %s: %s; the plot is not updated", self.png,
                                exc.strerror or exc)
                self._write_failed = True
            else:
                self._write_failed = False
        elif self.pyplot is not None:
            self.figure.canvas.draw_idle()
            self.pyplot.pause(0.001)
        self.dirty = False

    def close(self) -> None:
        if self.png is not None:
            self.update()  # the file shows everything received
        elif self.pyplot is not None:
            self.pyplot.close(self.figure)
