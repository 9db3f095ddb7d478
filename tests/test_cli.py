"""`netpose <command> --help` answers for every command and sub-command.

argparse expands `%` in help strings, so a literal "25 % of a core" crashes the help of the
whole command group with a TypeError; nothing but formatting every parser finds that.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from service.cli import COMMANDS, build_parser


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
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "estimate", "-c", str(folder / "camera.yaml"),
         "--mesh-size", "0.0275", str(folder / "038.png"), str(folder / "032.png")],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert done.returncode == 0, done.stderr
    seen, measured = done.stdout.splitlines()
    assert "038.png: net seen, ~0." in seen and "no distance (plane too uncertain" in seen
    assert "032.png: net detected" in measured


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
    empty = subprocess.run(
        [sys.executable, "-m", "service.cli", "estimate", "-c", str(tmp_path / "camera.yaml"),
         "--mesh-size", "0.025", str(tmp_path / "empty")], capture_output=True, text=True,
        timeout=120)
    assert empty.returncode == 1 and "a folder without images" in empty.stdout


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
