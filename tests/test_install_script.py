"""systemd/install.sh run for real (`sh install.sh` in a subprocess), in a sandbox.

PREFIX, CONF_DIR and UNIT_DIR point into a temporary folder. What would change the machine or
needs root is a stand-in first on PATH: `id` (root), `useradd`/`usermod`/`getent` (the netpose
user), `dpkg`/`apt-get` (Debian packages), `install` (without -o/-g: no netpose group here),
`runuser` (the check runs as this user), `systemd-analyze` and `systemctl`, which records its
calls and answers `is-active` as the test says. The configuration check is the real `netpose run
--check`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
INSTALL = REPO / "systemd" / "install.sh"

_STANDINS = {
    "id": 'case "$1" in -u) echo 0 ;; esac\n',  # root; and the netpose user exists
    "useradd": 'echo "useradd $*" >> "$SANDBOX_LOG"\n',
    "usermod": 'echo "usermod $*" >> "$SANDBOX_LOG"\n',
    "getent": "exit 0\n",
    "dpkg": "exit 0\n",  # every Debian package is present: apt-get is not needed
    "apt-get": 'echo "apt-get $*" >> "$SANDBOX_LOG"; exit 1\n',
    "systemd-analyze": "exit 0\n",
    "runuser": 'while [ "$1" != "--" ]; do shift; done; shift; exec "$@"\n',
    "systemctl": (
        'echo "systemctl $*" >> "$SANDBOX_LOG"\n'
        'case "$1" in is-active) [ "$SANDBOX_UNIT_ACTIVE" = 1 ] ;; esac\n'
    ),
    # install(1) without -o/-g: the sandbox has no netpose group and need not be root.
    "install": (
        'n=$#\n'
        'while [ "$n" -gt 0 ]; do\n'
        '    a=$1; shift; n=$((n - 1))\n'
        '    case "$a" in\n'
        '        -o|-g) shift; n=$((n - 1)) ;;\n'
        '        *) set -- "$@" "$a" ;;\n'
        '    esac\n'
        'done\n'
        'exec {install} "$@"\n'
    ),
}


@dataclass
class Sandbox:
    root: Path
    prefix: Path
    conf_dir: Path
    unit_dir: Path
    log: Path
    env: dict[str, str]

    def calls(self) -> list[str]:
        return self.log.read_text().splitlines() if self.log.exists() else []


def make_sandbox(root: Path) -> Sandbox:
    bin_dir = root / "bin"
    bin_dir.mkdir()
    real_install = shutil.which("install")
    assert real_install is not None
    for name, body in _STANDINS.items():
        path = bin_dir / name
        path.write_text("#!/bin/sh\n" + body.replace("{install}", real_install))
        path.chmod(0o755)
    sandbox = Sandbox(root, root / "opt" / "netpose", root / "etc" / "netpose",
                      root / "systemd", root / "calls.log", {})
    sandbox.unit_dir.mkdir(parents=True)
    sandbox.env = {
        **os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
        "PREFIX": str(sandbox.prefix), "CONF_DIR": str(sandbox.conf_dir),
        "UNIT_DIR": str(sandbox.unit_dir), "BIN_DIR": str(root / "usr-local-bin"),
        "SANDBOX_LOG": str(sandbox.log),
        "SANDBOX_UNIT_ACTIVE": "0",
    }
    return sandbox


def stand_in_venv(sandbox: Sandbox) -> None:
    """$PREFIX/venv as install.sh finds it on an upgrade, with pip recorded (and doing
    nothing: `pip wheel` exits with SANDBOX_PIP_WHEEL, 0 unless told), and netpose this
    checkout's."""
    venv_bin = sandbox.prefix / "venv" / "bin"
    venv_bin.mkdir(parents=True)
    (venv_bin / "python").write_text(
        "#!/bin/sh\n"
        'if [ "$1 $2" = "-m pip" ]; then\n'
        '    echo "$*" >> "$SANDBOX_LOG"\n'
        '    [ "$3" = wheel ] && exit "${SANDBOX_PIP_WHEEL:-0}"\n'
        "    exit 0\n"
        "fi\n"
        f'exec "{sys.executable}" "$@"\n'
    )
    (venv_bin / "netpose").write_text(
        f'#!/bin/sh\nPYTHONPATH="{REPO}" exec "{sys.executable}" -m service.cli "$@"\n')
    for path in venv_bin.iterdir():
        path.chmod(0o755)


