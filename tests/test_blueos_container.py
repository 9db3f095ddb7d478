"""The BlueOS extension image (blueos/Dockerfile), built and run with a real container engine.

Builds the image for this machine's architecture, checks the labels BlueOS reads, starts it
as BlueOS would (host network, the extension's data folder as /data, holding a configuration
on the demo source), and checks that the daemon runs, the page and /register_service answer,
and that a stop (SIGTERM) ends it cleanly.

Runs only where a container engine works (podman or docker) and a Debian bookworm base image
is at hand: $NETPOSE_CONTAINER_BASE, else localhost/bookworm-base:latest (made by
blueos/build-base.sh), else debian:bookworm-slim if the engine already has it. Otherwise it is
skipped, saying why, in well under a second per probe. The first build takes minutes (Debian's
OpenCV and SciPy); the engine's layer cache makes later ones quick.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.net import free_port
from service import __version__
from tests.web_harness import REPO, PageClient, demo_config

IMAGE = "localhost/netpose-test:ci"
BASES = ("localhost/bookworm-base:latest", "debian:bookworm-slim")
HOST_CA = "/etc/ssl/certs/ca-certificates.crt"


def _engine() -> tuple[str, str]:
    """(engine, base image) or pytest.skip with the reason."""
    reasons = []
    for name in ("podman", "docker"):
        path = shutil.which(name)
        if path is None:
            reasons.append(f"no {name}")
            continue
        try:
            info = subprocess.run([path, "info"], capture_output=True, text=True, timeout=20)
        except subprocess.TimeoutExpired:
            reasons.append(f"{name} info timed out")
            continue
        if info.returncode != 0:
            reasons.append(f"{name} does not work here ({info.stderr.strip().splitlines()[-1:]})")
            continue
        wanted = [os.environ["NETPOSE_CONTAINER_BASE"]] if os.environ.get(
            "NETPOSE_CONTAINER_BASE") else list(BASES)
        for base in wanted:
            probe = subprocess.run([path, "image", "inspect", base], capture_output=True,
                                   timeout=20)
            if probe.returncode == 0:
                return path, base
        reasons.append(f"{name} has none of the base images {', '.join(wanted)} (make one "
                       "with blueos/build-base.sh)")
    pytest.skip("container test skipped: " + "; ".join(reasons))


@pytest.fixture(scope="module")
def image() -> Iterator[tuple[str, str]]:
    engine, base = _engine()
    started = time.monotonic()
    extra = []
    if Path(engine).name == "podman" and Path(HOST_CA).is_file():
        # Where TLS to PyPI is intercepted by a local CA, pip in the build needs the host's
        # bundle (mounted for the build only, blueos/Dockerfile).
        extra = ["-v", f"{HOST_CA}:/run/host-ca.crt:ro"]
    build = subprocess.run(
        [engine, "build", *extra, "--build-arg", f"BASE={base}", "-f", "blueos/Dockerfile",
         "-t", IMAGE, "."], cwd=REPO, capture_output=True, text=True, timeout=3000)
    assert build.returncode == 0, build.stdout[-4000:] + build.stderr[-4000:]
    print(f"\nimage built in {time.monotonic() - started:.0f} s on {base}")
    yield engine, base


def _label(engine: str, name: str) -> str:
    out = subprocess.run([engine, "image", "inspect", IMAGE, "--format",
                          "{{json .Config.Labels}}"], capture_output=True, text=True,
                         timeout=30, check=True).stdout
    return str(json.loads(out)[name])


@pytest.mark.timeout(3600)
def test_labels_are_what_blueos_reads(image: tuple[str, str]) -> None:
    engine, _ = image
    for plain in ("version", "type", "readme", "requirements"):
        assert _label(engine, plain)
    assert _label(engine, "version") == __version__
    assert _label(engine, "type") in ("device-integration", "example", "tool", "other")
    permissions = json.loads(_label(engine, "permissions"))  # Kraken: json.loads
    host = permissions["HostConfig"]
    assert host["NetworkMode"] == "host"
    assert "/usr/blueos/extensions/netpose:/data" in host["Binds"]
    assert "/dev:/dev" in host["Binds"] and host["Privileged"] is True
    authors = json.loads(_label(engine, "authors"))
    assert isinstance(authors, list) and authors[0]["name"]
    assert json.loads(_label(engine, "company"))["name"]
    assert set(json.loads(_label(engine, "links"))) >= {"website", "support"}
    tags = json.loads(_label(engine, "tags"))
    assert 0 < len(tags) <= 10 and all(t == t.lower() and " " not in t for t in tags)
    size = subprocess.run([engine, "image", "inspect", IMAGE, "--format", "{{.Size}}"],
                          capture_output=True, text=True, timeout=30, check=True).stdout
    print(f"image size {int(size) / 1e6:.0f} MB")


@pytest.mark.timeout(3600)
def test_the_extension_runs_the_daemon_and_serves_the_page(
        image: tuple[str, str], tmp_path: Path) -> None:
    engine, _ = image
    port = free_port()
    data = tmp_path / "data"
    data.mkdir()
    demo_config(data / "netpose.toml", {"enabled": True, "host": "0.0.0.0", "port": port})
    name = f"netpose-test-{port}"
    run = subprocess.run([engine, "run", "-d", "--name", name, "--network", "host",
                          "-v", f"{data}:/data", IMAGE], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    try:
        client = PageClient(port)
        deadline = time.monotonic() + 120
        while True:
            try:
                status, service = client.request("GET", "/register_service", timeout_s=5)
                if status == 200:
                    break
            except OSError:
                pass
            assert time.monotonic() < deadline, _logs(engine, name)
            time.sleep(1.0)
        assert service["name"] == "netpose" and service["works_in_relative_paths"] is True
        assert b"<title>netpose</title>" in client.request("GET", "/")[1]
        assert client.request("GET", "/api/settings")[1]["path"] == "/data/netpose.toml"
        texts, frames = client.collect(6.0)
        estimates = [t for t in texts if t["kind"] == "estimate"]
        assert any(e["detected"] for e in estimates), _logs(engine, name)
        assert frames and frames[-1][1][:3] == b"\xff\xd8\xff"
    finally:
        stop = subprocess.run([engine, "stop", "-t", "15", name], capture_output=True,
                              text=True, timeout=60)
        logs = _logs(engine, name)
        code = subprocess.run([engine, "inspect", name, "--format", "{{.State.ExitCode}}"],
                              capture_output=True, text=True, timeout=30).stdout.strip()
        subprocess.run([engine, "rm", "-f", name], capture_output=True, timeout=60)
    assert stop.returncode == 0 and code == "0", logs
    assert "stopped cleanly" in logs


def _logs(engine: str, name: str) -> str:
    out = subprocess.run([engine, "logs", name], capture_output=True, text=True, timeout=30)
    return out.stdout[-6000:] + out.stderr[-6000:]


# --- without a container engine: what the files say ----------------------------------------


def _label_text(name: str) -> str:
    """A LABEL's value as the Dockerfile writes it (quotes and line continuations removed)."""
    text = (REPO / "blueos" / "Dockerfile").read_text(encoding="utf-8").replace("\\\n", "")
    for line in text.splitlines():
        prefix = f"LABEL {name}="
        if line.startswith(prefix):
            return line[len(prefix):].strip().strip("'\"")
    raise AssertionError(f"no LABEL {name}")


