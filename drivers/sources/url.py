"""Parsing of frame-source URLs: `scheme:path?key=value&...`, with typed, checked options.

The URL is the one `camera.url` configuration value, so every mistake in it is a configuration
error naming that key: an unknown option (a typo) is refused rather than silently ignored.
Network URLs (rtsp://, udp://, ...) are not parsed here: their query belongs to FFmpeg.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qsl

from service.core.errors import ConfigError
from service.core.redact import redact_text

# The configuration key that holds a source URL (service/config.py, [camera] url).
URL_CONFIG_KEY = "camera.url"

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


def url_error(url: str, problem: str) -> ConfigError:
    return ConfigError(URL_CONFIG_KEY, f"{redact_text(url)}: {problem}")


@dataclass(frozen=True)
class SourceUrl:
    """A `scheme:path?options` URL of one of netpose's own schemes (v4l2, file, images, ...)."""

    raw: str
    scheme: str
    path: str
    options: Mapping[str, str]

    def check_options(self, allowed: Iterable[str]) -> None:
        known = set(allowed)
        unknown = sorted(set(self.options) - known)
        if unknown:
            raise url_error(
                self.raw,
                f"unknown option(s) {', '.join(unknown)} for {self.scheme}: "
                f"(known: {', '.join(sorted(known)) or 'none'})",
            )

    def text(self, key: str, default: str) -> str:
        return self.options.get(key, default)

    def choice(self, key: str, default: str, choices: Iterable[str]) -> str:
        allowed = tuple(choices)
        value = self.options.get(key, default)
        if value not in allowed:
            raise url_error(self.raw, f"option {key} must be one of {', '.join(allowed)}")
        return value

    def integer_or(self, key: str, default: int, low: int, high: int) -> int:
        value = self.integer(key, None, low, high)
        return default if value is None else value

    def number_or(self, key: str, default: float, low: float, high: float) -> float:
        value = self.number(key, None, low, high)
        return default if value is None else value

    def integer(self, key: str, default: int | None, low: int, high: int) -> int | None:
        raw = self.options.get(key)
        if raw is None:
            return default
        try:
            value = int(raw)
        except ValueError:
            raise url_error(self.raw, f"option {key}={raw!r} is not an integer") from None
        if not low <= value <= high:
            raise url_error(self.raw, f"option {key}={value} is outside {low}..{high}")
        return value

    def number(self, key: str, default: float | None, low: float, high: float) -> float | None:
        raw = self.options.get(key)
        if raw is None:
            return default
        try:
            value = float(raw)
        except ValueError:
            raise url_error(self.raw, f"option {key}={raw!r} is not a number") from None
        if not math.isfinite(value) or not low <= value <= high:
            raise url_error(self.raw, f"option {key}={raw} is outside {low:g}..{high:g}")
        return value

    def flag(self, key: str, default: bool) -> bool:
        raw = self.options.get(key)
        if raw is None:
            return default
        if raw.lower() in _TRUE or raw == "":
            return True
        if raw.lower() in _FALSE:
            return False
        raise url_error(self.raw, f"option {key}={raw!r} must be 0 or 1")

    def interval(self, key: str) -> tuple[float, float] | None:
        """`key=START-END` in seconds (e.g. gap=4-6)."""
        raw = self.options.get(key)
        if raw is None:
            return None
        match = re.fullmatch(r"\s*(\d+(?:\.\d*)?)\s*-\s*(\d+(?:\.\d*)?)\s*", raw)
        if match is None or float(match.group(1)) >= float(match.group(2)):
            raise url_error(self.raw, f"option {key}={raw!r} must be START-END seconds, START<END")
        return float(match.group(1)), float(match.group(2))


# Schemes that netpose parses itself; everything else with "://" goes to FFmpeg.
OWN_SCHEMES = ("v4l2", "file", "images", "synthetic", "sim", "recording")


def parse_source_url(url: str) -> SourceUrl:
    """Split one of netpose's own URLs. Bare paths are accepted as a convenience:
    `/dev/video0` means `v4l2:/dev/video0`, a folder means `images:`, any other path `file:`.
    """
    text = url.strip()
    if not text:
        raise url_error(url, "empty source URL")
    scheme, sep, rest = text.partition(":")
    if not sep or scheme not in OWN_SCHEMES:
        return _bare_path(text)
    path, _, query = rest.partition("?")
    if scheme in ("file", "images", "recording") and path.startswith("//"):
        path = path[2:]  # file:///abs/path -> /abs/path
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError:
        raise url_error(
            url, f"cannot parse the options {query!r} (use key=value&key=value)"
        ) from None
    options: dict[str, str] = {}
    for key, value in pairs:
        if key in options:
            raise url_error(url, f"option {key} is given twice")
        options[key] = value
    return SourceUrl(raw=text, scheme=scheme, path=path, options=options)


def _bare_path(text: str) -> SourceUrl:
    if "://" in text:
        raise url_error(text, "not a netpose scheme (network URLs go to the stream source)")
    path, _, query = text.partition("?")
    prefix = re.match(r"([A-Za-z][A-Za-z0-9+.-]+):", path)
    if prefix is not None and not Path(path).exists():
        # A mistyped scheme read as a file name: "V4L2:/dev/video0" was then refused as a
        # recorded video (mavlink.allow_simulated), "synthetc:" retried "no such file" for ever.
        name = prefix.group(1)
        hint = (f"schemes are lower case: {name.lower()}:" if name.lower() in OWN_SCHEMES
                else f"netpose's own are {', '.join(f'{s}:' for s in OWN_SCHEMES)} and sdp:; "
                "network streams are rtsp://, udp://, ...")
        raise url_error(text, f"unknown scheme {name + ':'!r} ({hint})")
    if path.startswith("/dev/video") or path.startswith("/dev/v4l/") or path.isdigit():
        scheme = "v4l2"  # a bare number is a camera index, as OpenCV takes it
    elif Path(path).is_dir() and (Path(path) / "recording.json").is_file():
        scheme = "recording"  # a folder written by drivers/recorder.py
    elif Path(path).is_dir():
        scheme = "images"
    else:
        scheme = "file"
    return parse_source_url(f"{scheme}:{path}" + (f"?{query}" if query else ""))


def is_network_url(url: str) -> bool:
    """rtsp://, udp://, tcp://, http(s)://, srt://...: anything FFmpeg opens by protocol."""
    return re.match(r"^[A-Za-z][A-Za-z0-9+.-]*://", url.strip()) is not None and not any(
        url.strip().startswith(f"{s}:") for s in OWN_SCHEMES
    )
