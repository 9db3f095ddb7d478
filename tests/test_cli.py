"""`netpose <command> --help` answers for every command and sub-command.

argparse expands `%` in help strings, so a literal "25 % of a core" crashes the help of the
whole command group with a TypeError; nothing but formatting every parser finds that.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from service.cli import COMMANDS, build_parser

REPO = Path(__file__).resolve().parents[1]


def _all_parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found.extend(_all_parsers(sub))
    return found


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_help_text_formats(command: str) -> None:
    parsers = _all_parsers(build_parser([command]))
    assert len(parsers) >= 2  # the top level and the command's own parser, at least
    for parser in parsers:
        text = parser.format_help()
        assert parser.prog in text


def test_bench_help_answers_from_the_installed_command() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "bench", "--help"],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "soak" in done.stdout and "Traceback" not in done.stderr


def test_estimate_says_net_seen_for_a_frame_too_uncertain_for_a_distance() -> None:
    """A real sequence frame whose plane is too uncertain for a distance: the command says a
    net is seen, roughly how far, and that there is no distance (exit 0: nothing was wrong
    with the file)."""
    from tests.shared_data import shared_data_dir

    folder = shared_data_dir() / "real-field" / "sequence_2024-08-22_142905"
    if not folder.is_dir():
        pytest.skip(f"real-field data set not found at {folder.parent}")
    # Which few frames are measured differs between numeric stacks (OpenCV 4.6 and 5 decode
    # these frames a grey level apart): one of these is on each.
    measured = ("003.png", "032.png")
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "estimate", "-c", str(folder / "camera.yaml"),
         "--mesh-size", "0.0275", str(folder / "038.png"), *(str(folder / m) for m in measured)],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert done.returncode == 0, done.stderr
    seen, *others = done.stdout.splitlines()
    assert "038.png: net seen, ~0." in seen and "no distance (plane too uncertain" in seen
    assert any(f"{m}: net detected" in line for m, line in zip(measured, others, strict=True))


def test_estimate_reads_the_images_of_a_folder_in_name_order(tmp_path: Path) -> None:
    """`netpose estimate FOLDER` (what `images:` and `netpose calibrate` take): each image in it,
    in name order, other files left out; an empty folder is named as such (it read 'no such
    file')."""
    import cv2
    import numpy as np

    from drivers.sources.synthetic import builtin_camera
    from drivers.synthetic_net import NetPose, NetRenderer
    from service.core.camera import save_camera
    from service.core.mesh import MeshGeometry

    camera = builtin_camera(640, 360)
    save_camera(camera, tmp_path / "camera.yaml")
    frames = tmp_path / "frames"
    frames.mkdir()
    renderer = NetRenderer(camera, MeshGeometry(0.025), seed=0)
    for name, range_m in (("b.png", 1.2), ("a.jpg", 0.8)):
        image, _ = renderer.render(NetPose(range_m, tilt_deg=10.0), rng=np.random.default_rng(1))
        cv2.imwrite(str(frames / name), image)
    (frames / "notes.txt").write_text("not an image")
    (tmp_path / "empty").mkdir()
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "estimate", "-c", str(tmp_path / "camera.yaml"),
         "--mesh-size", "0.025", str(frames)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert [line.split(":")[0] for line in lines] == [str(frames / "a.jpg"), str(frames / "b.png")]
    assert all("net detected" in line for line in lines)
    # The range's sigma counts the scale's error (2 % bar and 1 % focal by default), beside
    # the image's own: a used net's bar is known to a few per cent, whatever the image says.
    for line in lines:
        found = re.search(r"range ([\d.]+) m \+- ([\d.]+) \(image ([\d.]+), scale 2\.2 %\)", line)
        assert found is not None, line
        range_m, total, image_sigma = (float(v) for v in found.groups())
        assert total == pytest.approx(math.hypot(image_sigma, 0.02236 * range_m), abs=0.001)
    empty = subprocess.run(
        [sys.executable, "-m", "service.cli", "estimate", "-c", str(tmp_path / "camera.yaml"),
         "--mesh-size", "0.025", str(tmp_path / "empty")], capture_output=True, text=True,
        timeout=120)
    assert empty.returncode == 1 and "a folder without images" in empty.stdout


def test_estimate_json_says_too_close_and_keeps_its_keys_in_order(tmp_path: Path) -> None:
    """`--json` had no `too_close`: a reader could tell "the net too close to measure" from
    "no net" only by parsing the reason; and the keys of `timings_ms` came in the order the
    stages ran, which differed between frames."""
    import json

    import cv2
    import numpy as np

    from drivers.synthetic_net import NetPose, NetRenderer, SceneStyle
    from service.benchmarks.scenes import bench_camera
    from service.core.camera import save_camera
    from service.core.mesh import MeshGeometry

    camera = bench_camera(640, 360)
    save_camera(camera, tmp_path / "camera.yaml")
    renderer = NetRenderer(camera, MeshGeometry(0.025))
    # Up close a net is out of focus (as in tests/test_integrity.py: "too close" below 0.2 m).
    style = SceneStyle(focus_m=1.5, aperture_m=0.003)
    for name, range_m in (("a_near.png", 0.16), ("b_far.png", 0.6)):
        image, _ = renderer.render(NetPose(range_m, 15.0, 30.0, 10.0), np.random.default_rng(1),
                                   style)
        cv2.imwrite(str(tmp_path / name), image)
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "estimate", "-c", str(tmp_path / "camera.yaml"),
         "--mesh-size", "0.025", "--json", str(tmp_path / "a_near.png"),
         str(tmp_path / "b_far.png")], capture_output=True, text=True, timeout=120)
    near, far = (json.loads(line) for line in done.stdout.splitlines())
    assert near["too_close"] is True and not near["detected"], near
    assert far["too_close"] is False and far["detected"] and far["level"] in (0, 1, 2), far
    for message in (near, far):
        assert list(message["timings_ms"]) == sorted(message["timings_ms"])
    assert far["sigma_distance_total_m"] == pytest.approx(
        math.hypot(far["sigma_distance_m"], 0.02236 * far["distance_m"]), abs=2e-5)
    assert near["sigma_distance_total_m"] is None
    bad = subprocess.run(
        [sys.executable, "-m", "service.cli", "estimate", "-c", str(tmp_path / "camera.yaml"),
         "--mesh-size", "0.025", "--focal-tolerance", "1.5", str(tmp_path / "b_far.png")],
        capture_output=True, text=True, timeout=120)
    assert bad.returncode == 78 and "--focal-tolerance" in bad.stderr, bad.stderr


