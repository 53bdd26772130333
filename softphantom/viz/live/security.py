"""Who may see the live page (docs/stream.md, "Security"), as ASGI middleware around the page's app.

Outermost first: :class:`MaxClients` (503 beyond ``max_clients`` requests in flight; an open event
stream is one), :class:`LoopbackOnly` (403 for a peer that is not this machine while serving on
loopback), :class:`HostCheck` (403 unless the ``Host`` header names this server: DNS rebinding),
:class:`TokenCheck` (401 without the session's token, given once as ``?token=`` and then as a
cookie), :class:`PageHeaders` (what the browser may load and do: this origin only).
"""

from __future__ import annotations

import hmac
import ipaddress
import socket
from http.cookies import CookieError, SimpleCookie
from typing import Any, Awaitable, Callable
from urllib.parse import parse_qs

Scope = dict[str, Any]
App = Callable[[Scope, Any, Any], Awaitable[None]]

COOKIE = "softphantom_live_token"

# Everything the page loads comes from this server: the browser refuses anything else.
CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
       "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")


def is_loopback(host: str) -> bool:
    """True for an address or name that only this machine can reach ("" and 0.0.0.0 are every interface).

    >>> [is_loopback(h) for h in ("127.0.0.1", "::1", "localhost", "", "0.0.0.0", "192.168.1.5")]
    [True, True, True, False, False, False]
    """
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def every_interface(host: str) -> bool:
    """True for the addresses that mean every interface: "", 0.0.0.0, :: (bracketed or not)."""
    return host.strip("[]") in ("", "0.0.0.0", "::")


def check_listen_host(option: str, host: str, allow_remote: bool, unauthenticated: str) -> bool:
    """The rule of every listening option (``live --listen-host``, ``virtual serve --natnet-host``):
    loopback needs nothing (False); beyond it, a UserError naming ``option`` unless ``allow_remote``,
    else True (the caller warns, saying what ``unauthenticated`` exposes).

    >>> check_listen_host("--natnet-host", "127.0.0.1", False, "the tracker stream")
    False
    >>> check_listen_host("--natnet-host", "0.0.0.0", False, "the tracker stream")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --natnet-host '0.0.0.0' serves every interface, beyond this machine; pass --allow-remote to mean it (the tracker stream has no authentication)
    """
    from softphantom.errors import UserError

    if is_loopback(host):
        return False
    if not allow_remote:
        what = "every interface" if every_interface(host) else host
        raise UserError(f"{option} {host!r} serves {what}, beyond this machine; pass --allow-remote to mean it "
                        f"({unauthenticated} has no authentication)")
    return True


def host_names(listen_host: str, allowed_hosts: tuple[str, ...]) -> set[str]:
    """Names a client may put in the ``Host`` header (lower case, without the port)."""
    names = {"localhost", *(h.lower() for h in allowed_hosts)}
    if not is_loopback(listen_host):
        names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        if listen_host:
            names.add(listen_host.lower())
    return names


def host_allowed(header: str | None, names: set[str], loopback_only: bool) -> bool:
    """Whether a ``Host`` header names this server: a listed name, or an IP literal (loopback
    only when serving on loopback). DNS rebinding gives the attacker's name: refused.

    >>> host_allowed("127.0.0.1:8765", {"localhost"}, True), host_allowed("evil.example:8765", {"localhost"}, True)
    (True, False)
    """
    if not header:
        return False
    host = header.strip().lower()
    if host.startswith("["):
        host = host[1:].split("]", 1)[0]
    elif host.count(":") == 1:
        host = host.split(":", 1)[0]
    if host in names:
        return True
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return False
    return ip.is_loopback or not loopback_only


FOXGLOVE_ORIGINS = ("https://app.foxglove.dev",)
"""Web origins of Foxglove's own viewer: a page of one of them may open the session's WebSocket."""


def origin_allowed(origin: str | None, names: set[str], extra: tuple[str, ...] = FOXGLOVE_ORIGINS) -> bool:
    """Whether a WebSocket's ``Origin`` may see the session. Browsers send the page's origin and
    do not apply the same-origin rule to WebSockets, so a page of another site could open it:
    refused. No ``Origin`` (not a browser page: a program, a desktop viewer's own process) and a
    non-web origin (``file://``, ``app://``: a desktop app; no web page can send one) pass; an
    http(s) origin passes when it is ``extra`` (Foxglove's web app) or its host is one of ``names``
    (this server's, ``--allowed-host``) or loopback. ``null`` (a sandboxed frame, a data: page) is
    refused.

    >>> names = {"localhost"}
    >>> [origin_allowed(o, names) for o in (None, "http://localhost:8765", "https://app.foxglove.dev",
    ...                                      "http://evil.example", "null", "file://")]
    [True, True, True, False, False, True]
    """
    if origin is None:
        return True
    o = origin.strip().lower()
    if o in extra:
        return True
    scheme, sep, rest = o.partition("://")
    if not sep:
        return False  # "null" and anything unparsable
    if scheme not in ("http", "https"):
        return True
    return host_allowed(rest.split("/", 1)[0], names, loopback_only=True)