def run_install(sandbox: Sandbox, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["sh", str(INSTALL)], cwd=sandbox.root, capture_output=True,
                          text=True, timeout=300, env={**sandbox.env, **env}, check=False)


def _rejected_upgrade(
    tmp_path: Path, active: bool
) -> tuple[Sandbox, subprocess.CompletedProcess[str]]:
    """An upgrade whose new code rejects the configuration in /etc (here: the profile's mesh
    size was never set)."""
    sandbox = make_sandbox(tmp_path)
    stand_in_venv(sandbox)
    done = run_install(sandbox, SANDBOX_UNIT_ACTIVE="1" if active else "0")
    return sandbox, done


def test_a_rejected_configuration_while_the_old_version_runs_fails_the_upgrade(
        tmp_path: Path) -> None:
    """The check of the new code failed, yet the script said "not started ... then: systemctl
    start netpose" and exited 0, while the unit was running the previous version: a start
    does nothing to an active unit, so the new code never loaded (and at the next boot the
    unit exits 78 and stays down). It says what runs, asks for a restart, and exits 78."""
    sandbox, done = _rejected_upgrade(tmp_path, active=True)
    assert done.returncode == 78, done.stdout + done.stderr
    assert "mesh.bar_length_m" in done.stderr  # the check's own line, naming the key
    assert "keeps the previous version" in done.stderr
    assert "systemctl restart netpose" in done.stderr
    assert "systemctl start netpose" not in done.stderr
    assert not [c for c in sandbox.calls() if c.startswith(("systemctl restart",
                                                            "systemctl start"))]
    assert "systemctl enable netpose.service" in sandbox.calls()


def test_new_code_that_does_not_run_is_not_blamed_on_the_configuration(tmp_path: Path) -> None:
    """A new version that fails to import (exit 1) was reported as "rejects your
    configuration ... fix the file": the file was never judged, and the service would crash
    and restart every few seconds, not stay down as it does on exit 78."""
    sandbox = make_sandbox(tmp_path)
    stand_in_venv(sandbox)
    (sandbox.prefix / "venv" / "bin" / "netpose").write_text(
        "#!/bin/sh\necho 'ImportError: numpy.core.multiarray failed to import' >&2\nexit 1\n")
    done = run_install(sandbox, CONFIG="config/demo.toml", SANDBOX_UNIT_ACTIVE="1")
    assert done.returncode == 1, done.stdout + done.stderr
    assert "does not run" in done.stderr and "was not judged" in done.stderr
    assert "rejects" not in done.stderr
    assert not [c for c in sandbox.calls() if c.startswith(("systemctl restart",
                                                            "systemctl start"))]


def test_a_rejected_configuration_of_a_stopped_service_fails_the_install(tmp_path: Path) -> None:
    sandbox, done = _rejected_upgrade(tmp_path, active=False)
    assert done.returncode == 78, done.stdout + done.stderr
    assert "not running" in done.stderr and "systemctl start netpose" in done.stderr
    assert "previous version" not in done.stderr
    assert not [c for c in sandbox.calls() if c.startswith(("systemctl restart",
                                                            "systemctl start"))]


def test_an_upgrade_with_a_valid_configuration_restarts_the_running_service(
        tmp_path: Path) -> None:
    sandbox = make_sandbox(tmp_path)
    stand_in_venv(sandbox)
    done = run_install(sandbox, CONFIG="config/demo.toml", SANDBOX_UNIT_ACTIVE="1")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "upgraded and restarted" in done.stdout
    assert "systemctl restart netpose.service" in sandbox.calls()
    # The command the docs write (`sudo netpose mavlink-check ...`) is on PATH, into the venv.
    command = sandbox.root / "usr-local-bin" / "netpose"
    assert command.is_symlink() and command.resolve() == (sandbox.prefix / "venv" / "bin" /
                                                          "netpose").resolve()


# What pip and the build backend bring into a venv; the sandbox's venv keeps its own.
_BUILD_TOOLS = ("pip", "setuptools", "wheel", "_distutils_hack", "pkg_resources",
                "distutils-precedence", "netpose", "__editable__")


