"""The web UI's HTTP layer: routes over a :class:`~hitl_slam.web.host.SessionHost`, the static
front end, and the guards of :mod:`hitl_slam.web.security`. Blocking work (solves, EM, file
output) runs in the threadpool, so the long-poll and other tabs keep answering during a solve.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.staticfiles import StaticFiles
from starlette.types import Receive, Scope, Send

from hitl_slam.alignment import AlignmentRefused
from hitl_slam.errors import HitlSlamError, InputError, SolverError
from hitl_slam.web import schemas
from hitl_slam.web.host import NothingToDo, OutsideFolder, SessionHost
from hitl_slam.web.security import (
    BodyLimit,
    HostCheck,
    JsonBodyCheck,
    OriginCheck,
    ResponseHeaders,
    TokenCheck,
    check_token,
    is_loopback,
)

__all__ = ["DEFAULT_MAX_BODY", "STATIC_DIR", "create_app"]

DEFAULT_MAX_BODY = 1 << 20
"""[bytes] Largest request body accepted (a drawing is a few hundred bytes)."""

STATIC_DIR = Path(__file__).parent / "static"
"""The front end (index.html, style.css, js/), served as is: no build step."""

_LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "[::1]")
_MISSING_PAGE = """<!doctype html><meta charset="utf-8"><title>hitl-slam</title>
<p>The hitl-slam server is running, but the web page is not installed
(<code>{path}</code> is missing). Reinstall hitl-slam; the HTTP API under /api works.</p>
"""


class _Static:
    """StaticFiles that answers 404 (not a server error) while the folder does not exist."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.files = StaticFiles(directory=directory, check_dir=False)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not self.directory.is_dir():
            await Response("not found", status_code=404, media_type="text/plain")(
                scope, receive, send
            )
            return
        await self.files(scope, receive, send)


def _error_handler(status: int) -> Callable[[Request, Exception], Awaitable[Response]]:
    """An exception handler answering ``status`` with the error's message as ``detail``."""

    async def handle(_request: Request, exc: Exception) -> Response:
        return JSONResponse({"detail": str(exc)}, status_code=status)

    return handle


