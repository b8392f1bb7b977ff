"""Local mode's guard against web pages: with no tokens configured, nothing but the network address stands between
a request and the server, and a web page the user visits can make the browser send requests to 127.0.0.1 (a
form or fetch: cross-site request forgery) or, after re-pointing its own domain name at 127.0.0.1, read the
answers as its own (DNS rebinding). Both carry the page's name: DNS rebinding in the `Host` header, a cross-site
request in `Origin`. So without tokens a request is refused when its `Host` is not a loopback name or address
(localhost, 127.0.0.1, [::1], any port) nor in `allowed_hosts` (400 host_not_allowed), or when it carries an
`Origin` that is neither the server's own (a page it serves, e.g. /inspect) nor in `allowed_origins`
(403 origin_not_allowed). Requests without `Origin` (the CLI, curl, the Python client) pass. With tokens the
bearer token is the defence: a browser never attaches it on its own, so nothing here applies."""
from __future__ import annotations

from .settings import Settings, is_loopback


def host_name(host: str) -> str | None:
    """The name or address of a Host header value, lower case, without its port ('[::1]:8000' -> '::1');
    None when it does not parse."""
    host = host.strip().lower()
    if host.startswith("["):
        end = host.find("]")
        rest = host[end + 1:]
        if end < 0 or (rest and not (rest.startswith(":") and rest[1:].isdigit())):
            return None
        return host[1:end]
    name, sep, port = host.partition(":")
    if sep and not port.isdigit():
        return None
    return name or None


def _header(scope, key: bytes) -> str | None:
    for k, v in scope.get("headers") or []:
        if k == key:
            return v.decode("latin-1")
    return None


def refusal(scope, settings: Settings) -> tuple[int, str, str, str] | None:
    """(status, code, message, field) when a tokenless server must refuse this request, else None."""
    if settings.auth_enabled:
        return None
    allowed = {h.strip("[]").lower() for h in settings.allowed_hosts}
    host = _header(scope, b"host")
    if host is not None:  # HTTP/1.1 always sends one; a browser always does
        name = host_name(host)
        if name is None or not (is_loopback(name) or name in allowed):
            return (400, "host_not_allowed",
                    f"Host {host[:100]!r} is not a loopback name or address (localhost, 127.0.0.1, [::1]) nor in "
                    "the server's allowed_hosts: without tokens the server answers only requests addressed to "
                    "it by a local name, so that a web page cannot reach it by re-pointing its own domain name "
                    "(DNS rebinding); add the name to allowed_hosts, or configure tokens", "Host")
    origin = _header(scope, b"origin")
    if origin is not None:
        own = f"{scope.get('scheme', 'http')}://{(host or '').strip().lower()}"
        listed = {o.rstrip("/").lower() for o in settings.allowed_origins}
        if origin.strip().rstrip("/").lower() not in listed | {own}:
            return (403, "origin_not_allowed",
                    f"Origin {origin[:100]!r} is not this server's own nor in its allowed_origins: without tokens "
                    "a request sent by a web page of another origin is refused (cross-site request forgery); "
                    "requests without an Origin (the CLI, curl, the Python client) are accepted; add the origin "
                    "to allowed_origins, or configure tokens", "Origin")
    return None
