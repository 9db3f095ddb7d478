"""Soak benchmark: the real daemon process for minutes at 30 frames/s, measured from outside.

The daemon runs as a subprocess (`netpose run`) on the synthetic source in real time, sending
MAVLink over loopback UDP to a recorder here and telemetry over Zenoh to a subscriber here. The
benchmark reports:

- CPU per processed frame: the daemon process's CPU time (user + system, all its threads, from
  /proc) divided by the frames it processed (rendering the synthetic frames is part of it; the
  estimator's own share is reported separately from its stage timings);
- latency from frame capture to MAVLink: for every DISTANCE_SENSOR the recorder receives, the
  time since the capture of the frame whose distance it carries (matched through the estimate
  telemetry, which carries the capture time and the filtered distance; CLOCK_MONOTONIC is
  shared by all processes on the machine); median and 99th percentile;
- memory growth: resident set size after warm-up and at the end, and the slope between.

`main_soak(...)` is what `netpose bench soak` calls.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.mavlink_observer import DistanceObserver
from drivers.telemetry_subscriber import TelemetrySubscriber
from service.core.errors import ConfigError

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CONFIG = REPO_ROOT / "config" / "demo.toml"


@dataclass
class ProcessSample:
    t: float
    cpu_s: float
    rss_mb: float


def sample_process(pid: int) -> ProcessSample | None:
    """CPU time (all threads) and resident memory of a process, from /proc."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2 :].split()
    ticks = os.sysconf("SC_CLK_TCK")
    cpu = (int(fields[11]) + int(fields[12])) / ticks  # utime, stime
    rss_kb = next((int(line.split()[1]) for line in status.splitlines()
                   if line.startswith("VmRSS:")), 0)
    return ProcessSample(time.monotonic(), cpu, rss_kb / 1024.0)


def match_latencies(
    distances: Sequence[tuple[float, int]], estimates: Sequence[dict[str, Any]], field_name: str
) -> list[float]:
    """Capture-to-arrival latency (s) of each DISTANCE_SENSOR, matched to its estimate.

    For a message received at t_rx carrying d cm, the frame it came from is the newest valid
    estimate published before t_rx whose filtered distance rounds to d (within 1 cm);
    messages without a match (e.g. a coasting prediction) are left out.
    """
    table = []
    for e in estimates:
        filtered = e.get("filtered") or {}
        value = filtered.get(field_name)
        if filtered.get("valid") and value is not None and e.get("frame_time_mono") is not None:
            table.append((float(e["time_mono"]), float(e["frame_time_mono"]),
                          round(float(value) * 100)))
    table.sort()
    published = np.array([row[0] for row in table])
    latencies = []
    for t_rx, cm in distances:
        i = int(np.searchsorted(published, t_rx, side="right")) - 1
        # The link sends the newest value it holds; look back over the few latest estimates.
        for j in range(i, max(i - 10, -1), -1):
            _, t_capture, value_cm = table[j]
            if abs(value_cm - cm) <= 1:
                latencies.append(t_rx - t_capture)
                break
    return latencies


@dataclass
class SoakReport:
    duration_s: float
    source_fps: float
    frames_processed: int
    processed_fps: float
    frames_skipped: int
    detected_fraction: float
    cpu_ms_per_frame: float
    cpu_percent_of_one_core: float
    estimator_ms_median: float
    distance_messages: int
    distance_rate_hz: float
    latency_ms_median: float
    latency_ms_p99: float
    latency_matched: int
    handoff_ms_median: float
    rss_mb_after_warmup: float
    rss_mb_end: float
    rss_growth_mb_per_hour: float
    exit_status: int
    notes: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        return [
            f"soak: {self.duration_s:.0f} s at a {self.source_fps:g} frames/s source, exit "
            f"status {self.exit_status}",
            f"  frames processed {self.frames_processed} ({self.processed_fps:.1f}/s), skipped "
            f"{self.frames_skipped}, net detected in {100 * self.detected_fraction:.0f}%",
            f"  CPU {self.cpu_ms_per_frame:.1f} ms per processed frame "
            f"({self.cpu_percent_of_one_core:.0f}% of one core, rendering included); "
            f"estimator {self.estimator_ms_median:.1f} ms median",
            f"  capture -> MAVLink arrival: median {self.latency_ms_median:.1f} ms, p99 "
            f"{self.latency_ms_p99:.1f} ms ({self.latency_matched} of {self.distance_messages} "
            f"DISTANCE_SENSOR matched, {self.distance_rate_hz:.1f} Hz); capture -> hand-off to "
            f"the link {self.handoff_ms_median:.1f} ms median",
            f"  memory: RSS {self.rss_mb_after_warmup:.1f} MB after warm-up, "
            f"{self.rss_mb_end:.1f} MB at the end ({self.rss_growth_mb_per_hour:+.1f} MB/h)",
            *[f"  note: {n}" for n in self.notes],
        ]


