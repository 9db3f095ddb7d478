"""Where the project's shared real data lives: `shared/` beside the repository checkout.

CI clones the repository with `shared/` next to it, as on the developers' machines;
NETPOSE_SHARED_DATA overrides the location.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def shared_data_dir() -> Path:
    override = os.environ.get("NETPOSE_SHARED_DATA")
    if override:
        return Path(override)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


REAL_NET_DIR = shared_data_dir() / "real-net-frame"
REAL_NET_FRAME = REAL_NET_DIR / "net_1280x720.jpg"
REAL_NET_CALIBRATION = REAL_NET_DIR / "camera_solaqua_1280x720.yaml"

REAL_FIELD_DIR = shared_data_dir() / "real-field"

# Tests of real frames skip, saying why, on a checkout without `shared/` beside it.
needs_real_net_frame = pytest.mark.skipif(
    not (REAL_NET_FRAME.exists() and REAL_NET_CALIBRATION.exists()),
    reason=f"real-net-frame data set not present at {REAL_NET_DIR} (set NETPOSE_SHARED_DATA)",
)
needs_real_field = pytest.mark.skipif(
    not REAL_FIELD_DIR.is_dir(),
    reason=f"real-field data set not present at {REAL_FIELD_DIR} (set NETPOSE_SHARED_DATA)",
)