_FIRST_NUMPY_IMPORT = """
import json, os, sys
seen = {}
class Watch:
    def find_spec(self, name, path=None, target=None):
        if name == "numpy" and not seen:
            seen.update({k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")})
        return None
sys.meta_path.insert(0, Watch())
from service.cli import main
try:
    main(["replay", "--help"])  # a command whose module imports numpy
except SystemExit:
    pass
print(json.dumps(seen))
"""


@pytest.mark.parametrize(("preset", "expected"), [(None, "1"), ("2", "2")])
def test_numpy_is_first_imported_with_one_blas_thread(preset: str | None, expected: str) -> None:
    """numpy 1.24's OpenBLAS (bookworm's) sizes its pool at numpy's import and its idle
    threads spin: the command sets one thread before any command module imports numpy, unless
    the user chose otherwise."""
    import json
    import os

    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    if preset is not None:
        env["OPENBLAS_NUM_THREADS"] = preset
    done = subprocess.run([sys.executable, "-c", _FIRST_NUMPY_IMPORT], capture_output=True,
                          text=True, timeout=60, check=False, env=env)
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.splitlines()[-1])
    assert seen == {"OPENBLAS_NUM_THREADS": expected, "OMP_NUM_THREADS": "1"}


def test_the_command_lines_log_level_wins_over_the_files() -> None:
    """`netpose --log-level WARNING run` printed every INFO line: service.log_level (INFO in
    the demo) replaced it. The command line wins, as a --set does."""
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "--log-level", "WARNING", "run", "--config",
         str(Path(__file__).resolve().parents[1] / "config" / "demo.toml"), "--duration", "2",
         "--set", "telemetry.enabled=false"],
        capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert " INFO " not in done.stdout + done.stderr


_SIGNAL_WHILE_STARTING = """
import os, signal, sys, time
class Gate:
    def find_spec(self, name, path=None, target=None):
        if name == "service.commands.run":  # the heavy imports of start-up begin here
            os.kill(os.getpid(), getattr(signal, sys.argv[1]))
            time.sleep(0.05)
        return None
sys.meta_path.insert(0, Gate())
from service.cli import main
sys.exit(main(["run", "--config", sys.argv[2], "--duration", "3",
               "--set", "telemetry.enabled=false"]))
"""