def _percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if len(values) else math.nan


def run_soak(
    duration_s: float,
    fps: float,
    *,
    config: Path = DEFAULT_CONFIG,
    source_url: str | None = None,
    extra_overrides: Sequence[str] = (),
    warmup_s: float | None = None,
) -> SoakReport:
    """Run the daemon for `duration_s` and measure it (see the module docstring)."""
    url = source_url or (
        f"synthetic:?width=640&height=360&fps={fps:g}&realtime=1&trajectory=approach"
    )
    mav = DistanceObserver()
    tel = TelemetrySubscriber(vehicle="soak")
    overrides = [
        f"camera.url={url}",
        f"mavlink.url={mav.url}",
        "telemetry.vehicle=soak",
        "telemetry.preview_hz=0",
        "service.status_interval_s=1",
        *tel.daemon_overrides(),
        *extra_overrides,
    ]
    cmd = [sys.executable, "-m", "service.cli", "run", "--config", str(config)]
    for o in overrides:
        cmd += ["--set", o]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("NOTIFY_SOCKET", None)
    warm = warmup_s if warmup_s is not None else min(30.0, 0.2 * duration_s)
    samples: list[ProcessSample] = []
    proc = subprocess.Popen(cmd, cwd=REPO_ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    stderr_tail: list[str] = []
    reader = threading.Thread(target=_drain, args=(proc, stderr_tail), daemon=True)
    reader.start()
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < duration_s and proc.poll() is None:
            s = sample_process(proc.pid)
            if s is not None:
                samples.append(s)
            time.sleep(1.0)
        end_sample = sample_process(proc.pid)
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            status = proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            status = proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        reader.join(timeout=2.0)
        estimates, statuses = tel.snapshot()
        distances = mav.snapshot()
        tel.close()
        mav.close()
    if end_sample is not None:
        samples.append(end_sample)
    return _report(duration_s, fps, estimates, statuses, distances, samples, warm, status,
                   stderr_tail)


def _drain(proc: subprocess.Popen[str], tail: list[str]) -> None:
    assert proc.stderr is not None
    for line in proc.stderr:
        tail.append(line.rstrip())
        del tail[:-50]


def _report(
    duration_s: float,
    fps: float,
    estimates: list[dict[str, Any]],
    statuses: list[dict[str, Any]],
    distances: list[tuple[float, int]],
    samples: list[ProcessSample],
    warmup_s: float,
    status: int,
    stderr_tail: list[str],
) -> SoakReport:
    notes: list[str] = []
    steady = [e for e in estimates if e.get("time_mono") is not None]
    if steady:
        t_first = min(float(e["time_mono"]) for e in steady)
        steady = [e for e in steady if float(e["time_mono"]) >= t_first + warmup_s]
    frames = len(steady)
    t_span = (float(steady[-1]["time_mono"]) - float(steady[0]["time_mono"])) if frames > 1 \
        else math.nan
    detected = sum(1 for e in steady if e.get("detected"))
    estimator_ms = [float(e["latency_ms"]["estimator_total"]) for e in steady
                    if (e.get("latency_ms") or {}).get("estimator_total") is not None]
    handoff_ms = [float(e["latency_ms"]["frame_to_publish"]) for e in steady
                  if (e.get("latency_ms") or {}).get("frame_to_publish") is not None]
    # Frames the source produced that the loop never saw (it always takes the newest).
    last_status = statuses[-1] if statuses else {}
    skipped = int((last_status.get("frame_source") or {}).get("dropped") or 0)
    field_name = "range_m"
    if steady and all((e.get("filtered") or {}).get("range_m") is None for e in steady):
        field_name = "distance_m"
    t_lo = float(steady[0]["time_mono"]) if steady else math.inf
    msgs = [(t, cm) for t, cm in distances if t >= t_lo]
    latencies = match_latencies(msgs, estimates, field_name)
    msg_span = msgs[-1][0] - msgs[0][0] if len(msgs) > 1 else math.nan

    warm_samples = [s for s in samples if s.t >= (samples[0].t + warmup_s)] if samples else []
    cpu_ms = cpu_pct = math.nan
    rss_warm = rss_end = growth = math.nan
    if len(warm_samples) >= 2:
        a, b = warm_samples[0], warm_samples[-1]
        frames_between = sum(
            1 for e in steady if a.t <= float(e["time_mono"]) <= b.t
        )
        cpu_used = b.cpu_s - a.cpu_s
        cpu_ms = 1e3 * cpu_used / frames_between if frames_between else math.nan
        cpu_pct = 100.0 * cpu_used / (b.t - a.t)
        rss_warm, rss_end = a.rss_mb, b.rss_mb
        ts = np.array([s.t for s in warm_samples])
        rss = np.array([s.rss_mb for s in warm_samples])
        growth = float(np.polyfit(ts - ts[0], rss, 1)[0] * 3600.0) if len(ts) >= 3 else math.nan
    else:
        notes.append("too short for CPU and memory after warm-up")
    if status != 0:
        notes.append("daemon stderr tail: " + " | ".join(stderr_tail[-5:]))
    return SoakReport(
        duration_s=duration_s,
        source_fps=fps,
        frames_processed=frames,
        processed_fps=frames / t_span if math.isfinite(t_span) and t_span > 0 else math.nan,
        frames_skipped=skipped,
        detected_fraction=detected / frames if frames else 0.0,
        cpu_ms_per_frame=cpu_ms,
        cpu_percent_of_one_core=cpu_pct,
        estimator_ms_median=_percentile(estimator_ms, 50),
        distance_messages=len(msgs),
        distance_rate_hz=(len(msgs) - 1) / msg_span if math.isfinite(msg_span) and msg_span > 0
        else 0.0,
        latency_ms_median=1e3 * _percentile(latencies, 50),
        latency_ms_p99=1e3 * _percentile(latencies, 99),
        latency_matched=len(latencies),
        handoff_ms_median=_percentile(handoff_ms, 50),
        rss_mb_after_warmup=rss_warm,
        rss_mb_end=rss_end,
        rss_growth_mb_per_hour=growth,
        exit_status=status,
        notes=notes,
    )


def main_soak(
    duration_s: float = 300.0,
    fps: float = 30.0,
    *,
    config: str | Path | None = None,
    source_url: str | None = None,
    json_out: str | Path | None = None,
    extra_overrides: Sequence[str] = (),
) -> int:
    """`netpose bench soak`: run, print the report, optionally save it as JSON. Exit status 0
    when the daemon ran the whole time and stopped cleanly, 1 otherwise."""
    if not duration_s > 0 or not fps > 0:
        raise ConfigError("soak", "duration and fps must be positive")
    report = run_soak(
        duration_s, fps, config=Path(config) if config else DEFAULT_CONFIG,
        source_url=source_url, extra_overrides=extra_overrides,
    )
    for line in report.lines():
        print(line, flush=True)
    if json_out is not None:
        Path(json_out).write_text(json.dumps(asdict(report), indent=2, allow_nan=True) + "\n")
    return 0 if report.exit_status == 0 and report.frames_processed > 0 else 1


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="netpose soak benchmark")
    parser.add_argument("--duration", type=float, default=300.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--config", default=None)
    parser.add_argument("--source", default=None)
    parser.add_argument("--json", default=None)
    ns = parser.parse_args()
    sys.exit(main_soak(ns.duration, ns.fps, config=ns.config, source_url=ns.source,
                       json_out=ns.json))