def test_the_docs_give_the_manual_install_the_labels_permissions() -> None:
    """BlueOS's create dialog does not read the image's permissions label: the docs said to
    leave Custom settings empty, which gave a container without the host network, /dev or the
    data folder (lost at every update). The JSON to paste must be the label's."""
    docs = (REPO / "docs" / "blueos.md").read_text(encoding="utf-8")
    section = docs.split("### From the Extensions Manager", 1)[1]
    pasted = json.loads(section.split("```json\n", 1)[1].split("\n```", 1)[0])
    assert pasted == json.loads(_label_text("permissions"))


def _entrypoint(data: Path, tmp_path: Path, **env_extra: str
                ) -> subprocess.CompletedProcess[str]:
    """The extension's entrypoint on `data`, with a stand-in for the netpose command (and the
    repository's config/ for the image's)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    fake = bin_dir / "netpose"
    fake.write_text("#!/bin/sh\necho \"netpose $*\"\n")
    fake.chmod(0o755)
    env = dict(os.environ, NETPOSE_DATA=str(data), PATH=f"{bin_dir}:{os.environ['PATH']}",
               NETPOSE_CONFIG_DIR=str(REPO / "config"), **env_extra)
    return subprocess.run(["sh", str(REPO / "blueos" / "entrypoint.sh")], env=env,
                          capture_output=True, text=True, timeout=10, check=False)


def test_the_extension_warns_when_its_data_is_not_the_vehicles_folder(tmp_path: Path) -> None:
    """Installed without the permissions, /data is a volume of the container, and the next
    update takes the configuration with it: said at every start, in the log BlueOS shows."""
    data = tmp_path / "data"
    data.mkdir()
    (data / "netpose.toml").write_text("")
    unmounted = _entrypoint(data, tmp_path)
    assert unmounted.returncode == 0, unmounted.stderr
    assert "WARNING" in unmounted.stderr and "lost at the next update" in unmounted.stderr
    assert f"netpose run --config {data}/netpose.toml" in unmounted.stdout
    shm = Path("/dev/shm")
    if not os.path.ismount(shm) or not os.access(shm, os.W_OK):
        pytest.skip("no writable mount point to stand in for the vehicle's folder")
    keep = shm / "netpose.toml"
    existed = keep.exists()
    try:
        if not existed:
            keep.write_text("")
        bound = _entrypoint(shm, tmp_path)
    finally:
        if not existed:
            keep.unlink(missing_ok=True)
    assert bound.returncode == 0 and "WARNING" not in bound.stderr, bound.stderr


def test_the_first_start_speaks_as_the_vehicle_blueos_names(tmp_path: Path) -> None:
    """BlueOS hands every extension the vehicle's MAVLink id (MAV_SYSTEM_ID); netpose spoke as
    system 1 whatever it was. The first start writes it into the configuration (a number
    1..255; anything else leaves the file's)."""
    import tomllib

    for given, expected in (("7", 7), ("abc", 1), ("300", 1)):
        data = tmp_path / f"data-{given}"
        data.mkdir()
        done = _entrypoint(data, tmp_path, MAV_SYSTEM_ID=given)
        assert done.returncode == 0, done.stderr
        config = tomllib.loads((data / "netpose.toml").read_text())
        assert config["mavlink"]["source_system"] == expected, given
