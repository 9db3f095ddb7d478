"""Configuration: defaults, validation naming the key, overrides, digest, shipped examples."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Literal

import pytest

from service.config import (
    CameraSettings,
    Config,
    ServiceSettings,
    build_section,
    load_config,
    parse_override,
)
from service.core.errors import ConfigError
from service.core.tracking import FilterSettings
from service.daemon.wiring import driver_sections

REPO = Path(__file__).resolve().parents[1]
CONFIG_DIR = REPO / "config"

MINIMAL = '[camera]\nurl = "synthetic:"\n[mesh]\nbar_length_m = 0.025\n'


@dataclasses.dataclass(frozen=True)
class LinkSettings:
    """Stands in for a driver's settings dataclass (the daemon passes the real ones)."""

    url: str = "udpout:127.0.0.1:14550"
    rate_hz: float = 10.0
    system_id: int = 1
    enabled: bool = True
    mode: Literal["a", "b"] = "a"
    endpoints: tuple[str, ...] = ()
    note: str | None = None

    def __post_init__(self) -> None:
        if not 1.0 <= self.rate_hz <= 50.0:
            raise ConfigError("rate_hz", "must be 1..50 Hz")


def write(tmp_path: Path, text: str, name: str = "netpose.toml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_defaults_fill_every_section(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, MINIMAL))
    assert cfg.camera == CameraSettings(url="synthetic:")
    assert cfg.filter == FilterSettings()
    assert cfg.service == ServiceSettings()
    assert cfg.mesh.bar_length_m == 0.025 and cfg.mesh.opening_angle_deg == 90.0
    assert cfg.effective["filter"]["gate_sigma"] == FilterSettings().gate_sigma
    assert cfg.digest.startswith("sha256:") and len(cfg.digest) == len("sha256:") + 16


def test_missing_required_key_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, "[camera]\nurl = 'synthetic:'\n[filter]\ngate_sigma = 3.0\n"))
    assert info.value.key == "mesh.bar_length_m"
    assert "required" in info.value.problem
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, "[mesh]\nbar_length_m = 0.02\n"))
    assert info.value.key == "camera.url" and "required" in info.value.problem
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, "[camera]\nurl = ''\n[mesh]\nbar_length_m = 0.02\n"))
    assert info.value.key == "camera.url"


def test_a_file_with_a_byte_order_mark_reads_like_one_without(tmp_path: Path) -> None:
    plain = load_config(write(tmp_path, MINIMAL))
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf" + MINIMAL.encode())
    assert load_config(p).effective == plain.effective


@pytest.mark.parametrize(
    ("text", "key", "words"),
    [
        ("[filter]\ngate_sigmaa = 3.0\n", "filter.gate_sigmaa", "unknown key"),
        ("[filtre]\ngate_sigma = 3.0\n", "filtre", "unknown section"),
        ("[filter]\ngate_sigma = 'wide'\n", "filter.gate_sigma", "must be a number"),
        ("[filter]\nacquire_count = 2.5\n", "filter.acquire_count", "must be an integer"),
        ("[filter]\nacquire_count = true\n", "filter.acquire_count", "must be an integer"),
        ("[filter]\ngate_sigma = -1\n", "filter.gate_sigma", "positive"),
        ("[filter]\ngate_sigma = nan\n", "filter.gate_sigma", "finite"),
        ("[service]\nlog_level = 'LOUD'\n", "service.log_level", "must be one of"),
        ("[camera]\nurl = 'synthetic:'\nread_timeout_s = 2.0\n[mesh]\nbar_length_m = 0.025\n",
         "camera.read_timeout_s", "within a second"),
        ("[telemetry]\nconnect = ['tcp/127.0.0.1']\n", "telemetry.connect", "needs a port"),
        ("[telemetry]\nlisten = ['tcp/10.0.0.300:7447']\n", "telemetry.listen", "invalid IPv4"),
        ("[mavlink]\nallow_simulated = 'yes'\n", "mavlink.allow_simulated", "true or false"),
        ("[link]\nrate_hz = 500.0\n", "link.rate_hz", "1..50"),
        ("[link]\nendpoints = [1, 2]\n", "link.endpoints", "must be a string"),
        ("[link]\nmode = 'c'\n", "link.mode", "must be one of"),
        ("filter = 3\n", "filter", "must be a table"),
        # Each names its own key (they named grid_cols, source.stall_timeout_s, retry_max_s).
        ("[estimator]\ngrid_rows = 13\n", "estimator.grid_rows", "2..12"),
        ("[camera]\nurl = 'synthetic:'\nstale_after_s = 7200\n[mesh]\nbar_length_m = 0.025\n",
         "camera.stale_after_s", "at most 3600"),
        ("[telemetry]\nretry_initial_s = 0\n", "telemetry.retry_initial_s", "> 0"),
        ("[mavlink]\nmax_age_s = 0.001\n", "mavlink.max_age_s", "0.1..2"),
        ("[camera]\nurl = 'synthetic:'\nfocal_tolerance = -0.01\n[mesh]\nbar_length_m = 0.025\n",
         "camera.focal_tolerance", "fraction 0..0.25"),
        ("[camera]\nurl = 'synthetic:'\n[mesh]\nbar_length_m = 0.025\nbar_length_tolerance = 2\n",
         "mesh.bar_length_tolerance", "(0.02 = 2 %)"),
    ],
)
def test_bad_values_name_the_key(tmp_path: Path, text: str, key: str, words: str) -> None:
    with pytest.raises(ConfigError) as info:
        # Top-level keys must come before the first table to be top-level.
        if "[mesh]" in text:
            full = text  # a complete file
        else:
            full = MINIMAL + text if text.startswith("[") else text + MINIMAL
        load_config(write(tmp_path, full),
                    extra_sections={"link": LinkSettings, **driver_sections()})
    assert info.value.key == key
    assert words in info.value.problem