def websocket_check(listen_host: str, allowed_hosts: tuple[str, ...] = (), token: str | None = None,
                    origins: tuple[str, ...] = FOXGLOVE_ORIGINS):
    """The live page's rules for a WebSocket's opening request (``live --foxglove``): the
    :data:`~softphantom.stream.foxglove.Check` of a
    :class:`~softphantom.stream.foxglove.HandshakeGate`. While serving on loopback, a peer from
    elsewhere: 403; a ``Host`` that does not name this server (DNS rebinding): 403; an ``Origin``
    of another site (:func:`origin_allowed`): 403; beyond loopback, a request without the
    session's ``?token=``: 401."""
    loopback_only = is_loopback(listen_host)
    names = host_names(listen_host, allowed_hosts)

    def check(h) -> tuple[int, str] | None:
        if loopback_only and not is_loopback(h.peer):
            return 403, "served to this machine only (softphantom live --allow-remote)"
        if not host_allowed(h.headers.get("host"), names, loopback_only):
            return 403, "Host not served here (use the printed address)"
        if not origin_allowed(h.headers.get("origin"), names, origins):
            return 403, "Origin not allowed: a page of another site may not open this session"
        if token is not None:
            given = parse_qs(h.target.partition("?")[2]).get("token", [""])[0]
            if not (given and hmac.compare_digest(given.encode(), token.encode())):
                return 401, "token required (use the printed address)"
        return None

    return check


async def refuse(send, status: int, text: str, headers: tuple[tuple[bytes, bytes], ...] = ()) -> None:
    """A one-line plain-text answer (the refusals, 404)."""
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"), (b"cache-control", b"no-store"),
                            *headers]})
    await send({"type": "http.response.body", "body": text.encode() + b"\n"})


def _header(scope: Scope, name: bytes) -> str | None:
    for k, v in scope.get("headers", ()):
        if k == name:
            return v.decode("latin-1")
    return None


class MaxClients:
    """At most ``limit`` requests served at once (a browser's event stream holds one for as long
    as the page is open); one more is answered 503 with ``Retry-After: 5`` at once."""

    def __init__(self, app: App, limit: int):
        self.app, self.limit, self.active = app, int(limit), 0

    async def __call__(self, scope: Scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if self.active >= self.limit:
            await refuse(send, 503, "too many clients (--max-clients); retry later", ((b"retry-after", b"5"),))
            return
        self.active += 1  # one event loop: no lock needed
        try:
            await self.app(scope, receive, send)
        finally:
            self.active -= 1


class LoopbackOnly:
    """While serving on loopback, a peer that is not this machine (a port some other program
    forwards) is refused: 403."""

    def __init__(self, app: App):
        self.app = app

    async def __call__(self, scope: Scope, receive, send) -> None:
        client = scope.get("client")
        if scope["type"] == "http" and client and not is_loopback(str(client[0])):
            await refuse(send, 403, "served to this machine only (softphantom live --allow-remote)")
            return
        await self.app(scope, receive, send)


class HostCheck:
    """The ``Host`` header must name this server (:func:`host_allowed`), else 403."""

    def __init__(self, app: App, names: set[str], loopback_only: bool):
        self.app, self.names, self.loopback_only = app, names, loopback_only

    async def __call__(self, scope: Scope, receive, send) -> None:
        if scope["type"] == "http" and not host_allowed(_header(scope, b"host"), self.names, self.loopback_only):
            await refuse(send, 403, "Host not served here (use the printed address)")
            return
        await self.app(scope, receive, send)


class TokenCheck:
    """Every request carries the session's token: ``?token=`` (the printed address; the answer
    then sets an ``HttpOnly; SameSite=Strict`` cookie) or that cookie. Else 401."""

    def __init__(self, app: App, token: str):
        self.app, self._token = app, token.encode()

    def _ok(self, given: str | None) -> bool:
        return bool(given) and hmac.compare_digest(given.encode(), self._token)

    async def __call__(self, scope: Scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        query = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token", [""])[0]
        from_query = self._ok(query)
        if not from_query:
            try:
                morsel = SimpleCookie(_header(scope, b"cookie") or "").get(COOKIE)
            except CookieError:
                morsel = None
            if morsel is None or not self._ok(morsel.value):
                await refuse(send, 401, "token required (open the printed address)")
                return
            await self.app(scope, receive, send)
            return
        cookie = f"{COOKIE}={self._token.decode()}; HttpOnly; SameSite=Strict; Path=/".encode()

        async def send_with_cookie(message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), (b"set-cookie", cookie)]}
            await send(message)

        await self.app(scope, receive, send_with_cookie)


class PageHeaders:
    """Headers on every answer: the content security policy (this origin only: nothing is fetched
    from elsewhere, no framing), no MIME sniffing, no referrer (the address may hold the token)."""

    HEADERS = ((b"content-security-policy", CSP.encode()), (b"x-content-type-options", b"nosniff"),
               (b"referrer-policy", b"no-referrer"), (b"x-frame-options", b"DENY"))

    def __init__(self, app: App):
        self.app = app

    async def __call__(self, scope: Scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), *self.HEADERS]}
            await send(message)

        await self.app(scope, receive, send_with_headers)