def create_app(
    host: SessionHost,
    *,
    token: str | None,
    max_body: int = DEFAULT_MAX_BODY,
    bind: str = "127.0.0.1",
    static_dir: str | os.PathLike[str] | None = None,
) -> FastAPI:
    """The web UI for ``host``'s session.

    Args:
        host: the session and its change notification.
        token: required on every request (query ``token``, ``Authorization: Bearer``, or the
            cookie set by ``GET /?token=...``); None: no token (loopback binds only).
        max_body: [bytes] larger request bodies are refused with 413.
        bind: the address the server listens on; on a loopback address only Host headers naming
            it or localhost, 127.0.0.1, [::1] are served (DNS-rebinding protection). On any
            bind, a request other than GET/HEAD/OPTIONS must come from the page's own origin
            and carry a JSON Content-Type or the X-Hitl-Slam header (see
            :class:`~hitl_slam.web.security.OriginCheck`).
        static_dir: the front end's folder (default :data:`STATIC_DIR`).

    Raises:
        InputError: no token on a non-loopback ``bind``, a token with characters other than
            letters, digits and ``._~-`` (8 to 200 of them), or ``max_body`` < 1.
    """
    loopback = is_loopback(bind)
    if token is None and not loopback:
        raise InputError(f"refusing to serve on {bind} without an access token; drop --no-token")
    if token is not None:
        check_token(token)
    if max_body < 1:
        raise InputError(f"max_body must be at least 1 byte, got {max_body}")
    static = STATIC_DIR if static_dir is None else Path(static_dir)

    app = FastAPI(
        title="hitl-slam",
        docs_url=None,
        redoc_url=None,
        openapi_url=None,
        swagger_ui_oauth2_redirect_url=None,
    )

    @app.exception_handler(RequestValidationError)
    async def _invalid(_request: Request, exc: RequestValidationError) -> JSONResponse:
        # Only where and what: echoing the input back could fail (a NaN is not JSON) and would
        # repeat up to max_body bytes.
        detail = [
            {
                "loc": [str(part) for part in e.get("loc", ())],
                "msg": str(e.get("msg", "")),
                "type": str(e.get("type", "")),
            }
            for e in exc.errors()
        ]
        return JSONResponse({"detail": detail}, status_code=422)

    # Starlette picks the handler of the most specific class, so the subclasses come first
    # only for the reader: NothingToDo, AlignmentRefused and OutsideFolder are InputErrors with
    # their own status (a refused alignment is not a malformed request: the map, as it stands,
    # cannot be aligned now; nothing changed).
    for error, status in (
        (NothingToDo, 409),
        (AlignmentRefused, 409),
        (OutsideFolder, 403),
        (InputError, 400),
        (SolverError, 500),
        (HitlSlamError, 500),
    ):
        app.add_exception_handler(error, _error_handler(status))

    @app.get("/", response_model=None)
    def index() -> Response:
        page = static / "index.html"
        if not page.is_file():
            return HTMLResponse(_MISSING_PAGE.format(path=page), status_code=404)
        return FileResponse(page, media_type="text/html")

    @app.get("/api/state", response_model=schemas.State)
    async def state(after: int | None = None) -> dict[str, Any]:
        if after is None:
            return host.state()
        # Waiting costs no thread: the host's change callback sets an event on this loop.
        loop = asyncio.get_running_loop()
        changed = asyncio.Event()

        def wake() -> None:
            loop.call_soon_threadsafe(changed.set)

        host.add_listener(wake)
        try:
            if host.version == after and not host.closing:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(changed.wait(), host.poll_timeout)
        finally:
            host.remove_listener(wake)
        return host.state()

    def binary(version: int | None, data: bytes) -> Response:
        headers = {} if version is None else {"X-Map-Version": str(version)}
        return Response(data, media_type="application/octet-stream", headers=headers)

    @app.get("/api/map/points", response_class=Response)
    def points() -> Response:
        return binary(*host.points())

    # The arrays are ready-made bytes (the snapshot's, read under a lock held only briefly): they
    # are answered on the event loop, without a trip through the threadpool.
    @app.get("/api/map/scans", response_class=Response)
    async def scans() -> Response:
        # Robot-frame points: they never change, so the page fetches them once.
        return binary(None, host.scans())

    @app.get("/api/map/poses", response_class=Response)
    async def poses() -> Response:
        return binary(*host.poses())

    @app.get("/api/map/offsets", response_class=Response)
    async def offsets() -> Response:
        return binary(host.version, host.offsets())

    # A change or an interpretation runs in the threadpool; its answer is checked against the
    # response model back on the event loop (a plain `def` route would take a second trip through
    # the threadpool for that, each a wait for a thread to be scheduled on a busy machine).
    @app.post("/api/interpret", response_model=schemas.Preview)
    async def interpret(drawn: schemas.Drawn) -> dict[str, Any]:
        return await run_in_threadpool(host.interpret, drawn.to_correction())

    @app.post("/api/corrections", response_model=schemas.Applied)
    async def corrections(drawn: schemas.Drawn) -> dict[str, Any]:
        return await run_in_threadpool(host.apply, drawn.to_correction())

    @app.get("/api/map/info", response_model=schemas.MapInfo)
    async def map_info() -> dict[str, Any]:
        # Built once with the host: it never changes, so the page fetches it once.
        return host.map_info()

    @app.get("/api/loop_closures", response_model=schemas.LoopClosures)
    async def loop_closures() -> dict[str, Any]:
        # Built once with the host: they never change, so the page fetches them once.
        return host.loop_closures()

    @app.post("/api/loop_closures", response_model=schemas.State)
    async def set_loop_closure(request: schemas.LoopClosureRequest) -> dict[str, Any]:
        return await run_in_threadpool(host.set_loop_closure, request.index, request.rejected)

    @app.post("/api/align", response_model=schemas.State)
    async def align() -> dict[str, Any]:
        # Seconds to a minute on a big map: the long-poll and the reads keep answering meanwhile.
        return await run_in_threadpool(host.align)

    @app.post("/api/undo", response_model=schemas.State)
    async def undo() -> dict[str, Any]:
        return await run_in_threadpool(host.undo)

    @app.post("/api/redo", response_model=schemas.State)
    async def redo() -> dict[str, Any]:
        return await run_in_threadpool(host.redo)

    @app.get("/api/relations", response_model=list[schemas.Relation])
    def relations() -> list[dict[str, Any]]:
        return host.relations()

    @app.post("/api/save", response_model=schemas.Files)
    def save(request: schemas.SaveRequest | None = None) -> dict[str, Any]:
        return {"files": host.save(None if request is None else request.name)}

    @app.post("/api/export", response_model=schemas.Files)
    def export(request: schemas.ExportRequest) -> dict[str, Any]:
        return {"files": host.export(request.path)}

    @app.post("/api/journal/step", response_model=schemas.Applied)
    async def journal_step() -> dict[str, Any]:
        return await run_in_threadpool(host.journal_step)

    app.mount("/static", _Static(static), name="static")

    # Outermost first: headers on everything, then Host, same origin (every mode, every bind),
    # token, body size, JSON body checks, routes.
    app.add_middleware(JsonBodyCheck)
    app.add_middleware(BodyLimit, max_body=max_body)
    app.add_middleware(TokenCheck, token=token)
    app.add_middleware(OriginCheck)
    app.add_middleware(HostCheck, allowed=(bind, *_LOOPBACK_HOSTS) if loopback else None)
    app.add_middleware(ResponseHeaders)
    return app
