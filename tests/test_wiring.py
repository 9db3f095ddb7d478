"""What `netpose run` builds before it opens anything, and what `--check` therefore catches.

`run --check` and `run` share one validation (`service.daemon.wiring.build_parts`): a
configuration that `--check` passes starts, one it refuses never starts, and both name the same
key. Rendered distances never reach an autopilot unless the configuration says so.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import tomlkit

from drivers.mavlink_link import RecordingAutopilotLink
from drivers.net import free_port
from drivers.sdnotify import NullNotifier
from drivers.sources.synthetic import builtin_camera
from drivers.telemetry import RecordingPublisher
from service.core.camera import save_camera
from service.core.errors import ConfigError
from service.core.messages import to_json
from service.daemon.loop import Daemon
from service.daemon.wiring import (
    build_parts,
    build_source,
    check_config,
    load_daemon_config,
    main,
)
from tests.daemon_harness import (
    REPO,
    FakeClock,
    demo_config,
)
from tests.fake_autopilot import FakeAutopilot, UdpServerTransport

DEMO = REPO / "config" / "demo.toml"
CAMERA = "camera.url=rtsp://127.0.0.1:9/none"


def bad_cases(tmp: Path) -> list[tuple[list[str], str, str]]:
    """(overrides, the key named, words of the problem) for configurations run must refuse."""
    short_key = tmp / "short.key"
    short_key.write_bytes(b"0123456789")
    broken_json5 = tmp / "broken.json5"
    broken_json5.write_text("{ mode: 'peer', connect: { endpoints: [ } ")
    return [
        ([CAMERA, "camera.calibration=builtin"], "camera.calibration", "rtsp"),
        ([f"mavlink.signing_key_file={tmp / 'absent.key'}"], "mavlink.signing_key_file",
         "cannot read"),
        ([f"mavlink.signing_key_file={short_key}"], "mavlink.signing_key_file", "32 raw bytes"),
        ([f"telemetry.config_file={tmp / 'absent.json5'}"], "telemetry.config_file",
         "does not exist"),
        ([f"telemetry.config_file={broken_json5}"], "telemetry.config_file", "broken.json5"),
        (["telemetry.connect=['tcp/127.0.0.1']"], "telemetry.connect", "needs a port"),
        (["telemetry.listen=['tcp/300.0.0.1:7447']"], "telemetry.listen", "invalid IPv4"),
    ]


@pytest.mark.parametrize("case", range(7))
def test_check_refuses_what_run_would_refuse(tmp_path: Path, case: int) -> None:
    overrides, key, words = bad_cases(tmp_path)[case]
    with pytest.raises(ConfigError) as info:
        check_config(str(DEMO), overrides)
    assert info.value.key == key and words in str(info.value), str(info.value)
    assert "\n" not in str(info.value)  # one line, however the library words its error


def test_check_and_run_exit_78_with_the_same_line(tmp_path: Path) -> None:
    """The real command: both refuse before anything is opened, with the same one line."""
    lines = []
    for overrides, key, _ in bad_cases(tmp_path)[3:5]:
        for extra in (["--check"], ["--duration", "5"]):
            cmd = [sys.executable, "-m", "service.cli", "run", "--config", str(DEMO)]
            for o in overrides:
                cmd += ["--set", o]
            proc = subprocess.run(cmd + extra, cwd=REPO, capture_output=True, text=True,
                                  timeout=60)
            assert proc.returncode == 78, proc.stderr
            last = proc.stderr.strip().splitlines()[-1]
            assert last.startswith(f"netpose: configuration error: {key}: "), proc.stderr
            assert "READY" not in proc.stderr and "started" not in proc.stderr
            lines.append(last)
    assert lines[0] == lines[1] and lines[2] == lines[3]


def test_check_builds_what_run_starts_and_opens_nothing(tmp_path: Path) -> None:
    text = check_config(str(DEMO))
    assert text.startswith("configuration OK") and "sha256:" in text


def test_a_rendered_source_needs_allow_simulated_to_start() -> None:
    """The QA finding: an installed configuration left on the demo source fed a real autopilot
    283 rendered distances in 25 s. Rendered frames now start only where the configuration
    says so explicitly (the demo and SITL configurations)."""
    with pytest.raises(ConfigError) as info:
        check_config(str(DEMO), ["mavlink.allow_simulated=false"])
    assert info.value.key == "mavlink.allow_simulated" and "renders" in info.value.problem
    with pytest.raises(ConfigError):
        build_parts(demo_config("mavlink.allow_simulated=false"), NullNotifier())
    assert build_source(demo_config()).rendered  # the demo says so, and starts
    build_parts(demo_config(), NullNotifier()).source.close()


def test_the_daemons_file_like_sources_keep_to_the_clock(tmp_path: Path) -> None:
    """A folder of stills (or a video file) as the daemon's camera: read as fast as the loop
    went, at 10 frames/s of media time, frame stamps ran ahead of the clock (the log's latency
    went to -11 s in 12 s, each DISTANCE_SENSOR stamped seconds in the future). The daemon
    paces such sources to their frame rate; a URL that says realtime=0 is read as written."""
    import cv2
    import numpy as np

    for i in range(4):
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), np.full((180, 320), 40 * i, np.uint8))
    paced = build_source(demo_config(f"camera.url=images:{tmp_path}?fps=20"))
    unpaced = build_source(demo_config(f"camera.url=images:{tmp_path}?fps=20&realtime=0"))
    for source, keeps_to_the_clock in ((paced, True), (unpaced, False)):
        source.open()
        try:
            ahead = []
            for _ in range(4):
                frame = source.read(1.0)
                assert frame is not None
                ahead.append(frame.t_monotonic - time.monotonic())
        finally:
            source.close()
        if keeps_to_the_clock:
            assert max(ahead) <= 0.0
        else:
            assert max(ahead) > 0.1  # the fourth frame, 0.15 s of media time, read at once


@pytest.mark.parametrize("url", ["file:{folder}/dive.avi", "{folder}/dive.avi",
                                 "images:{folder}", "recording:{folder}"])
def test_a_recorded_source_needs_allow_simulated_to_start(tmp_path: Path, url: str) -> None:
    """A recording played as the camera (a dive video, a folder of stills, a netpose
    recording) is not what the vehicle sees now: its distances would steer a real vehicle by a
    net that is somewhere else. Like a rendered source, it starts only where the configuration
    says so (a bench test, SITL)."""
    camera = tmp_path / "camera.yaml"
    save_camera(builtin_camera(640, 360), camera)
    (tmp_path / "dive.avi").write_bytes(b"")  # there (not opened by the check)
    overrides = [f"camera.url={url.format(folder=tmp_path)}", f"camera.calibration={camera}"]
    with pytest.raises(ConfigError) as info:
        build_parts(demo_config(*overrides, "mavlink.allow_simulated=false"), NullNotifier())
    assert info.value.key == "mavlink.allow_simulated" and "recorded" in info.value.problem
    source = build_source(demo_config(*overrides))
    assert source.recorded and not source.rendered
    assert not build_source(demo_config("camera.url=rtsp://127.0.0.1:8554/x")).recorded
    assert not build_source(demo_config()).recorded  # rendered, not recorded


@pytest.mark.parametrize("allow", [False, True])
@pytest.mark.parametrize("url", ["/dev/vide0", "rtsp//typo:8554/cam", "file:{folder}/dive.avi",
                                 "images:{folder}/stills"])
def test_a_recorded_source_that_is_not_there_is_a_camera_url_error(
    tmp_path: Path, url: str, allow: bool
) -> None:
    """A mistyped camera path was refused as "mavlink.allow_simulated: camera.url plays
    recorded frames" (the key to fix is camera.url), and where the configuration allows
    recorded frames --check said OK and the service retried "no such file" for ever."""
    camera = tmp_path / "camera.yaml"
    save_camera(builtin_camera(640, 360), camera)
    config = demo_config(f"camera.url={url.format(folder=tmp_path)}",
                         f"camera.calibration={camera}",
                         f"mavlink.allow_simulated={str(allow).lower()}")
    with pytest.raises(ConfigError) as info:
        build_parts(config, NullNotifier())
    assert info.value.key == "camera.url" and "no such file" in info.value.problem
    if url.startswith("/dev/"):
        assert "/dev/videoN" in info.value.problem
    if url.startswith("rtsp//"):
        assert "scheme://host" in info.value.problem


def test_a_recorded_source_is_found_beside_the_configuration(tmp_path: Path) -> None:
    """Like camera.calibration: the service runs in /var/lib/netpose, its configuration and
    the dive video it names in /etc/netpose."""
    folder = tmp_path / "etc"
    folder.mkdir()
    (folder / "dive.avi").write_bytes(b"")
    config = folder / "netpose.toml"
    config.write_text(DEMO.read_text())
    source = build_source(load_daemon_config(str(config), ["camera.url=dive.avi"]))
    assert source.recorded and getattr(source, "path", None) == folder / "dive.avi"
    (folder / "stills").mkdir()
    globbed = build_source(load_daemon_config(str(config), ["camera.url='images:stills/*.png'"]))
    assert globbed.recorded
    # A bare folder is told from a file beside the configuration too, not in the working
    # directory (it became file:/.../stills, then "no such file" for ever).
    bare = build_source(load_daemon_config(str(config), ["camera.url=stills"]))
    assert type(bare).__name__ == "ImageFolderSource", type(bare)
    (folder / "dives" / "a").mkdir(parents=True)
    deep = build_source(load_daemon_config(str(config),
                                           ["camera.url='images:dives/*/frames/*.png'"]))
    assert deep.recorded


def test_a_bare_camera_index_is_a_camera() -> None:
    """OpenCV's habit: camera.url = "0" is the first camera, not a video file named 0."""
    source = build_source(demo_config("camera.url='0'"))
    assert not source.recorded and not source.rendered