@pytest.mark.parametrize("sig", ["SIGHUP", "SIGTERM"])
def test_a_signal_while_the_service_starts_is_acted_on_not_fatal(sig: str) -> None:
    """systemd may signal the service from its first moment: a `systemctl reload` while it was
    still importing ended it (SIGHUP's default action, exit 129, and a restart), a stop ended it
    with 143. A reload now happens once the daemon is up; a stop is a clean stop."""
    demo = Path(__file__).resolve().parents[1] / "config" / "demo.toml"
    done = subprocess.run([sys.executable, "-c", _SIGNAL_WHILE_STARTING, sig, str(demo)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    if sig == "SIGHUP":
        assert "configuration reloaded" in done.stderr
    else:
        assert "SIGTERM received: stopping" in done.stderr


@pytest.mark.parametrize(("args", "said"), [
    # a typo in an ExecStart= of a drop-in
    (["run", "--config", "/etc/netpose/netpose.toml", "--chek"], "unrecognized arguments: --chek"),
    (["rn", "--config", "/etc/netpose/netpose.toml"], "invalid choice: 'rn'"),
    (["mavlink-check", "--timeout", "soon"], "invalid float value: 'soon'"),
    (["bench", "damage", "--frames", "0"], "--frames: must be at least 1"),
    # replay's, estimate's and undistort's own checks of their options said 1, "other bad input"
    (["replay", "/nonexistent.mp4", "--every", "0", "--out", "/nonexistent/out"],
     "--every: must be at least 1"),
    (["replay", "/nonexistent.mp4", "--mesh-size", "0.0275", "--out", "/nonexistent/out"],
     "--calibration: required"),
    (["estimate", "/nonexistent.png", "-c", "/nonexistent.yaml", "--mesh-size", "27.5"],
     "--mesh-size: must be"),  # it named the key inside, mesh.bar_length_m
    (["undistort", "/nonexistent.png", "-c", "/nonexistent.yaml", "-o", "/nonexistent/o.png",
      "--alpha", "2"], "--alpha: must be"),
    ([], "usage: netpose"),  # no command: the help, listing them
])
def test_command_line_mistakes_exit_78_as_the_docs_and_the_unit_say(
        args: list[str], said: str) -> None:
    """argparse exits 2 on a usage error, but the docs (and `mavlink-check --help`) said 78, and
    the unit's RestartPreventExitStatus=78 did not cover 2: a typo in an ExecStart= of a
    drop-in restarted the service every 2 s for ever. A mistake on the command line is a
    configuration error like any other: 78 (EX_CONFIG), saying what is wrong."""
    done = subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True,
                          text=True, timeout=60, check=False)
    assert done.returncode == 78, (done.returncode, done.stdout, done.stderr)
    assert said in done.stdout + done.stderr and "Traceback" not in done.stderr


def test_a_camera_that_is_away_is_said_once_not_by_opencv_on_every_retry(tmp_path: Path) -> None:
    """OpenCV's own warning came with every retry of a missing camera (17 lines in 4 s of a
    service whose source already says why, once); the command quiets OpenCV's log unless the
    user set OPENCV_LOG_LEVEL."""
    import os

    from drivers.sources.synthetic import builtin_camera
    from service.core.camera import save_camera

    save_camera(builtin_camera(1280, 720), tmp_path / "camera.yaml")
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_LOG_LEVEL"}
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "run", "--config",
         str(Path(__file__).parents[1] / "config" / "demo.toml"),
         "--set", "camera.url=v4l2:/dev/video77", "--set",
         f"camera.calibration={tmp_path / 'camera.yaml'}", "--set",
         "mavlink.allow_simulated=false", "--set", "telemetry.enabled=false",
         "--duration", "3"],
        capture_output=True, text=True, timeout=60, env=env, cwd=Path(__file__).parents[1],
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "frame source v4l2:/dev/video77 down: cannot open /dev/video77" in done.stderr
    assert "WARN:" not in done.stderr, done.stderr[-2000:]


def _saved_camera(folder: Path) -> Path:
    from drivers.sources.synthetic import builtin_camera
    from service.core.camera import save_camera

    path = folder / "camera.yaml"
    save_camera(builtin_camera(640, 360), path)
    return path


def test_estimate_counts_failures_against_the_images_not_the_arguments(tmp_path: Path) -> None:
    """One folder of three images, two of them broken: "2 of 1 images" it said."""
    import cv2
    import numpy as np

    camera = _saved_camera(tmp_path)
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "a.png"), np.full((360, 640), 128, np.uint8))
    (frames / "b.png").write_bytes(b"x")
    (frames / "c.png").write_bytes((frames / "a.png").read_bytes()[:200])
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "estimate", "-c", str(camera), "--mesh-size",
         "0.025", str(frames)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert "netpose: 2 of 3 images could not be processed" in done.stderr


