"""Who may talk to the web UI: the access token (query, bearer header or cookie), the Host-header
check against DNS rebinding, the same-origin check on every state-changing request (cross-site
request forgery), the request-body size limit, the JSON body checks, and the headers every
response carries. Pure ASGI middleware (no FastAPI), so each guard answers before any route or
body parsing runs.
"""

from __future__ import annotations

import email.message
import ipaddress
import json
import re
import secrets
import socket
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from typing import Any
from urllib.parse import parse_qs, urlsplit

from hitl_slam.errors import InputError

__all__ = [
    "COOKIE",
    "CUSTOM_HEADER",
    "MAX_JSON_DEPTH",
    "MAX_NUMBER_LENGTH",
    "BodyLimit",
    "HostCheck",
    "JsonBodyCheck",
    "OriginCheck",
    "ResponseHeaders",
    "TokenCheck",
    "check_token",
    "host_header_name",
    "is_loopback",
    "new_token",
    "same_origin",
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

CUSTOM_HEADER = "X-Hitl-Slam"
"""A header the page sends with every POST: a page of another origin cannot add it without the
CORS preflight this server never grants. A body-less POST needs it (or ``Authorization``, or a
JSON ``Content-Type``)."""

MAX_JSON_DEPTH = 32
"""Deepest nesting of arrays and objects in a request body (a drawing nests 4 deep)."""

MAX_NUMBER_LENGTH = 100
"""[characters] Longest number in a request body (JavaScript writes at most 24)."""

_SAFE_METHODS = ("GET", "HEAD", "OPTIONS")
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


def _replaying(body: bytes, receive: Receive) -> Receive:
    """A ``receive`` that hands the app the body already read, once, then defers to the
    server's (disconnects)."""
    delivered = False

    async def replay() -> Message:
        nonlocal delivered
        if not delivered:
            delivered = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


async def _refuse(send: Send, status: int, detail: Any, close: bool = False) -> None:
    body = json.dumps({"detail": detail}).encode("utf-8")
    headers = [
        (b"content-type", b"application/json"),
        (b"content-length", str(len(body)).encode("ascii")),
    ]
    if close:
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body, "more_body": False})