def test_files_a_configuration_names_are_found_beside_it(tmp_path: Path) -> None:
    """camera.calibration and web.recordings_dir were relative to the configuration file, the
    signing key and the Zenoh configuration to the working directory: `run --check` in
    /etc/netpose passed, the service (WorkingDirectory=/var/lib/netpose) exited 78. All are
    the configuration file's now; an empty name is an error, not "no key" (it ran unsigned)."""
    folder = tmp_path / "etc"
    folder.mkdir()
    (folder / "mav.key").write_text("00" * 32)
    (folder / "zenoh.json5").write_text("{}")
    config = folder / "netpose.toml"
    config.write_text(DEMO.read_text().replace(
        "[mavlink]", '[mavlink]\nsigning_key_file = "mav.key"', 1).replace(
        "[telemetry]", '[telemetry]\nconfig_file = "zenoh.json5"', 1))
    (folder / "mav.key").chmod(0o600)
    elsewhere = tmp_path / "var"
    elsewhere.mkdir()
    done = subprocess.run([sys.executable, "-m", "service.cli", "run", "--config", str(config),
                           "--check"], cwd=elsewhere, capture_output=True, text=True,
                          timeout=60, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr
    for key in ("mavlink.signing_key_file", "telemetry.config_file"):
        with pytest.raises(ConfigError) as info:
            check_config(str(config), [f"{key}="])
        assert info.value.key == key


def test_the_daemon_process_refuses_a_rendered_source_without_allow_simulated() -> None:
    """End to end: with a real (fake) autopilot listening, the process exits 78 naming the
    key, and the autopilot never hears a distance (nor anything else)."""
    with FakeAutopilot(UdpServerTransport()) as autopilot:
        cmd = [sys.executable, "-m", "service.cli", "run", "--config", str(DEMO),
               "--duration", "6", "--set", f"mavlink.url={autopilot.url}",
               "--set", "mavlink.allow_simulated=false", "--set", "telemetry.enabled=false"]
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=60,
                              env=dict(os.environ, PYTHONUNBUFFERED="1"))
        time.sleep(0.2)
        distances = autopilot.received("DISTANCE_SENSOR")
    assert proc.returncode == 78, proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith(
        "netpose: configuration error: mavlink.allow_simulated:")
    assert distances == []


