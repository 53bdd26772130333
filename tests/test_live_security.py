"""The live page's security model (docs/stream.md): loopback unless --allow-remote, a token
beyond loopback, the Host header checked (DNS rebinding), bounded connections."""

from __future__ import annotations

import http.client
import socket
import time

import pytest

from softphantom.cli import main
from softphantom.errors import UserError
from softphantom.viz.live import LiveConfig, LiveSession
from softphantom.viz.live.security import host_allowed, is_loopback
from softphantom.viz.live.source import SyntheticSource


def _session(**cfg) -> LiveSession:
    src = SyntheticSource(rate_Hz=50, duration_s=30.0, subdivisions=1)
    return LiveSession(src, LiveConfig(http_port=0, stream_port=None, **cfg))


def _get(port: int, path: str, host: str | None = None, cookie: str | None = None):
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    c.putrequest("GET", path, skip_host=True)
    if host is not None:
        c.putheader("Host", host)
    if cookie is not None:
        c.putheader("Cookie", cookie)
    c.endheaders()
    r = c.getresponse()
    body = r.read()
    c.close()
    return r.status, r.headers, body  # case-insensitive names


def _raw(port: int, request: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as c:
        c.sendall(request)
        return c.recv(4096)


def _port(s: LiveSession) -> int:
    return int(s.url.split("://")[1].split("/")[0].rsplit(":", 1)[1])


def test_loopback_names_and_ips_only_in_the_host_header():
    with _session() as s:
        p = _port(s)
        for host in (f"127.0.0.1:{p}", f"localhost:{p}", "localhost", f"[::1]:{p}"):
            assert _get(p, "/api/state", host)[0] == 200, host
        # a rebound DNS name, a LAN address: refused
        for host in (f"evil.example:{p}", f"192.168.1.20:{p}"):
            status, _, body = _get(p, "/api/state", host)
            assert status == 403 and b"Host" in body, host
        # no Host at all: an HTTP/1.0 request reaches the check (403); HTTP/1.1 requires the header,
        # so the HTTP layer answers 400 before (RFC 9112 3.2)
        assert _raw(p, b"GET /api/state HTTP/1.0\r\n\r\n").startswith(b"HTTP/1.1 403")
        assert _get(p, "/api/state", None)[0] == 400


def test_token_required_when_configured_then_cookie():
    with _session(token="s3cret", allowed_hosts=("phantom-bench",)) as s:
        p = _port(s)
        assert s.url.endswith("/?token=s3cret")
        h = f"127.0.0.1:{p}"
        assert _get(p, "/api/state", h)[0] == 401
        assert _get(p, "/api/state?token=wrong", h)[0] == 401
        assert _get(p, "/api/state", h, cookie="softphantom_live_token=wrong")[0] == 401
        status, headers, _ = _get(p, "/?token=s3cret", h)
        assert status == 200 and "HttpOnly" in headers["Set-Cookie"] and "SameSite=Strict" in headers["Set-Cookie"]
        assert _get(p, "/api/state", h, cookie="softphantom_live_token=s3cret")[0] == 200
        # a listed name passes the Host check; the token is still needed
        assert _get(p, "/api/state", f"phantom-bench:{p}")[0] == 401
        assert _get(p, "/api/state?token=s3cret", f"phantom-bench:{p}")[0] == 200
        assert _get(p, "/api/state?token=s3cret", f"evil.example:{p}")[0] == 403


def test_beyond_loopback_needs_a_token():
    assert [is_loopback(h) for h in ("127.0.0.5", "::1", "", "0.0.0.0", "::", "10.0.0.1")] == \
        [True, True, False, False, False, False]
    with pytest.raises(UserError, match="token is required"):
        LiveConfig(listen_host="0.0.0.0")
    with pytest.raises(UserError, match="token is required"):
        LiveConfig(listen_host="")
    # serving on every interface: IP literals of this machine are fine, names only if listed
    assert host_allowed("10.1.2.3:8765", {"localhost"}, loopback_only=False)
    assert not host_allowed("evil.example", {"localhost"}, loopback_only=False)


def test_connections_are_bounded():
    with _session(max_clients=2, client_timeout_s=5.0) as s:
        p = _port(s)
        held = []
        for _ in range(2):  # two browsers on the event stream hold their connections
            c = socket.create_connection(("127.0.0.1", p), timeout=5)
            c.sendall(f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{p}\r\n\r\n".encode())
            assert c.recv(64).startswith(b"HTTP/1.1 200")
            held.append(c)
        status, headers, _ = _get(p, "/api/state", f"127.0.0.1:{p}")
        assert status == 503 and headers.get("Retry-After") == "5"
        for c in held:
            c.close()
        deadline = time.monotonic() + 10
        while (status := _get(p, "/api/state", f"127.0.0.1:{p}")[0]) == 503 and time.monotonic() < deadline:
            time.sleep(0.1)  # the server notices the closed streams at its next write
        assert status == 200


def test_idle_connection_is_dropped():
    with _session(max_clients=1, client_timeout_s=0.5) as s:
        p = _port(s)
        idle = socket.create_connection(("127.0.0.1", p), timeout=5)  # connects, never asks
        deadline = time.monotonic() + 10
        while (status := _get(p, "/api/state", f"127.0.0.1:{p}")[0]) == 503 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert status == 200
        assert idle.recv(16) == b""  # closed by the server
        idle.close()


def test_loopback_only_refuses_a_peer_from_elsewhere():
    import asyncio

    from softphantom.viz.live.security import LoopbackOnly

    async def app(scope, receive, send):
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})

    def call(client) -> tuple[int, bytes]:
        sent = []

        async def send(m):
            sent.append(m)

        asyncio.run(LoopbackOnly(app)({"type": "http", "client": client, "headers": []}, None, send))
        return sent[0]["status"], sent[-1]["body"]

    assert call(("127.0.0.1", 50000)) == (200, b"ok") and call(("::1", 50000)) == (200, b"ok")
    status, body = call(("192.168.1.7", 50000))  # e.g. a port some other program forwards
    assert status == 403 and b"--allow-remote" in body
    # a session on loopback has the policy; one beyond loopback (token) has not
    with _session() as s:
        assert LoopbackOnly in [m.cls for m in s._web.app.user_middleware]
    with _session(listen_host="0.0.0.0", token="t") as s:
        assert LoopbackOnly not in [m.cls for m in s._web.app.user_middleware]


@pytest.mark.parametrize("host", ["", "0.0.0.0"])
def test_cli_refuses_every_interface_without_the_flag(host, capsys):
    assert main(["live", "--listen-host", host, "--duration-s", "1", "--http-port", "0", "--no-stream"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--allow-remote" in err and "every interface" in err


def test_cli_allow_remote_warns_and_prints_a_token(capsys):
    assert main(["live", "--listen-host", "0.0.0.0", "--allow-remote", "--duration-s", "0.5", "--http-port", "0",
                 "--no-stream"]) == 0
    cap = capsys.readouterr()
    assert cap.err.startswith("warning: serving on every interface") and "no authentication" in cap.err
    assert "?token=" in cap.out
