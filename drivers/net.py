"""Small network helpers shared by drivers, benchmarks and tests."""

from __future__ import annotations

import socket


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A loopback port that was free a moment ago (for peers that cannot bind port 0 and report
    it, such as a Zenoh endpoint given on another process's command line)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