def test_mesh_range_checked_by_the_mesh_itself(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, "[camera]\nurl = 'synthetic:'\n[mesh]\nbar_length_m = 5.0\n"))
    assert info.value.key == "mesh.bar_length_m"


def test_a_value_nested_too_deeply_is_a_configuration_error(tmp_path: Path) -> None:
    """3000 nested arrays: the parser's RecursionError was a traceback, exit 1, not 78."""
    path = write(tmp_path, MINIMAL + "[filter]\nx = " + "[" * 3000 + "]" * 3000 + "\n")
    with pytest.raises(ConfigError, match="nested too deeply"):
        load_config(path)


def test_invalid_toml_names_file_and_line(tmp_path: Path) -> None:
    p = write(tmp_path, "[mesh]\nbar_length_m = = 1\n")
    with pytest.raises(ConfigError) as info:
        load_config(p)
    assert info.value.key == str(p)
    assert "line 2" in info.value.problem


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "absent.toml")


def test_calibration_path_relative_to_config_and_must_exist(tmp_path: Path) -> None:
    text = ("[mesh]\nbar_length_m = 0.025\n[camera]\nurl = 'rtsp://127.0.0.1:8554/x'\n"
            "calibration = 'cam.yaml'\n")
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(p)
    assert info.value.key == "camera.calibration"
    assert str(tmp_path / "cam.yaml") in info.value.problem
    (tmp_path / "cam.yaml").write_text("image_width: 4\n")
    assert load_config(p).calibration_path() == tmp_path / "cam.yaml"


def test_extra_section_builds_the_driver_dataclass(tmp_path: Path) -> None:
    text = MINIMAL + "[link]\nrate_hz = 20\nendpoints = ['a', 'b']\nmode = 'b'\n"
    cfg = load_config(write(tmp_path, text), extra_sections={"link": LinkSettings})
    link = cfg.section("link", LinkSettings)
    assert link == LinkSettings(rate_hz=20.0, endpoints=("a", "b"), mode="b")
    assert isinstance(link.rate_hz, float)  # TOML integer accepted for a float key
    assert cfg.effective["link"]["endpoints"] == ["a", "b"]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("filter.gate_sigma=3.5", ("filter", "gate_sigma", 3.5)),
        ("filter.acquire_count=2", ("filter", "acquire_count", 2)),
        ("link.enabled=false", ("link", "enabled", False)),
        ("camera.url=rtsp://127.0.0.1:8554/video_stream__dev_video2",
         ("camera", "url", "rtsp://127.0.0.1:8554/video_stream__dev_video2")),
        ('camera.url="synthetic:?fps=30"', ("camera", "url", "synthetic:?fps=30")),
        ("link.endpoints=['x', 'y']", ("link", "endpoints", ["x", "y"])),
    ],
)
def test_parse_override(text: str, expected: tuple[str, str, object]) -> None:
    assert parse_override(text) == expected


@pytest.mark.parametrize("text", ["gate_sigma=3", "filter.gate_sigma", ".x=1", "a.b.c=1"])
def test_malformed_override(text: str) -> None:
    with pytest.raises(ConfigError, match=r"section\.key=value"):
        parse_override(text)