_TOKEN_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>hitl-slam: access token needed</title>
<style>body{font:16px/1.5 system-ui,sans-serif;max-width:40em;margin:3em auto;padding:0 1em}
code{background:#eee;padding:0 .2em}</style></head><body>
<h1>This hitl-slam server needs its access token</h1>
<p>Open the address that <code>hitl-slam serve</code> printed when it started, the whole line
after <code>listening on</code>, ending in <code>?token=...</code>, e.g.
<code>http://127.0.0.1:8765/?token=...</code>. The page then remembers the token (a cookie), so
this address works without it afterwards in this browser.</p>
<p>Lost it? Stop the server (Ctrl-C) and start it again: it prints a new address. To choose
the token yourself, start it with <code>--token YOUR-TOKEN</code>.</p>
</body></html>
"""


async def _refuse_page(send: Send) -> None:
    body = _TOKEN_PAGE.encode("utf-8")
    headers = [
        (b"content-type", b"text/html; charset=utf-8"),
        (b"content-length", str(len(body)).encode("ascii")),
    ]
    await send({"type": "http.response.start", "status": 403, "headers": headers})
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


def same_origin(origin: str, host: str | None, scheme: str = "http") -> bool:
    """Whether an ``Origin`` header names this server as the browser reached it: the request's
    scheme and its Host header (host name case-insensitive, the scheme's default port filled in).
    ``null`` (sandboxed frames, file pages, privacy redirects) and anything unparsable are not."""
    if host is None:
        return False
    default = {"http": 80, "https": 443}
    try:
        theirs = urlsplit(origin.strip())
        ours = urlsplit(f"//{host.strip()}")
        their_port = theirs.port or default.get(theirs.scheme.lower())
        our_port = ours.port or default.get(scheme)
    except ValueError:
        return False
    if theirs.path or theirs.query or theirs.fragment or theirs.username or ours.username:
        return False
    return (
        theirs.scheme.lower() == scheme
        and theirs.hostname is not None
        and theirs.hostname == ours.hostname
        and their_port == our_port
    )


def _shown(value: str) -> str:
    """A header value quoted for a message, cut short (it comes from the client)."""
    return repr(value if len(value) <= 80 else value[:80] + "...")


def _is_json(content_type: str | None) -> bool:
    """``application/json`` or ``application/*+json``, the types FastAPI parses as JSON."""
    if content_type is None:
        return False
    message = email.message.Message()
    message["content-type"] = content_type
    subtype = message.get_content_subtype()
    return message.get_content_maintype() == "application" and (
        subtype == "json" or subtype.endswith("+json")
    )


class OriginCheck:
    """Cross-site request forgery protection, in every mode (token or not, any bind): a request
    other than GET, HEAD or OPTIONS is refused (403) when its ``Origin`` is not this server's own
    (the scheme and Host it was sent to), or when ``Sec-Fetch-Site`` says another site or origin
    sent it; browsers send at least one of them with every POST, other clients (curl, scripts)
    neither. It must also be one a page of another origin cannot send without a CORS preflight
    (which this server never grants): a JSON ``Content-Type``, or the header
    :data:`CUSTOM_HEADER` or ``Authorization``; otherwise 415. So neither a form post nor a
    body-less ``fetch`` from another page changes anything, even with the token in a cookie."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("method", "GET") in _SAFE_METHODS:
            await self.app(scope, receive, send)
            return
        host = _header(scope, b"host")
        origin = _header(scope, b"origin")
        site = _header(scope, b"sec-fetch-site")
        scheme = str(scope.get("scheme", "http")).lower()
        own = f"{scheme}://{host}" if host else "this server's address"
        refused = None
        if origin is not None and not same_origin(origin, host, scheme):
            refused = f"its Origin {_shown(origin)} is not this server's own ({own})"
        elif site is not None and site.strip().lower() not in ("same-origin", "none"):
            refused = f"it was sent from another site or origin (Sec-Fetch-Site: {_shown(site)})"
        if refused is not None:
            await _refuse(
                send,
                403,
                f"cross-origin request refused: {refused}; only the hitl-slam page itself may "
                "change the session: open the URL that `hitl-slam serve` printed",
            )
            return
        custom = _header(scope, CUSTOM_HEADER.lower().encode("ascii")) is not None
        if not (custom or _is_json(_header(scope, b"content-type"))) and (
            _header(scope, b"authorization") is None
        ):
            await _refuse(
                send,
                415,
                f"a {scope.get('method')} request needs the header Content-Type: "
                f"application/json (or {CUSTOM_HEADER}: 1), so that no other web page can send "
                "it; e.g. curl -X POST -H 'Content-Type: application/json' ...",
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
            if scope.get("path") == "/" and scope.get("method") in ("GET", "HEAD"):
                await _refuse_page(send)  # a person at a browser: say how to get in
                return
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
        await self.app(scope, _replaying(body, receive), send)


class _BodyError(Exception):
    """What is wrong with a request body, and the status to answer."""

    def __init__(self, status: int, detail: Any) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


# One token at a time, left to right, each string (even an unterminated one) consumed whole: one
# linear pass, whatever the body holds.
_STRING_OR_BRACKET = re.compile(r'"(?:[^"\\]|\\.)*"?|[\[\]{}]', re.DOTALL)


def _too_deep(text: str) -> bool:
    """Whether JSON ``text`` nests arrays and objects deeper than :data:`MAX_JSON_DEPTH`
    (strings skipped); stops at the first level too deep."""
    depth = 0
    for match in _STRING_OR_BRACKET.finditer(text):
        token = match.group()
        if token in ("[", "{"):
            depth += 1
            if depth > MAX_JSON_DEPTH:
                return True
        elif token in ("]", "}"):
            depth -= 1
    return False


def _short_number(text: str) -> str:
    if len(text) > MAX_NUMBER_LENGTH:
        raise _BodyError(
            400,
            f"the body holds a number of {len(text)} characters ({text[:20]}...); numbers may "
            f"have at most {MAX_NUMBER_LENGTH}: send coordinates in metres as plain decimals",
        )
    return text


def check_json_body(body: bytes, content_type: str | None) -> None:
    """Raise :class:`_BodyError` unless ``body`` is JSON the routes can take as it is: UTF-8
    (the only charset declared, if any), nested at most :data:`MAX_JSON_DEPTH` deep, no number
    longer than :data:`MAX_NUMBER_LENGTH` characters, and well formed (422 as FastAPI's own)."""
    if not _is_json(content_type):
        raise _BodyError(
            415,
            f"the body's Content-Type is {_shown(content_type or '(none)')}; send the body as "
            "JSON with Content-Type: application/json",
        )
    message = email.message.Message()
    message["content-type"] = content_type or ""
    charset = message.get_param("charset")
    if charset is not None:
        name = str(charset).strip().lower()
        if name not in ("utf-8", "utf8"):
            raise _BodyError(
                415,
                f"the body is declared charset={_shown(str(charset))}; send JSON in UTF-8 "
                "(Content-Type: application/json, or charset=utf-8)",
            )
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _BodyError(
            400,
            f"the body is not UTF-8 (byte 0x{body[exc.start]:02x} at offset {exc.start}: "
            f"{exc.reason}); send JSON encoded in UTF-8",
        ) from None
    if _too_deep(text):
        raise _BodyError(
            400,
            f"the body nests arrays and objects more than {MAX_JSON_DEPTH} levels deep, the "
            'most accepted (a correction is {"mode": ..., "a": [[x, y], [x, y]], "b": ...})',
        )
    try:
        json.loads(text, parse_int=_short_number, parse_float=_short_number)
    except json.JSONDecodeError as exc:
        raise _BodyError(
            422,
            [
                {
                    "loc": ["body", str(exc.pos)],
                    "msg": f"JSON decode error: {exc.msg} (line {exc.lineno} column {exc.colno})",
                    "type": "json_invalid",
                }
            ],
        ) from None
    except RecursionError:  # unreachable after the depth check; never a traceback all the same
        raise _BodyError(400, "the body nests too deep to read") from None


class JsonBodyCheck:
    """Refuses a request body the routes would mis-read or could only call "an error parsing
    the body", saying what is wrong (see :func:`check_json_body`): a body that is not JSON
    (415), another charset than UTF-8 (415), bytes that are not UTF-8, nesting too deep or a
    number too long (400), malformed JSON (422); for every method but GET, HEAD and OPTIONS.
    Reads the whole body first, so it belongs inside :class:`BodyLimit`; bodies that pass reach
    the app unchanged."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("method", "GET") in _SAFE_METHODS:
            await self.app(scope, receive, send)  # no route reads a GET's body
            return
        chunks: list[bytes] = []
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return  # the client left; nobody to answer
            chunks.append(bytes(message.get("body", b"")))
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        if body:
            try:
                check_json_body(body, _header(scope, b"content-type"))
            except _BodyError as exc:
                await _refuse(send, exc.status, exc.detail)
                return
        await self.app(scope, _replaying(body, receive), send)
