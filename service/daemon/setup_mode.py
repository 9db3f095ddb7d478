"""Set-up mode: the web page without the estimator, until the configuration is complete.

On a first start under BlueOS there is no mesh size and no camera calibration yet, and `netpose
run` would stop with exit status 78, restarted in a loop by the container engine, with no page to
fix it from. With `web.enabled`, a problem with either starts this mode instead: the camera's
frames (with the problem written on them), the settings form and the calibration upload. So
does any other configuration error but the page's own (wiring.py's `_rescue`): the page names
the key, and its settings or the file fix it.
Nothing is sent to the autopilot and nothing is published: the link and telemetry are not even
built. A change saved on the page asks for a reload (the editor's ordinary path); when the
configuration is then valid, set-up mode ends and the daemon starts as usual, in the same
process.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from service.config import Config
from service.core.errors import NetposeError
from service.core.messages import EstimateMessage
from service.daemon.loop import ReloadOutcome
from service.daemon.ports import Frame, FrameSource, Notifier
from service.signals import SignalFlags
from service.tools.preview import render_preview

log = logging.getLogger("netpose.daemon")

READ_TIMEOUT_S = 0.2
REOPEN_AFTER_S = 5.0
# No frame for this long from an open camera: the page says so (a stream that is not there).
NO_FRAMES_S = 5.0


class SetupPage(Protocol):
    """The web page, fed frames without a pipeline result."""

    def start(self) -> None: ...
    def observe(self, frame: Frame, result: None, message: EstimateMessage) -> None: ...
    def close(self) -> None: ...


def setup_renderer(problem: str, width: int) -> Callable[[Any, Any], npt.NDArray[np.uint8]]:
    """The live view in set-up mode: the frame and what is missing."""
    lines = ["set-up mode: nothing is sent to the autopilot", problem[:90]]

    def render(frame: Any, _result: Any) -> npt.NDArray[np.uint8]:
        return render_preview(frame.image, (), lines, width=width)

    return render


def run_setup(
    *,
    source: FrameSource,
    page: SetupPage,
    notifier: Notifier,
    flags: SignalFlags,
    problem: str,
    validate: Callable[[], Config],
    on_reload: Callable[[ReloadOutcome], None],
    vehicle: str,
    deadline: float | None = None,
    note_camera: Callable[[str], None] = lambda _text: None,
) -> Config | None:
    """Serve the page until a saved configuration is valid (returned), or a stop or the
    monotonic `deadline` (`netpose run --duration`) comes first (None). `note_camera` is told
    what keeps the live view dark ("" once frames come), for the page to say."""
    log.warning("configuration not usable yet (%s): set-up mode, nothing is sent to the "
                "autopilot; finish it on the web page (or in the file)", problem)
    page.start()
    notifier.ready(status=f"set-up mode: {problem}")
    opened_at: float | None = None
    last_frame_at: float | None = None
    said: str | None = None  # unknown: the first say() always tells the page
    seq = 0

    def say(text: str) -> None:
        nonlocal said
        if text != said:
            said = text
            note_camera(text)

    say("")  # a note from an earlier set-up of this run is no longer true
    try:
        while not flags.stop.is_set():
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                log.info("run duration reached in set-up mode")
                break
            notifier.watchdog(now)
            if flags.reload.is_set():
                flags.reload.clear()
                try:
                    config = validate()
                except NetposeError as exc:
                    # Saved (the page checked it as far as set-up allows), still not complete:
                    # the page says what is left, and set-up goes on. The journal says it too,
                    # for whoever edited the file by hand and reloaded.
                    log.warning("set-up mode: configuration reloaded, still not complete: %s",
                                exc)
                    on_reload(ReloadOutcome(ok=True, pending=str(exc)))
                    notifier.status(f"set-up mode: {exc}")
                    continue
                log.info("configuration complete: leaving set-up mode")
                on_reload(ReloadOutcome(ok=True, digest=config.digest))
                return config
            if opened_at is None or (opened_at < 0 and now + opened_at > REOPEN_AFTER_S):
                try:
                    source.open()
                    opened_at = now
                except NetposeError as exc:
                    if opened_at is None:
                        log.warning("set-up mode: the camera cannot be opened (%s); retrying",
                                    exc)
                    say(f"the camera cannot be opened ({exc}): check camera.url")
                    opened_at = -now  # negative: failed at -opened_at, retry later
                    time.sleep(READ_TIMEOUT_S)
                    continue
            if opened_at < 0:
                time.sleep(READ_TIMEOUT_S)
                continue
            frame = source.read(READ_TIMEOUT_S)
            if frame is None:
                silent = now - (last_frame_at if last_frame_at is not None else opened_at)
                if silent > NO_FRAMES_S:
                    error = source.stats().error
                    say(f"no frames from the camera for {silent:.0f} s"
                        + (f" ({error})" if error else "") + ": check camera.url")
                continue
            last_frame_at = now
            say("")
            seq += 1
            page.observe(frame, None, EstimateMessage(
                vehicle=vehicle, time_unix=time.time(), time_mono=time.monotonic(), seq=seq,
                frame_time_unix=frame.t_wall, frame_time_mono=frame.t_monotonic,
                reason=f"set-up mode: {problem}"))
        return None
    finally:
        note_camera("")  # the daemon proper (or a stop) follows: set-up's camera note ends
        for closer in (page.close, source.close):
            try:
                closer()
            except Exception:
                log.exception("closing after set-up mode failed")
