"""Who may talk to the web UI: the access token (query, bearer header or cookie), the Host-header
check against DNS rebinding, the request-body size limit, and the headers every response carries.
Pure ASGI middleware (no FastAPI), so each guard answers before any route or body parsing runs.
"""

from __future__ import annotations

import ipaddress
import json
import re
import secrets
import socket
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from typing import Any
from urllib.parse import parse_qs

from hitl_slam.errors import InputError

__all__ = [
    "COOKIE",
    "BodyLimit",
    "HostCheck",
    "ResponseHeaders",
    "TokenCheck",
    "check_token",
    "host_header_name",
    "is_loopback",
    "new_token",
    "token_matches",
]

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

_TOKEN = re.compile(r"[A-Za-z0-9._~-]{8,200}")

COOKIE = "hitl_token"
"""The cookie ``GET /?token=T`` sets, so the page's own requests need no token in their URLs."""

_LOOPBACK_NAMES = ("localhost", "localhost.", "ip6-localhost", "ip6-loopback")
# Every response: never cached (the map changes under the same URL, and responses may hold the
# token), never sniffed into another type, never framed by another site, no token in Referer.
_ALWAYS = (
    (b"cache-control", b"no-store"),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
    (b"content-security-policy", b"frame-ancestors 'none'"),
)


def new_token() -> str:
    """A fresh random access token (192 bits, URL-safe), as Jupyter prints in its URL."""
    return secrets.token_urlsafe(24)


def check_token(token: str) -> None:
    """Raise InputError unless ``token`` is usable in a URL and a cookie as it is."""
    if not _TOKEN.fullmatch(token):
        raise InputError(
            "the access token must be 8 to 200 letters, digits, '.', '_', '~' or '-'; leave "
            "--token out to get a random one"
        )


def token_matches(presented: str, token: str) -> bool:
    """Constant-time comparison (bytes, so a non-ASCII guess cannot raise)."""
    return secrets.compare_digest(presented.encode("utf-8"), token.encode("utf-8"))


def is_loopback(host: str) -> bool:
    """Whether binding ``host`` keeps the server reachable from this machine only.

    An address must be a loopback address; a name must be ``localhost`` or resolve to loopback
    addresses only. The wildcard addresses (``0.0.0.0``, ``::``, ``""``) are not loopback.
    """
    name = host.strip().strip("[]").lower()
    if not name:
        return False
    if name in _LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(name, None)
    except (OSError, UnicodeError):
        return False
    addresses = {info[4][0] for info in infos}
    return bool(addresses) and all(
        ipaddress.ip_address(str(a).split("%")[0]).is_loopback for a in addresses
    )


def host_header_name(value: str) -> str:
    """The host name of a Host header, lower case, without port (IPv6 keeps its brackets)."""
    value = value.strip().lower()
    if value.startswith("["):
        end = value.find("]")
        return value if end < 0 else value[: end + 1]
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", ()):
        if key.lower() == name:
            return bytes(value).decode("latin-1")
    return None


async def _refuse(send: Send, status: int, detail: str, close: bool = False) -> None:
    body = json.dumps({"detail": detail}).encode("utf-8")
    headers = [
        (b"content-type", b"application/json"),
        (b"content-length", str(len(body)).encode("ascii")),
    ]
    if close:
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body, "more_body": False})


