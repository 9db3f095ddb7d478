"""Who may change what: the page is reachable by anyone on the vehicle's network.

- Reading (GET) is open, by a trusted name (below) for the page's data.
- A request that changes something (any other method) or opens the live WebSocket must come
  from the page's own origin, or from one listed in `web.allowed_origins`. Browsers always
  send `Origin` with those requests, so a page of another site cannot drive this one; tools
  such as curl send none and are let through (they are not a browser being abused).
- A browser's change must also reach the page by a name no website can point at the
  vehicle: an IP address, `localhost`, a name without a dot (the LAN's), one under a suffix
  kept out of public DNS (`.local` for mDNS, `.home.arpa`, `.internal`, `.lan`, `.home`,
  `.localdomain`), or the host of an origin listed in `web.allowed_origins`. Otherwise a site
  the topside browser visits could resolve its own name to the vehicle (DNS rebinding) and be
  "the page's own origin"; with no token set (BlueOS's default) it could then rewrite the
  settings. The page's data (the live WebSocket, /api/...) is read by such a name only, too:
  a rebound site would read the cage's video and the recordings (the pages answer any name).
- A browser's change (one that sends `Origin`) must carry the `X-Netpose-Change` header, as
  the page's own requests do. A page of another site can send a "simple" cross-origin POST
  (a form, or JSON labelled text/plain) with no preflight, and behind BlueOS's proxy the Origin
  check above compares host names only, so any page served from the vehicle's name on another
  port passed it. A custom header makes the browser ask first (a CORS preflight), which this
  server never grants.
- With `web.token` set, every change also needs the token in the `X-Netpose-Token` header.
- Request bodies are bounded (`web.max_upload_kb`).

Behind BlueOS's nginx (/extensionv2/netpose/) the Host header is the vehicle's host name
without a port (`proxy_set_header Host $host`), so when Host carries no port only the host
names are compared.
"""

from __future__ import annotations

import hmac
import ipaddress
from collections.abc import Iterable
from urllib.parse import urlsplit

TOKEN_HEADER = "X-Netpose-Token"
CHANGE_HEADER = "X-Netpose-Change"
# Name suffixes no public DNS answers for (mDNS, RFC 8375, ICANN's .internal, and the ones home
# routers hand out): a website cannot be served under them, so nor rebound to one.
PRIVATE_SUFFIXES = (".local", ".home.arpa", ".internal", ".lan", ".home", ".localdomain")
DEFAULT_PORTS = {"http": 80, "https": 443}


def split_host(host: str) -> tuple[str, int | None]:
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
    name, port = split_host(host)
    if parts.hostname.lower() != name:
        return False
    return port is None or port == origin_port


def host_trusted(host: str, allowed: Iterable[str] = ()) -> bool:
    """Whether the name a browser reached the page by (the `Host` header) is one no other
    website can be served under (module docstring)."""
    name, _ = split_host(host)
    if not name:
        return False
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        pass
    name = name.rstrip(".")  # "blueos.local." is the same name, fully qualified
    if name == "localhost" or "." not in name or name.endswith(PRIVATE_SUFFIXES):
        return True
    listed = {(urlsplit(origin.strip()).hostname or "").lower() for origin in allowed}
    return name in listed


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