def test_a_world_readable_signing_key_is_named_in_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    key = tmp_path / "mavlink.key"
    key.write_bytes(os.urandom(32))
    key.chmod(0o644)
    caplog.set_level(logging.WARNING, logger="drivers.mavlink_settings")
    check_config(str(DEMO), [f"mavlink.signing_key_file={key}"])
    assert "readable by every user" in caplog.text and str(key) in caplog.text
    caplog.clear()
    key.chmod(0o600)
    check_config(str(DEMO), [f"mavlink.signing_key_file={key}"])
    assert "readable by every user" not in caplog.text


def test_vehicle_profile_refuses_to_start_until_the_mesh_is_set() -> None:
    with pytest.raises(ConfigError) as info:
        load_daemon_config(str(REPO / "config" / "raspberrypi.toml"), check_files=False)
    assert info.value.key == "mesh.bar_length_m"


def test_check_says_what_run_does_with_a_configuration_set_up_mode_can_finish() -> None:
    """config/blueos.toml as shipped (no mesh size, the page on): `run` starts set-up mode,
    but `run --check` exited 78, so install.sh never started the service whose page was to
    ask for the mesh. The check says the service starts in set-up mode, naming what it waits
    for; without the page (the Pi profile) it is the configuration error it was."""
    text = check_config(str(REPO / "config" / "blueos.toml"))
    assert text.startswith("configuration incomplete") and "mesh.bar_length_m" in text
    assert "set-up mode" in text
    with pytest.raises(ConfigError) as info:
        check_config(str(REPO / "config" / "raspberrypi.toml"))
    assert info.value.key == "mesh.bar_length_m"
    with pytest.raises(ConfigError) as info:  # set-up mode cannot fix a bad MAVLink URL
        check_config(str(REPO / "config" / "blueos.toml"), ["mavlink.url=nonsense"])
    assert info.value.key == "mavlink.url"