class ResponseHeaders:
    """Adds :data:`_ALWAYS` to every HTTP response, including the guards' refusals."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", ()))
                present = {bytes(k).lower() for k, _ in headers}
                headers += [(k, v) for k, v in _ALWAYS if k not in present]
                message["headers"] = headers
            await send(message)

        await self.app(scope, receive, send_with_headers)


class HostCheck:
    """DNS-rebinding protection: a page of another site whose name was made to resolve to
    127.0.0.1 sends its own name in the Host header; only loopback names (and the bound name)
    get through. Nothing is checked when ``allowed`` is None (a non-loopback bind, where the
    token is mandatory and the names users type cannot be known)."""

    def __init__(self, app: ASGIApp, *, allowed: Iterable[str] | None) -> None:
        self.app = app
        self.allowed = None if allowed is None else {host_header_name(h) for h in allowed}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or self.allowed is None:
            await self.app(scope, receive, send)
            return
        host = _header(scope, b"host")
        if host is None or host_header_name(host) not in self.allowed:
            await _refuse(
                send,
                403,
                f"unexpected Host header {host!r}; open the page at http://127.0.0.1:PORT/ "
                "as printed by `hitl-slam serve`",
            )
            return
        await self.app(scope, receive, send)


def _port_of(scope: Scope) -> str:
    host = _header(scope, b"host") or ""
    tail = host.rsplit("]", 1)[-1]
    return tail.rsplit(":", 1)[1] if ":" in tail else ""


class TokenCheck:
    """Every route needs the token (query ``token``, ``Authorization: Bearer``, or the cookie).

    ``GET /`` with a valid token sets the cookie :data:`COOKIE` (HttpOnly, SameSite=Strict,
    Path=/) and a copy named after the port (``hitl_token_8765``): cookies ignore ports, so two
    servers on one machine would otherwise overwrite each other's cookie in the same browser.
    """

    def __init__(self, app: ASGIApp, *, token: str | None) -> None:
        self.app = app
        self.token = token

    def _presented(self, scope: Scope) -> list[str]:
        out: list[str] = []
        query = bytes(scope.get("query_string", b"")).decode("latin-1")
        out += parse_qs(query, keep_blank_values=True).get("token", [])
        auth = _header(scope, b"authorization")
        if auth is not None:
            kind, _, value = auth.strip().partition(" ")
            if kind.lower() == "bearer":
                out.append(value.strip())
        cookie = _header(scope, b"cookie")
        if cookie is not None:
            from starlette.requests import cookie_parser

            jar = cookie_parser(cookie)
            for name in (COOKIE, f"{COOKIE}_{_port_of(scope)}"):
                if name in jar:
                    out.append(jar[name])
        return out

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or self.token is None:
            await self.app(scope, receive, send)
            return
        token = self.token
        if not any(token_matches(p, token) for p in self._presented(scope)):
            await _refuse(
                send,
                403,
                "missing or wrong access token; open the URL that `hitl-slam serve` printed "
                "(it ends in ?token=...)",
            )
            return
        if scope.get("path") != "/" or scope.get("method") != "GET":
            await self.app(scope, receive, send)
            return
        attributes = "; HttpOnly; SameSite=Strict; Path=/"
        cookies = [f"{COOKIE}={token}{attributes}"]
        port = _port_of(scope)
        if port:
            cookies.append(f"{COOKIE}_{port}={token}{attributes}")

        async def send_with_cookie(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", ()))
                headers += [(b"set-cookie", c.encode("latin-1")) for c in cookies]
                message["headers"] = headers
            await send(message)

        await self.app(scope, receive, send_with_cookie)


class BodyLimit:
    """Refuses request bodies over ``max_body`` bytes with 413: at once from Content-Length, and
    while reading for a body without one (chunked), before any of it reaches the app. Bodies here
    are small JSON objects, so the app gets the body buffered."""

    def __init__(self, app: ASGIApp, *, max_body: int) -> None:
        self.app = app
        self.max_body = max_body

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        too_large = f"request body over {self.max_body} bytes; send a smaller request"
        declared = _header(scope, b"content-length")
        if declared is not None:
            try:
                length = int(declared)
            except ValueError:
                await _refuse(send, 400, "Content-Length is not a number", close=True)
                return
            if length > self.max_body:
                await _refuse(send, 413, too_large, close=True)
                return
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return  # the client left; nobody to answer
            chunk = bytes(message.get("body", b""))
            size += len(chunk)
            if size > self.max_body:
                await _refuse(send, 413, too_large, close=True)
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        delivered = False

        async def replay() -> Message:
            nonlocal delivered
            if not delivered:
                delivered = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)
