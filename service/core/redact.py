"""Secrets out of everything that leaves the process: logs, error lines, telemetry, summaries.

One rule, used everywhere a URL or a configuration is shown:

- the user-info password of a URL (`rtsp://user:pa@ss@camera/...` -> `rtsp://user:<redacted>@...`).
  The password ends at the *last* `@` on the line, so a password containing `@`, `#`, `/`, `?`
  or a space is hidden whole, not cut where one of them begins;
- the value of query parameters that name a secret (`?passphrase=`, `?token=`, `?password=`,
  `?key=`... see `_SECRET_NAME`), as SRT and many cameras take them;
- in a configuration mapping, the value of any key that names a secret, and every URL-looking
  string below it.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

REDACTED = "<redacted>"

# A key or parameter name that holds a secret: matched anywhere in the name, any case.
_SECRET_NAME = re.compile(
    r"(password|passwd|passphrase|pwd|secret|token|api[_-]?key|private[_-]?key|credential|"
    r"auth|^key$|signing_key)",
    re.I,
)
# scheme://user:password@host — the password is everything up to the last '@' on the line: a
# password typed raw into a configuration may hold '@', '#', '/', '?' or a space, and any of
# them ended a narrower match early, leaving the rest in clear. Hiding too much (a second
# address later on the same line) is the safe way to be wrong. The user part has no ':', '/'
# or '@'.
_USERINFO = re.compile(r"(?P<head>[a-z][a-z0-9+.-]*://[^:/@\s?#]*:).*@", re.I)
# name=value in a query string or an FFmpeg option list (&, ?, ; and | separate pairs).
_PARAMETER = re.compile(r"(?P<sep>[?&;|])(?P<name>[A-Za-z0-9_.-]+)=(?P<value>[^&;|#\s]*)")


def redact_text(text: str) -> str:
    """`text` (a URL, or a message that contains URLs) with every secret replaced."""
    text = _USERINFO.sub(rf"\g<head>{REDACTED}@", text)

    def parameter(match: re.Match[str]) -> str:
        if _SECRET_NAME.search(match.group("name")) and match.group("value"):
            return f"{match.group('sep')}{match.group('name')}={REDACTED}"
        return match.group(0)

    return _PARAMETER.sub(parameter, text)


def is_secret_name(name: str) -> bool:
    return bool(_SECRET_NAME.search(name))


def redact_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of a (nested) configuration mapping with secret values replaced.

    Values under secret-named keys become REDACTED (unless empty: an unset secret is not one);
    strings anywhere are passed through `redact_text`.
    """

    def scrub(key: str, value: Any) -> Any:
        if is_secret_name(key) and value not in (None, ""):
            return REDACTED
        if isinstance(value, Mapping):
            return {str(k): scrub(str(k), v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [scrub(key, v) for v in value]
        if isinstance(value, str):
            return redact_text(value)
        return value

    return {str(k): scrub(str(k), v) for k, v in config.items()}
