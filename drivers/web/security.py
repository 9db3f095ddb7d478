"""Who may change what: the page is reachable by anyone on the vehicle's network.

- Reading (GET) is open.
- A request that changes something (any other method) or opens the live WebSocket must come
  from the page's own origin, or from one listed in `web.allowed_origins`. Browsers always
  send `Origin` with those requests, so a page of another site cannot drive this one; tools
  such as curl send none and are let through (they are not a browser being abused).
- With `web.token` set, every change also needs the token in the `X-Netpose-Token` header.
- Request bodies are bounded (`web.max_upload_kb`).

Behind BlueOS's nginx (/extensionv2/netpose/) the Host header is the vehicle's host name
without a port (`proxy_set_header Host $host`), so when Host carries no port only the host
names are compared.
"""

from __future__ import annotations

import hmac
from collections.abc import Iterable
from urllib.parse import urlsplit

TOKEN_HEADER = "X-Netpose-Token"
DEFAULT_PORTS = {"http": 80, "https": 443}


def _split_host(host: str) -> tuple[str, int | None]:
    """'Host' header -> (lower-case name, port or None)."""
    host = host.strip().lower()
    if host.startswith("["):  # [::1]:8780
        name, _, rest = host[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else ""
    else:
        name, _, port = host.partition(":")
    return name, int(port) if port.isdigit() else None


def origin_allowed(origin: str | None, host: str, allowed: Iterable[str] = ()) -> bool:
    """Whether a request with this `Origin` header may change things on the server `host`."""
    if origin is None:
        return True  # not sent by a browser page
    origin = origin.strip()
    if origin in allowed:
        return True
    if origin == "null":  # sandboxed frames, file:// pages
        return False
    parts = urlsplit(origin)
    if parts.scheme not in DEFAULT_PORTS or not parts.hostname:
        return False
    try:
        origin_port = parts.port or DEFAULT_PORTS[parts.scheme]
    except ValueError:
        return False
    name, port = _split_host(host)
    if parts.hostname.lower() != name:
        return False
    return port is None or port == origin_port


def token_ok(required: str, given: str | None) -> bool:
    if not required:
        return True
    if given is None:
        return False
    try:
        offered = given.encode()
    except UnicodeEncodeError:  # a header's undecodable bytes, kept as surrogates: not it
        return False
    return hmac.compare_digest(required.encode(), offered)