def test_a_file_that_cannot_be_written_is_one_line_not_a_traceback(tmp_path: Path) -> None:
    """A full disk (/dev/full) under `estimate`'s output, a missing folder for `schema
    --update`: an OSError came out as a traceback."""
    schema = subprocess.run(
        [sys.executable, "-m", "service.cli", "schema", "--update",
         str(tmp_path / "nowhere" / "telemetry.md")], capture_output=True, text=True, timeout=60)
    assert schema.returncode == 1 and "Traceback" not in schema.stderr, schema.stderr
    assert "nowhere" in schema.stderr and len(schema.stderr.strip().splitlines()) == 1
    camera = _saved_camera(tmp_path)
    with open("/dev/full", "w") as full:
        done = subprocess.run(
            [sys.executable, "-m", "service.cli", "estimate", "-c", str(camera), "--mesh-size",
             "0.025", str(tmp_path / "missing.png")], stdout=full, stderr=subprocess.PIPE,
            text=True, timeout=120)
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    assert "No space left on device" in done.stderr


def test_undistort_never_overwrites_its_input_and_asks_before_another_file(
        tmp_path: Path) -> None:
    import cv2
    import numpy as np

    camera = _saved_camera(tmp_path)
    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), np.full((360, 640, 3), 90, np.uint8))
    original = image.read_bytes()

    def undistort(output: Path, *extra: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "service.cli", "undistort", str(image), "-c", str(camera),
             "-o", str(output), *extra], capture_output=True, text=True, timeout=120)

    for extra in ((), ("--force",)):
        same = undistort(tmp_path / "." / "frame.png", *extra)
        assert same.returncode == 78 and "would overwrite the input" in same.stderr
        assert image.read_bytes() == original
    other = tmp_path / "undistorted.png"
    other.write_bytes(b"keep me")
    refused = undistort(other)
    assert refused.returncode == 78 and "--force" in refused.stderr
    assert other.read_bytes() == b"keep me"
    assert undistort(other, "--force").returncode == 0
    assert cv2.imread(str(other)) is not None


def test_the_service_keeps_its_traceback_for_an_os_error(monkeypatch: pytest.MonkeyPatch) -> None:
    """The one-line OSError message is for the offline commands; the daemon's (a port in use,
    a serial port's EIO mid-run) goes to the journal with where it happened."""
    import errno

    import service.commands.run as run_command
    from service.cli import main

    def in_use(*_args: object, **_kwargs: object) -> int:
        raise OSError(errno.EADDRINUSE, "Address already in use")

    monkeypatch.setattr(run_command, "main", in_use)
    watched = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
    before = {sig: signal.getsignal(sig) for sig in watched}
    try:  # `run` takes the service's signals from its first moment: given back after
        with pytest.raises(OSError, match="Address already in use"):
            main(["run", "--config", "config/demo.toml"])
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def _warn_once(tmp_path: Path, env: dict[str, str], stderr_file: Path) -> str:
    """`run --check` with a world-readable signing key: a WARNING, then "configuration OK"."""
    key = tmp_path / "mav.key"
    key.write_text("00" * 32)
    key.chmod(0o644)
    with open(stderr_file, "w") as err:
        stat = os.fstat(err.fileno())
        env = {**env, **({"JOURNAL_STREAM": f"{stat.st_dev}:{stat.st_ino}"}
                         if "JOURNAL_STREAM" in env else {})}
        done = subprocess.run(
            [sys.executable, "-m", "service.cli", "run", "--config", str(REPO / "config" /
                                                                           "demo.toml"),
             "--check", "--set", f"mavlink.signing_key_file={key}"],
            stdout=subprocess.PIPE, stderr=err, text=True, timeout=60, env=env, check=False)
    assert done.returncode == 0, stderr_file.read_text()
    return stderr_file.read_text()


def test_log_lines_carry_their_priority_for_the_journal(tmp_path: Path) -> None:
    """Under systemd every line went to the journal as priority info (`journalctl -u netpose
    -p warning` showed nothing), with a second timestamp beside the journal's own. With stderr
    connected to the journal (JOURNAL_STREAM names it), each line starts with its syslog
    priority (<4> a warning) and no timestamp; elsewhere lines keep their timestamp."""
    env = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
    journal = _warn_once(tmp_path, {**env, "JOURNAL_STREAM": ""}, tmp_path / "journal.txt")
    line = next(x for x in journal.splitlines() if "readable by every user" in x)
    assert line.startswith("<4>"), line
    assert not any(ch.isdigit() for ch in line[3:7]), line  # no date first
    console = _warn_once(tmp_path, env, tmp_path / "console.txt")
    line = next(x for x in console.splitlines() if "readable by every user" in x)
    assert line[:4].isdigit() and "WARNING" in line, line
