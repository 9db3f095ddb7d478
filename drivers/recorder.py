"""Recordings of what the daemon saw: every processed frame, lossless, with the daemon's estimate.

A recording is a folder that `netpose replay` reads as it is (the `recording:` frame source):

    netpose-<vehicle>-<UTC time>/
      recording.json   format, version, vehicle, netpose version, frames, dropped, times, and
                       which files below describe the camera and the tuning
      camera.yaml      the calibration in force (ROS camera_info layout)
      netpose.toml     the [mesh], [estimator], [filter], [service] and [damage] settings and
                       camera.focal_tolerance in force (a reload that changes them ends the
                       recording and starts the next: each recording has one set of settings,
                       so each replays exactly)
      pipeline_state.json  the filter's state and the estimator's prior just before the
                       first recorded frame (exact JSON values, service/pipeline.py)
      frames.jsonl     one line per frame, in order: the PNG's name, the source's frame number,
                       the capture time on the monotonic and the wall clock, and the daemon's
                       estimate message (the telemetry payload, service.core.messages)
      frames/          <number>.png: the 8-bit grey image the estimator was given

A replay of the folder starts the same pipeline from the recorded state and feeds it the same
images with the same capture times, so it reproduces the daemon's output even for a recording
started in the middle of a dive (tests/test_web.py). The state is taken on the frame loop, in
`observe` of the first frame after the start (that frame itself is not recorded). Frames are written
by a thread the recorder owns; the frame loop only appends to a bounded queue. When the disk
cannot keep up the queue overflows: the oldest waiting frames are dropped and counted in
`recording.json`, and a replay past such a gap may differ from the vehicle (the filter's
state depends on every frame).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt

from drivers.errors import DriverError
from drivers.lifecycle import Closeable
from service import __version__
from service.core.camera import CameraModel, save_camera
from service.core.files import write_atomically
from service.core.messages import DamageMessage, EstimateMessage, StatusMessage, to_json
from service.core.redact import redact_text

log = logging.getLogger(__name__)

RECORDING_FORMAT = "netpose-recording"
FORMAT_VERSION = 1
MANIFEST = "recording.json"
FRAMES_LOG = "frames.jsonl"
FRAMES_DIR = "frames"
CAMERA_FILE = "camera.yaml"
TUNING_FILE = "netpose.toml"
STATE_FILE = "pipeline_state.json"
# netpose-<vehicle>-<number>-<UTC start>: the number orders them (a Pi without a clock names
# its first recordings 1970..., and an NTP step mid-dive puts later ones before earlier ones);
# recordings of netpose before it have none.
NAME_PATTERN = re.compile(r"^netpose-[A-Za-z0-9_.-]+?(-(?P<number>\d{4,}))?-\d{8}T\d{6}Z(-\d+)?$")
# PNG level 1: a 640x360 grey frame in about 3 ms; the higher levels cost several times more
# for 10-20 % less disk.
PNG_LEVEL = 1
# Free disk below this stops a recording (the data volume also holds the configuration).
MIN_FREE_BYTES = 200 * 1024 * 1024
# How long a stop waits for the writer to put the queued frames on the card: within the unit's
# TimeoutStopSec (5 s) with room for the rest of the stop, or systemd kills the process before
# the manifest is written.
RECORDER_CLOSE_WAIT_S = 2.5
QUEUE_FRAMES = 64


class RecorderError(DriverError):
    """A recording cannot be started (already running, no space, folder not writable)."""


class ObservedFrame(Protocol):
    """What an observer of the frame loop (the recorder, the web page) reads of a frame."""

    @property
    def image(self) -> npt.NDArray[Any]: ...
    @property
    def index(self) -> int: ...
    @property
    def t_monotonic(self) -> float: ...
    @property
    def t_wall(self) -> float: ...


@dataclass(frozen=True)
class RecordingSetup:
    """What a replay needs besides the frames: the camera and the tuning, as in force."""

    camera: CameraModel
    tuning_toml: str  # [mesh], [estimator], [filter], [service], [damage] as TOML (and the
    # camera's focal tolerance)
    mesh_bar_length_m: float
    mesh_opening_angle_deg: float
    # The daemon's configuration digest (the one its log and every status message carry) and
    # its source, redacted: a recording joined to the dive's telemetry and log by them.
    config_digest: str = ""
    source: str = ""


@dataclass(frozen=True)
class RecorderStatus:
    active: bool = False
    name: str = ""
    frames: int = 0
    dropped: int = 0
    bytes: int = 0
    started_unix: float | None = None
    error: str = ""  # why the last recording stopped by itself or could not start

    def to_json(self) -> dict[str, Any]:
        return {"kind": "recording", **asdict(self)}


@dataclass(frozen=True)
class _Item:
    image: npt.NDArray[Any]
    index: int
    t_monotonic: float
    t_wall: float
    estimate: EstimateMessage


@dataclass(frozen=True)
class _State:
    after_index: int  # the frame the state follows (the next recorded one comes after it)
    state: dict[str, Any]


class _Session:
    """One recording in progress: its folder, its writer thread and its counters."""

    def __init__(self, folder: Path, max_bytes: int,
                 on_stop: Callable[[_Session, str], None],
                 on_full: Callable[[_Session], None] = lambda _session: None) -> None:
        """`on_stop`: the writer stopped by itself (a broken card, little space left), with
        the reason in a few words (for the pilot's 50-character STATUSTEXT);
        `on_full`: it reached `max_bytes` and goes on writing what it is given until closed
        (the recorder rolls over to a new one)."""
        self.folder = folder
        self.max_bytes = max_bytes
        self.started_unix = time.time()
        self.frames = 0
        self.dropped = 0
        self.bytes = 0
        self.error = ""
        self._on_stop = on_stop
        self._on_full = on_full
        self._full = False
        self._queue: deque[_Item | _State] = deque()
        self.needs_state = True  # the first observed frame gives the pipeline state
        self._cond = threading.Condition()
        self._closing = False
        self._log = (folder / FRAMES_LOG).open("a", encoding="utf-8")
        self._thread = threading.Thread(target=self._run, name=f"recorder {folder.name}",
                                        daemon=True)
        self._thread.start()

    def put(self, item: _Item | _State) -> None:
        with self._cond:
            if self._closing:
                return
            if len(self._queue) >= QUEUE_FRAMES:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append(item)
            self._cond.notify()

    def close(self, timeout_s: float = RECORDER_CLOSE_WAIT_S) -> bool:
        """Let the writer finish what is queued; False when it is still busy after
        `timeout_s` (a stalled card): its log is then left to it, not closed under it."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            return False
        self._log.close()
        return True

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if not self._queue:
                    return  # closing and everything written
                item = self._queue.popleft()
            try:
                self._write(item)
            except Exception as exc:  # a full or broken disk ends the recording, not the daemon
                self._stop_by_itself(f"writing failed: {exc}", "write failed")
                return
            if self.bytes >= self.max_bytes and not self._full:
                self._full = True
                self._on_full(self)
            if self.frames % 50 == 0 and shutil.disk_usage(self.folder).free < MIN_FREE_BYTES:
                self._stop_by_itself("less than 200 MB free on the data volume", "card full")
                return

    def _write(self, item: _Item | _State) -> None:
        if isinstance(item, _State):
            state = {"after_frame": item.after_index, "pipeline": item.state}
            (self.folder / STATE_FILE).write_text(json.dumps(state), encoding="utf-8")
            return
        name = f"{FRAMES_DIR}/{item.index:08d}.png"
        path = self.folder / name
        ok, data = cv2.imencode(".png", np.ascontiguousarray(item.image),
                                [int(cv2.IMWRITE_PNG_COMPRESSION), PNG_LEVEL])
        if not ok:
            raise RecorderError(f"OpenCV cannot encode frame {item.index} as PNG")
        # Written whole or not at all: a card that fills mid-frame left a truncated PNG that
        # no line names, and no room for the manifest that says why the recording ended.
        partial = path.with_name(path.name + ".part")
        try:
            partial.write_bytes(data.tobytes())
            os.replace(partial, path)
        except OSError:
            partial.unlink(missing_ok=True)
            raise
        line = json.dumps({"frame": name, "index": item.index, "t_mono": item.t_monotonic,
                           "t_unix": item.t_wall, "estimate": to_json(item.estimate)},
                          separators=(",", ":"), allow_nan=False)
        self._log.write(line + "\n")
        self._log.flush()  # a line always names a complete PNG: the log is valid at any moment
        self.frames += 1
        self.bytes += len(data) + len(line) + 1

    def _stop_by_itself(self, why: str, briefly: str) -> None:
        with self._cond:
            self._closing = True
            self.dropped += len(self._queue)
            self._queue.clear()
        self.error = why
        log.warning("recording %s stopped: %s", self.folder.name, why)
        self._on_stop(self, briefly)


def _number(name: str) -> int:
    """A recording's number (0: none, a recording of an older netpose, or not a recording)."""
    match = NAME_PATTERN.match(name)
    return int(match["number"]) if match and match["number"] else 0


def _contents_of(folder: Path) -> dict[str, int]:
    """Frames logged and bytes on disk of a recording folder (one its daemon never finished)."""
    frames = 0
    try:
        with (folder / FRAMES_LOG).open("rb") as fh:
            frames = sum(1 for line in fh if line.strip(b"\0 \t\r\n"))
    except OSError:
        pass
    size = 0
    for path in folder.rglob("*"):
        with contextlib.suppress(OSError):
            if path.is_file():
                size += path.stat().st_size
    return {"frames": frames, "bytes": size}


class Recorder(Closeable):
    """Records processed frames on request (the web page's start/stop); a FrameObserver.

    `setup()` is asked at each start for the camera and tuning in force, so a recording made
    after a reload describes the settings that produced it.
    """

    def __init__(self, root: Path, vehicle: str, setup: Callable[[], RecordingSetup],
                 max_bytes: int, pipeline_state: Callable[[], dict[str, Any]] | None = None,
                 recorded_sections: frozenset[str] | None = None,
                 tell_pilot: Callable[[str], None] | None = None) -> None:
        """`recorded_sections`: the configuration sections its replay depends on (a reload
        that changes one rolls the recording over); None: any change does. `tell_pilot`: a
        recording that stops by itself is said there (the autopilot link's STATUSTEXT), from
        the writer's thread."""
        self.root = root
        self._tell_pilot = tell_pilot
        self._recorded_sections = recorded_sections
        self._finishing: list[threading.Thread] = []  # recordings ended by a reload
        # Folders whose files are being finished (a stop, a reload's roll-over): not to be
        # deleted, nor listed as interrupted, until their manifest is written.
        self._closing: set[Path] = set()
        self._pipeline_state = pipeline_state
        self._vehicle = re.sub(r"[^A-Za-z0-9_.-]", "_", vehicle) or "rov"
        self._setup = setup
        self._max_bytes = max_bytes
        self._lock = threading.Lock()
        self._session: _Session | None = None
        self._last = RecorderStatus()
        self._session_setup: RecordingSetup | None = None

    # -- FrameObserver ------------------------------------------------------------------------
    def start(self) -> None:
        """Nothing runs until a recording is started."""

    def observe(self, frame: ObservedFrame, result: object, message: EstimateMessage) -> None:
        session = self._session  # one read: the loop never takes the lock
        if session is None:
            return
        if session.needs_state:
            # On the frame loop, between two frames: the state the next frame starts from.
            session.needs_state = False
            if self._pipeline_state is not None:
                session.put(_State(frame.index, self._pipeline_state()))
            return
        session.put(_Item(frame.image, frame.index, frame.t_monotonic, frame.t_wall, message))

    def observe_status(self, message: StatusMessage) -> None:
        """Recordings do not keep the status."""

    def observe_damage(self, message: DamageMessage) -> None:
        """Nor the holes found: a replay of the recording inspects the frames again."""

    def observe_reload(self, changed: frozenset[str]) -> None:
        """Settings the recording describes changed: it ends at the last frame made with the
        old ones and the next begins with the new ones (its netpose.toml, its pipeline state
        at its first frame), here on the loop, between two frames, so none is lost or goes
        to the wrong one. Finishing the old one's files (its writer drains its queue) is done
        on a thread of the recorder's own, which `stop` waits for."""
        if self._recorded_sections is not None and not changed & self._recorded_sections:
            return
        self._roll_over(None, f"settings changed ({', '.join(sorted(changed))})")

    def _roll_over(self, full: _Session | None, why: str) -> None:
        """End the recording in progress (only if it is `full`, when given) and begin the
        next at once; the old one's files are finished on a thread of the recorder's own,
        which `stop` waits for."""
        with self._lock:  # one hold: a stop from the page sees the old or the new, not none
            old, setup = self._session, self._session_setup
            if old is None or setup is None or (full is not None and old is not full):
                return
            log.info("recording %s ends here: %s; a new one starts", old.folder.name, why)
            try:
                # The old one takes the frames until the new one takes over (a roll-over off
                # the frame loop lost the frames that came while the new folder was made).
                self._begin_locked(replacing=old)
            except RecorderError as exc:
                self._session = None
                log.warning("recording after %s: %s", why, exc)
                # Said by the recording that ended (its manifest, the page's status): recording
                # stopped for the rest of the dive.
                old.error = f"no next recording after {why}: {exc}"
                self._said_to_pilot("next part failed")
            self._closing.add(old.folder)
            finishing = threading.Thread(target=self._finish, args=(old, setup),
                                         name="recorder finish", daemon=True)
            # Started under the lock: a stop that finds it in the list joins a started thread.
            finishing.start()
            self._finishing.append(finishing)

    def close(self) -> None:
        self.stop()

    # -- control ---------------------------------------------------------------------------------
    def begin(self) -> RecorderStatus:
        with self._lock:
            return self._begin_locked()

    def _begin_locked(self, replacing: _Session | None = None) -> RecorderStatus:
        if self._session is not None and self._session is not replacing:
            raise RecorderError(f"already recording {self._session.folder.name}")
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            free = shutil.disk_usage(self.root).free
        except OSError as exc:
            raise RecorderError(
                f"recordings folder {self.root}: {exc.strerror or exc}") from None
        if free < MIN_FREE_BYTES:
            raise RecorderError(f"only {free >> 20} MB free in {self.root}; 200 MB needed")
        setup = self._setup()
        folder = self._new_folder()
        try:
            (folder / FRAMES_DIR).mkdir(parents=True)
            # Not flushed to the card (nor is anything of a recording): this runs on the
            # frame loop when a reload rolls the recording over.
            save_camera(setup.camera, folder / CAMERA_FILE, durable=False)
            (folder / TUNING_FILE).write_text(setup.tuning_toml, encoding="utf-8")
            session = _Session(folder, self._max_bytes, self._stopped_by_itself,
                               self._full_by_itself)
        except OSError as exc:
            shutil.rmtree(folder, ignore_errors=True)
            raise RecorderError(f"cannot write in {self.root}: {exc.strerror or exc}") from None
        try:
            self._manifest(session, setup, finished=False)
        except OSError as exc:
            session.close()  # its writer thread too
            shutil.rmtree(folder, ignore_errors=True)
            raise RecorderError(f"cannot write in {self.root}: {exc.strerror or exc}") from None
        self._session_setup = setup
        self._session = session
        log.info("recording started: %s", folder)
        return self._status_of(session)

    def stop(self) -> RecorderStatus:
        with self._lock:
            finishing, self._finishing = self._finishing, []
        for thread in finishing:
            if thread is not threading.current_thread():
                thread.join()  # a recording a reload ended: its manifest is written first
        with self._lock:
            session, self._session = self._session, None
            if session is None:
                return self._last
            assert self._session_setup is not None
            self._closing.add(session.folder)
            return self._finish(session, self._session_setup)

    def _finish(self, session: _Session, setup: RecordingSetup) -> RecorderStatus:
        """Close a session's files and write its finished manifest."""
        try:
            return self._finish_files(session, setup)
        finally:
            self._closing.discard(session.folder)

    def _finish_files(self, session: _Session, setup: RecordingSetup) -> RecorderStatus:
        written = session.close()
        error = session.error
        if not written:
            # The card stalls: the frames it took stay, and the recording is not marked
            # finished (a replay reads what is there; the page lists it as interrupted).
            why = (f"the card did not finish writing within {RECORDER_CLOSE_WAIT_S:g} s; "
                   "the last frames may be missing")
            error = f"{error}; {why}" if error else why
            log.warning("recording %s: %s", session.folder.name, why)
        try:
            self._manifest(session, setup, finished=written)
        except OSError as exc:
            # The frames written stay; the recording is not marked finished (a replay can
            # still read it), and the page says why.
            why = f"cannot finish the recording's manifest: {exc.strerror or exc}"
            error = f"{error}; {why}" if error else why
            log.warning("recording %s: %s", session.folder.name, why)
        self._last = RecorderStatus(name=session.folder.name, frames=session.frames,
                                    dropped=session.dropped, bytes=session.bytes,
                                    started_unix=session.started_unix, error=error)
        log.info("recording %s stopped: %d frames (%d dropped), %.1f MB", session.folder.name,
                 session.frames, session.dropped, session.bytes / 1e6)
        return self._last

    def status(self) -> RecorderStatus:
        session = self._session
        return self._status_of(session) if session is not None else self._last

    def recordings(self) -> list[dict[str, Any]]:
        """Finished and running recordings, newest first."""
        out: list[dict[str, Any]] = []
        if not self.root.is_dir():
            return out
        for folder in sorted(self.root.iterdir(), key=lambda f: (_number(f.name), f.name),
                             reverse=True):
            if not (NAME_PATTERN.match(folder.name) and (folder / MANIFEST).is_file()):
                continue
            try:
                manifest = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
            except (OSError, ValueError):
                continue
            finished = bool(manifest.get("finished", False))
            session = self._session
            running = (session is not None and session.folder == folder) or (
                folder in self._closing)
            entry = {"name": folder.name, "frames": manifest.get("frames"),
                     "dropped": manifest.get("dropped"), "bytes": manifest.get("bytes"),
                     "started_unix": manifest.get("started_unix"), "finished": finished,
                     "interrupted": not finished and not running}
            if entry["interrupted"]:
                # The daemon ended without finishing it (power lost, killed): its manifest
                # still says what it said at the start; what it holds is on the disk.
                entry.update(_contents_of(folder))
            out.append(entry)
        return out

    def delete(self, name: str) -> int:
        """Remove a recording that is not being made (finished or interrupted): the page's way
        to free the card BlueOS shares with its own updates. Its size in bytes; RecorderError
        for one being recorded, one not there, or a folder that cannot be removed."""
        folder = self.folder_of(name)
        try:
            size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
            shutil.rmtree(folder)
        except OSError as exc:
            raise RecorderError(f"cannot delete {name}: {exc.strerror or exc}") from exc
        log.info("recording %s deleted (%.1f MB)", name, size / 1e6)
        return size

    def folder_of(self, name: str) -> Path:
        """The folder of a finished recording; RecorderError for anything else."""
        folder = self.root / name
        if not NAME_PATTERN.match(name) or not (folder / MANIFEST).is_file():
            raise RecorderError(f"no recording named {name!r}")
        session = self._session
        if session is not None and session.folder == folder:
            raise RecorderError(f"{name} is still being recorded: stop it first")
        if folder in self._closing:
            raise RecorderError(f"{name} is being finished: try again in a moment")
        return folder

    # -- internals -------------------------------------------------------------------------
    def _new_folder(self) -> Path:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        numbers = [_number(folder.name) for folder in self.root.iterdir()]
        base = f"netpose-{self._vehicle}-{max(numbers, default=0) + 1:04d}-{stamp}"
        folder, n = self.root / base, 1
        while folder.exists():
            n += 1
            folder = self.root / f"{base}-{n}"
        return folder

    def _full_by_itself(self, session: _Session) -> None:
        # On the writer thread: a long dive goes on in the next recording (one recording
        # stopped at web.max_recording_mb, 7.5 minutes of 640x360 at 30 frames/s, and nothing
        # recorded the rest of the dive); only the card's free space ends recording.
        threading.Thread(target=self._roll_over, name="recorder roll-over", daemon=True,
                         args=(session, f"it reached web.max_recording_mb "
                                        f"({session.max_bytes >> 20} MB)")).start()

    def _said_to_pilot(self, briefly: str) -> None:
        # A pilot who started a recording of an inspection dive watches the video, not the
        # page: a recording that ended is the evidence of the rest of the dive missing.
        if self._tell_pilot is not None:
            self._tell_pilot(f"netpose: recording stopped: {briefly}")

    def _stopped_by_itself(self, session: _Session, briefly: str) -> None:
        # Called on the writer thread: finish the recording from another one (stop() joins
        # it). Only that recording: one that filled up while a roll-over finished it must not
        # stop the next.
        if self._session is session:
            self._said_to_pilot(briefly)

        def stop_it() -> None:
            if self._session is session:
                self.stop()

        threading.Thread(target=stop_it, name="recorder stop", daemon=True).start()

    def _status_of(self, session: _Session) -> RecorderStatus:
        return RecorderStatus(active=True, name=session.folder.name, frames=session.frames,
                              dropped=session.dropped, bytes=session.bytes,
                              started_unix=session.started_unix, error=session.error)

    def _manifest(self, session: _Session, setup: RecordingSetup, *, finished: bool) -> None:
        manifest = {
            "format": RECORDING_FORMAT, "version": FORMAT_VERSION,
            "netpose_version": __version__, "vehicle": self._vehicle,
            "started_unix": session.started_unix,
            "stopped_unix": time.time() if finished else None, "finished": finished,
            "frames": session.frames, "dropped": session.dropped, "bytes": session.bytes,
            "stopped_because": session.error,
            "frames_log": FRAMES_LOG, "camera": CAMERA_FILE, "tuning": TUNING_FILE,
            "pipeline_state": STATE_FILE,
            "mesh": {"bar_length_m": setup.mesh_bar_length_m,
                     "opening_angle_deg": setup.mesh_opening_angle_deg},
            "config_digest": setup.config_digest or None,
            "source": redact_text(setup.source) if setup.source else None,
            "image": "8-bit grey PNG, the estimator's input",
        }
        write_atomically(session.folder / MANIFEST,
                         (json.dumps(manifest, indent=1) + "\n").encode("utf-8"), durable=False)