@pytest.mark.parametrize(("changes", "key"), [
    # No page to serve: the one-line error and exit 78, as ever.
    ({"web.enabled": False, "mavlink.url": "nonsense"}, "mavlink.url"),
    # The page's own settings wrong: no page to serve it with.
    ({"web.port": "eighty"}, "web.port"),
    # A required key with no default: nothing to stand in for it.
    ({"camera.url": None}, "camera.url"),
])
def test_set_up_mode_serves_no_configuration_error_it_cannot_serve_the_page_past(
    tmp_path: Path, changes: dict[str, Any], key: str,
) -> None:
    """Set-up mode takes any configuration error while the page is on (test_web.py); these it
    cannot, and `run` exits with the error naming the key instead of serving a page."""
    doc = tomlkit.parse(DEMO.read_text(encoding="utf-8"))
    doc["web"]["enabled"] = True
    doc["web"]["host"] = "127.0.0.1"
    doc["web"]["port"] = free_port()
    for name, value in changes.items():
        section, _, field = name.partition(".")
        if value is None:
            del doc[section][field]
        else:
            doc[section][field] = value
    path = tmp_path / "netpose.toml"
    path.write_text(tomlkit.dumps(doc), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        main(str(path), duration_s=5.0)
    assert info.value.key == key, info.value


def test_a_broken_set_on_the_command_line_is_not_set_up_for(tmp_path: Path) -> None:
    """A --set that fails only when the parts are built (a video file that is not there):
    set-up mode could never end (the page refuses overridden keys, --set wins over the file),
    so it is the configuration error, exit 78, as ever."""
    doc = tomlkit.parse(DEMO.read_text(encoding="utf-8"))
    doc["web"]["enabled"] = True
    doc["web"]["host"] = "127.0.0.1"
    doc["web"]["port"] = free_port()
    path = tmp_path / "netpose.toml"
    path.write_text(tomlkit.dumps(doc), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        main(str(path), ["camera.url=missing.mp4"], duration_s=5.0)
    assert info.value.key == "camera.url", info.value


def test_a_bad_calibration_file_is_a_configuration_error_naming_the_key(
        tmp_path: Path) -> None:
    (tmp_path / "camera.yaml").write_text("image_width: 640\n")
    with pytest.raises(ConfigError) as info:
        check_config(str(DEMO), [f"camera.calibration={tmp_path / 'camera.yaml'}"])
    assert info.value.key == "camera.calibration" and "image_height" in info.value.problem


@pytest.mark.timeout(20)
@pytest.mark.parametrize("key", ["camera.calibration", "mavlink.signing_key_file", "config"])
@pytest.mark.parametrize("kind", ["device", "fifo", "large"])
def test_a_file_key_naming_a_device_or_a_fifo_is_refused_without_reading_it(
        tmp_path: Path, key: str, kind: str) -> None:
    """Files named by settings are read whole. /dev/zero took the daemon from 131 MB to
    951 MB (then the OOM killer), a FIFO blocked the settings page and the service's stop
    for good: neither is opened, and a file far larger than its kind is refused."""
    import os

    if kind == "device":
        path = Path("/dev/zero")
    elif kind == "fifo":
        path = tmp_path / "fifo"
        os.mkfifo(path)
    else:
        path = tmp_path / "large"
        path.write_bytes(b"#" * (2 << 20))
    if key == "config":
        with pytest.raises(ConfigError) as info:
            check_config(str(path), [])
        assert info.value.key == str(path)
    else:
        with pytest.raises(ConfigError) as info:
            check_config(str(DEMO), [f"{key}={path}"])
        assert info.value.key == key
    assert "regular file" in str(info.value) or "larger than" in str(info.value)


def test_secrets_in_the_camera_url_reach_no_log_status_or_state(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An SRT passphrase, a token and a password containing '@', in a camera URL that cannot be
    opened: the daemon logs, reports and answers about it without any of them."""
    calibration = tmp_path / "camera.yaml"
    save_camera(builtin_camera(640, 360), calibration)
    secrets = ("s3cretPass", "tok3n42", "p@ss@word")
    url = ("rtsp://admin:p@ss@word@127.0.0.1:9/stream?token=tok3n42&passphrase=s3cretPass"
           "&latency=20")
    config = load_daemon_config(str(DEMO), [f"camera.url={url}",
                                            f"camera.calibration={calibration}"])
    parts = build_parts(config, NullNotifier())
    telemetry = RecordingPublisher()
    parts = dataclasses.replace(parts, link=RecordingAutopilotLink(), telemetry=telemetry)
    caplog.set_level(logging.DEBUG)
    clock = FakeClock()
    daemon = Daemon(config, parts, clock=time.monotonic, wall_clock=clock.wall)
    daemon.start()
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and not daemon.parts.source.stats().error:
            daemon.iterate()
        daemon.reporter.report(time.monotonic(), None)
    finally:
        daemon.close()
    assert daemon.parts.source.stats().error, "the source never said why it is down"
    published = str([to_json(m) for m in telemetry.statuses])
    published += str(to_json(telemetry.state)) if telemetry.state is not None else ""
    for secret in secrets:
        assert secret not in caplog.text
        assert secret not in published
    assert "<redacted>" in published and "latency=20" in published


_ARENA_PROBE = """
import ctypes, sys, tempfile, threading
import numpy as np
from service.daemon.wiring import fewer_malloc_arenas
if sys.argv[1] == "daemon":
    fewer_malloc_arenas()
held = []
start = threading.Barrier(8)
def work():
    start.wait()
    held.append([np.ones(4096) for _ in range(64)])  # below the mmap threshold: an arena's
threads = [threading.Thread(target=work) for _ in range(8)]
for t in threads: t.start()
for t in threads: t.join()
libc = ctypes.CDLL(None)
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes = (ctypes.c_char_p, ctypes.c_char_p)
libc.malloc_info.argtypes = (ctypes.c_int, ctypes.c_void_p)
libc.fclose.argtypes = (ctypes.c_void_p,)
with tempfile.NamedTemporaryFile(suffix=".xml") as f:
    fp = libc.fopen(f.name.encode(), b"w")
    libc.malloc_info(0, fp)
    libc.fclose(fp)
    print(open(f.name).read().count("<heap nr="))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or os.confstr("CS_GNU_LIBC_VERSION")
                    is None, reason="malloc arenas are glibc's")
def test_the_daemon_holds_its_threads_to_two_malloc_arenas() -> None:
    """Each thread that allocates gets a glibc arena of its own (eight per core), which keeps
    its freed memory; the daemon's process allows two. Counted by glibc's own malloc_info."""
    # The operator's own limits would decide both counts (and the daemon leaves them alone).
    env = {k: v for k, v in os.environ.items() if k not in ("MALLOC_ARENA_MAX", "GLIBC_TUNABLES")}

    def arenas(mode: str) -> int:
        out = subprocess.run([sys.executable, "-c", _ARENA_PROBE, mode], check=True, env=env,
                             capture_output=True, text=True, timeout=60, cwd=REPO)
        return int(out.stdout.strip())

    default = arenas("default")
    if default <= 2:
        pytest.skip(f"this machine's glibc makes {default} arenas for 8 threads anyway")
    assert arenas("daemon") <= 2


def test_an_operators_arena_limit_is_left_alone() -> None:
    """MALLOC_ARENA_MAX=4 set for the service: the daemon does not lower it to 2."""
    env = dict(os.environ, MALLOC_ARENA_MAX="4")
    env.pop("GLIBC_TUNABLES", None)
    out = subprocess.run([sys.executable, "-c", _ARENA_PROBE, "daemon"], check=True, env=env,
                         capture_output=True, text=True, timeout=60, cwd=REPO)
    assert int(out.stdout.strip()) > 2


def test_a_recording_brings_its_own_camera(tmp_path: Path) -> None:
    """A recording holds the vehicle's calibration (camera.yaml), so a bench run on it can say
    `camera.calibration = "builtin"`, as docs/sources.md says; the service resolves its camera
    before it opens the source, and the recording read its camera only at open(): refused,
    "camera.calibration: required for recording: sources"."""
    import json

    import cv2
    import numpy as np

    from service.daemon.wiring import resolve_camera

    folder = tmp_path / "netpose-rov-20260101T120000Z"
    folder.mkdir()
    (folder / "recording.json").write_text("{}")
    cv2.imwrite(str(folder / "000000.png"), np.zeros((360, 640), np.uint8))
    (folder / "frames.jsonl").write_text(json.dumps(
        {"frame": "000000.png", "index": 0, "t_mono": 1.0, "t_unix": 1.7e9}) + "\n")
    camera = builtin_camera(640, 360)
    save_camera(camera, folder / "camera.yaml")
    config = load_daemon_config(str(DEMO), [f"camera.url=recording:{folder}",
                                            "camera.calibration=builtin"])
    resolved = resolve_camera(config, build_source(config))
    assert (resolved.width, resolved.height) == (640, 360)
    assert (resolved.fx, resolved.cx) == pytest.approx((camera.fx, camera.cx))
    # A damaged one is named as such (not "required for recording: sources").
    (folder / "camera.yaml").write_text("image_width: 640\nimage_height: [\n")
    with pytest.raises(ConfigError) as err:
        resolve_camera(config, build_source(config))
    assert err.value.key == "camera.calibration" and "invalid YAML" in str(err.value)
    # Without its camera.yaml it still needs a calibration file, and says which key.
    (folder / "camera.yaml").unlink()
    with pytest.raises(ConfigError) as err:
        resolve_camera(config, build_source(config))
    assert err.value.key == "camera.calibration" and "camera.yaml" in str(err.value)


def test_a_calibration_for_another_frame_shape_than_the_url_asks_for_is_refused(
    tmp_path: Path
) -> None:
    """The Pi profile's camera asked for 1280x720 with a 640x480 calibration: `run --check`
    said OK, the unit ran and refused every frame. What the URL states is checked before the
    camera opens; the same sensor at another scale is fine."""
    from service.core.camera import CameraModel

    save_camera(CameraModel(width=640, height=480, fx=520.0, fy=520.0, cx=319.5, cy=239.5),
                tmp_path / "cam640x480.yaml")
    save_camera(builtin_camera(640, 360), tmp_path / "cam640x360.yaml")
    url = "camera.url=v4l2:/dev/video0?width=1280&height=720&fps=30&fourcc=MJPG"
    with pytest.raises(ConfigError) as err:
        check_config(str(DEMO), [url, f"camera.calibration={tmp_path / 'cam640x480.yaml'}",
                                 "mavlink.allow_simulated=false"])
    assert err.value.key == "camera.calibration"
    assert "640x480" in str(err.value) and "camera.url asks for 1280x720" in str(err.value)
    assert check_config(str(DEMO), [url, f"camera.calibration={tmp_path / 'cam640x360.yaml'}",
                                    "mavlink.allow_simulated=false"]).startswith("configuration OK")


def test_check_warns_of_files_the_services_sandbox_hides(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The unit runs the service with its own /tmp and without /home (PrivateTmp, ProtectHome):
    a calibration in /tmp passed `--check`, then the service exited 78 for a file it could not
    see. The check says so (a warning: outside systemd the path is fine)."""
    assert tmp_path.is_relative_to("/tmp")  # pytest's folders: where a user might put a file
    camera = tmp_path / "camera.yaml"
    save_camera(builtin_camera(640, 360), camera)
    caplog.set_level(logging.WARNING, logger="service.daemon.wiring")
    assert check_config(str(DEMO), [f"camera.calibration={camera}"]).startswith(
        "configuration OK")
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 1 and "camera.calibration" in warned[0], warned
    assert "PrivateTmp" in warned[0] and str(camera) in warned[0]
    caplog.clear()
    check_config(str(DEMO), [])  # the demo names no file: nothing to say
    assert not caplog.records