def test_overrides_win_and_are_validated(tmp_path: Path) -> None:
    p = write(tmp_path, MINIMAL + "[filter]\ngate_sigma = 3.0\n")
    cfg = load_config(p, ["filter.gate_sigma=5", "service.log_level=DEBUG"])
    assert cfg.filter.gate_sigma == 5.0 and cfg.service.log_level == "DEBUG"
    with pytest.raises(ConfigError) as info:
        load_config(p, ["filter.gate_sigme=5"])
    assert info.value.key == "filter.gate_sigme"


def test_digest_is_canonical(tmp_path: Path) -> None:
    a = load_config(write(tmp_path, MINIMAL, "a.toml"))
    # The same effective settings written differently (explicit default, other order, int vs
    # float) give the same digest; any real change gives another.
    b_text = "[filter]\ngate_sigma = 4\n" + MINIMAL
    b = load_config(write(tmp_path, b_text, "b.toml"))
    c = load_config(write(tmp_path, MINIMAL, "c.toml"), ["filter.gate_sigma=4.5"])
    assert a.digest == b.digest
    assert a.digest != c.digest
    assert a.changed_sections(c) == {"filter"}


def test_build_section_rejects_non_dataclass() -> None:
    with pytest.raises(TypeError):
        build_section("x", dict, {})


def _shipped(name: str) -> Path:
    return CONFIG_DIR / name


def _all_sections() -> dict[str, type]:
    return driver_sections()


@pytest.mark.parametrize("name", ["netpose.toml", "demo.toml"])
def test_shipped_configs_are_valid(name: str) -> None:
    path = _shipped(name)
    if not path.exists():
        pytest.fail(f"{path} is missing")
    cfg = load_config(path, extra_sections=_all_sections(), check_files=False)
    assert isinstance(cfg, Config)


@pytest.mark.parametrize("name", ["blueos.toml", "raspberrypi.toml"])
def test_vehicle_configs_leave_the_mesh_to_the_user(name: str) -> None:
    """What install.sh installs is a real vehicle's configuration: it refuses to start until the
    user has said what net this is (no pre-filled mesh size that would silently scale every
    distance), and it never sends rendered distances."""
    path = _shipped(name)
    with pytest.raises(ConfigError) as info:
        load_config(path, extra_sections=_all_sections(), check_files=False)
    assert info.value.key == "mesh.bar_length_m" and "required" in info.value.problem
    cfg = load_config(path, ["mesh.bar_length_m=0.02"], extra_sections=_all_sections(),
                      check_files=False)
    assert cfg.effective["mavlink"]["allow_simulated"] is False
    assert not cfg.camera.url.startswith(("synthetic:", "sim:"))


def test_reference_config_documents_every_key_with_its_default() -> None:
    """config/netpose.toml lists every key of every section, set to its default (keys whose
    default is 'unset' appear as a commented line), so the file is the reference."""
    path = _shipped("netpose.toml")
    text = path.read_text(encoding="utf-8")
    doc = tomllib.loads(text)
    from service.config import _jsonable, core_sections

    sections = core_sections() | _all_sections()
    assert set(doc) == set(sections)
    effective = load_config(path, extra_sections=_all_sections(), check_files=False).effective
    for name, cls in sections.items():
        for f in dataclasses.fields(cls):
            key = f"{name}.{f.name}"
            if f.default is not dataclasses.MISSING:
                default = f.default
            elif f.default_factory is not dataclasses.MISSING:
                default = f.default_factory()
            else:
                assert f.name in doc[name], f"required key {key} missing from netpose.toml"
                continue
            if default is None:
                assert f"# {f.name} =" in text, f"{key} (unset by default) not documented"
                continue
            assert f.name in doc[name], f"{key} missing from netpose.toml"
            assert effective[name][f.name] == _jsonable(default), (
                f"{key}: file says {effective[name][f.name]}, default is {default}"
            )


def test_cli_exits_78_naming_the_key(tmp_path: Path) -> None:
    p = write(tmp_path, MINIMAL + "[filter]\ngate_sigma = 'x'\n")
    proc = subprocess.run(
        [sys.executable, "-m", "service.cli", "run", "--config", str(p)],
        capture_output=True, text=True, timeout=60, cwd=REPO,
    )
    assert proc.returncode == 78, proc.stderr
    assert "netpose: configuration error: filter.gate_sigma: must be a number" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
