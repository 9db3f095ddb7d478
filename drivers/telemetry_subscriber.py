"""A Zenoh peer listening on loopback that keeps the estimates, statuses and confirmed holes
(damage) published to it.

What the topside sees of netpose, for the soak benchmark and the end-to-end tests: the daemon
connects to it (`daemon_overrides()`) and publishes here.
"""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import zenoh

from drivers.net import free_port
from drivers.telemetry import token_change


class TelemetrySubscriber:
    def __init__(self, key_prefix: str = "netpose", vehicle: str = "soak") -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        config = zenoh.Config()
        config.insert_json5("mode", json.dumps("peer"))
        config.insert_json5("listen/endpoints", json.dumps([self.endpoint]))
        config.insert_json5("scouting/multicast/enabled", "false")
        self._session = zenoh.open(config)
        self._lock = threading.Lock()
        self.estimates: list[dict[str, Any]] = []
        self.statuses: list[dict[str, Any]] = []
        self.damages: list[dict[str, Any]] = []

        def on_sample(sample: Any) -> None:
            try:
                payload = json.loads(sample.payload.to_bytes())
            except (ValueError, UnicodeDecodeError):
                return
            if not isinstance(payload, dict):
                return
            payload["_received_mono"] = time.monotonic()
            with self._lock:
                if payload.get("kind") == "estimate":
                    self.estimates.append(payload)
                elif payload.get("kind") == "status":
                    self.statuses.append(payload)
                elif payload.get("kind") == "damage":
                    self.damages.append(payload)

        self._subscriber = self._session.declare_subscriber(f"{key_prefix}/{vehicle}/**",
                                                            on_sample)
        # The daemon's liveliness token: ("PUT" | "DELETE", key, monotonic arrival).
        self._liveliness: list[tuple[str, str, float]] = []

        def on_token(sample: Any) -> None:
            with self._lock:
                self._liveliness.append((token_change(sample), str(sample.key_expr),
                                         time.monotonic()))

        self._tokens = self._session.liveliness().declare_subscriber(
            f"{key_prefix}/{vehicle}/**", on_token, history=True)

    def snapshot(self) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        with self._lock:
            return list(self.estimates), list(self.statuses)

    def daemon_overrides(self) -> list[str]:
        """--set options that point the daemon's telemetry at this subscriber."""
        return [
            "telemetry.enabled=true",
            "telemetry.mode=peer",
            f"telemetry.connect=['{self.endpoint}']",
            "telemetry.listen=[]",
            "telemetry.scouting=false",
        ]

    def tokens(self) -> list[tuple[str, str, float]]:
        """The daemon's liveliness token's comings and goings so far."""
        with self._lock:
            return list(self._liveliness)

    def close(self) -> None:
        self._tokens.undeclare()
        self._subscriber.undeclare()
        self._session.close()