def real_venv(sandbox: Sandbox, python: str) -> Path:
    """$PREFIX/venv made as install.sh makes it, from `python`, holding netpose's dependencies
    the way a vehicle's venv does after an earlier install: here, this test's own packages,
    reached through a .pth (not netpose itself, pip or the build backend: the venv's own)."""
    venv = sandbox.prefix / "venv"
    subprocess.run([python, "-m", "venv", "--system-site-packages", str(venv)], check=True,
                   capture_output=True, timeout=120)
    deps = sandbox.root / "deps"
    deps.mkdir()
    site_packages = next(Path(p) for p in sys.path if p.endswith("site-packages")
                         and Path(p).is_relative_to(sys.prefix))
    for entry in site_packages.iterdir():
        if not entry.name.startswith(_BUILD_TOOLS) and not entry.name.endswith(".pth"):
            (deps / entry.name).symlink_to(entry)
    venv_site = next((venv / "lib").glob("python3*/site-packages"))
    (venv_site / "netpose-test-deps.pth").write_text(f"{deps}\n")
    return venv


def offline(env: dict[str, str]) -> dict[str, str]:
    """No package index and no local wheels: pip config files and PIP_FIND_LINKS left out."""
    kept = {k: v for k, v in env.items() if not k.startswith("PIP_")}
    return {**kept, "PIP_NO_INDEX": "1", "PIP_CONFIG_FILE": os.devnull}


def _python_with_build_backend() -> str | None:
    """An interpreter whose venvs build netpose without downloading anything: setuptools>=66
    (pyproject's build-system) and wheel, as Debian bookworm's python3-setuptools and
    python3-wheel give a --system-site-packages venv on a Pi. Same minor version as this one:
    the sandbox's venv shares this test's compiled packages."""
    probe = ("import sys, setuptools, wheel; "
             "sys.exit(int(setuptools.__version__.split('.')[0]) < 66)")
    for candidate in (getattr(sys, "_base_executable", sys.executable), "/usr/bin/python3"):
        if not Path(candidate).exists():
            continue
        version = subprocess.run(
            [candidate, "-c", "import sys; print(sys.version_info[:2]); " + probe],
            capture_output=True, text=True, timeout=60, check=False)
        if version.returncode == 0 and version.stdout.strip() == str(sys.version_info[:2]):
            return candidate
    return None


def test_an_upgrade_installs_offline_when_the_venv_has_the_build_backend(
        tmp_path: Path) -> None:
    """Fish-farm companions are often offline. pip built netpose in an isolated environment
    and downloaded setuptools for it, even with every dependency and a suitable setuptools in
    the venv: with no index the upgrade failed. It builds with the venv's own backend then."""
    python = _python_with_build_backend()
    if python is None:
        pytest.skip("no Python with setuptools>=66 and wheel (Debian's python3-setuptools, "
                    "python3-wheel) to make the sandbox's venv from")
    sandbox = make_sandbox(tmp_path)
    venv = real_venv(sandbox, python)
    done = subprocess.run(["sh", str(INSTALL)], cwd=sandbox.root, capture_output=True,
                          text=True, timeout=600, check=False,
                          env=offline({**sandbox.env, "CONFIG": "config/demo.toml"}))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "installed and enabled" in done.stdout
    shown = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "show", "-f", "netpose"],
                           capture_output=True, text=True, timeout=60, check=True).stdout
    assert f"Location: {venv}" in shown  # in the sandbox's venv, from $PREFIX/src
    assert "service/cli.py" in shown


def test_a_venv_that_cannot_build_netpose_itself_builds_it_the_usual_way(tmp_path: Path) -> None:
    """The trial build without an index failed (no suitable setuptools, or no wheel): pip
    then builds netpose in its isolated environment, as before, and the script says that this
    downloads the backend."""
    sandbox = make_sandbox(tmp_path)
    stand_in_venv(sandbox)
    done = run_install(sandbox, CONFIG="config/demo.toml", SANDBOX_PIP_WHEEL="1")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "cannot build netpose itself" in done.stdout
    trial, install = [c for c in sandbox.calls() if c.startswith("-m pip")]
    assert "--no-index" in trial and "--no-build-isolation" in trial
    assert install.startswith("-m pip install") and "--no-build-isolation" not in install
    (tmp_path / "ok").mkdir()
    ok = make_sandbox(tmp_path / "ok")
    stand_in_venv(ok)
    assert run_install(ok, CONFIG="config/demo.toml").returncode == 0
    assert [c for c in ok.calls() if c.startswith("-m pip install")] == [
        f"-m pip install --quiet --prefer-binary --upgrade --no-build-isolation {ok.prefix}/src"]
