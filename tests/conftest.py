"""Shared pytest hooks: the versions of the numeric stack this run tests (current wheels under
`make test`, Debian bookworm's under `make test-bookworm`)."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import scipy


def pytest_report_header() -> str:
    return (f"netpose stack: Python {sys.version.split()[0]}, numpy {np.__version__}, "
            f"scipy {scipy.__version__}, OpenCV {cv2.__version__}")
