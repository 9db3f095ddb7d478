"""One version everywhere a user reads it: `netpose --version`, the status and the page
(`service.__version__`), the installed distribution (pyproject) and the BlueOS extension's
`version` label, which the Extensions Manager shows and compares with the store's tag."""

from __future__ import annotations

import re
import tomllib
from importlib.metadata import version
from pathlib import Path

from service import __version__

REPO = Path(__file__).resolve().parent.parent


def test_the_distribution_takes_its_version_from_the_package() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    # One place to bump: a literal version in pyproject drifts from service.__version__.
    assert "version" not in project and "version" in project.get("dynamic", [])
    assert version("netpose") == __version__


def test_the_blueos_image_labels_the_same_version() -> None:
    dockerfile = (REPO / "blueos" / "Dockerfile").read_text()
    default = re.search(r"^ARG VERSION=(\S+)$", dockerfile, re.MULTILINE)
    assert default is not None, "blueos/Dockerfile has no ARG VERSION default"
    assert default.group(1) == __version__
    # ... and the build command docs/blueos.md gives passes that version too.
    docs = (REPO / "docs" / "blueos.md").read_text()
    assert set(re.findall(r"--build-arg VERSION=(\S+)", docs)) <= {__version__}
