"""What both services share: error mapping, bounded body reading, request ids and logs."""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import logging
import os
import re
import time
import uuid
from typing import Annotated

from fastapi import FastAPI, Request, Security
from fastapi.responses import JSONResponse, Response
from fastapi.security import HTTPBearer
from pydantic import AfterValidator, BaseModel, Field
from starlette.requests import ClientDisconnect

from fleetmap.errors import (
    BadInput,
    FleetmapError,
    Forbidden,
    PayloadTooLarge,
    RequestTimeout,
    Unauthorized,
    Unavailable,
    UnsupportedEncoding,
)
from fleetmap.wire import error_body, status_of

log = logging.getLogger("fleetmap.http")
_REQUEST_ID = re.compile(r"[A-Za-z0-9._:-]{1,64}")
#: Longest wait for the next piece of a request body (a client that stalls is cut off).
BODY_CHUNK_TIMEOUT_S = 30.0
#: On every response: no MIME sniffing, never inside another site's frame, no referrer (a
#: token never leaves in one). A route may set a stricter Content-Security-Policy itself.
SECURITY_HEADERS = {
    "x-content-type-options": "nosniff",
    "x-frame-options": "DENY",
    "content-security-policy": "frame-ancestors 'none'",
    "referrer-policy": "no-referrer",
}


def _four_by_four(v: list[list[float]]) -> list[list[float]]:
    if len(v) != 4 or any(len(r) != 4 for r in v):
        raise ValueError("must be 4x4")
    return v


Matrix4 = Annotated[list[list[float]], AfterValidator(_four_by_four)]
"""A 4x4 matrix in a JSON body, rows of numbers (pose or rigid transform)."""


def install(app: FastAPI) -> None:
    """One exception handler for every domain error, and a request-id middleware."""

    @app.exception_handler(FleetmapError)
    async def _domain_error(request: Request, exc: FleetmapError) -> JSONResponse:
        headers = {}
        if getattr(exc, "retry_after", None) is not None:
            headers["retry-after"] = str(max(1, round(exc.retry_after)))
        return JSONResponse(
            status_code=status_of(exc),
            content=error_body(exc),
            headers=headers,
        )

    @app.exception_handler(ClientDisconnect)
    async def _gone(request: Request, exc: ClientDisconnect) -> Response:
        """A client that hung up mid-body: one INFO line, no traceback (nobody reads this)."""
        log.info("%s %s: client disconnected mid-request", request.method, request.url.path)
        return Response(status_code=400)

    @app.middleware("http")
    async def _request_id(request: Request, call_next):
        rid = request.headers.get("x-request-id", "")
        if not _REQUEST_ID.fullmatch(rid):  # never echo or log a caller's control characters
            rid = uuid.uuid4().hex[:16]
        t = time.perf_counter()
        response = await call_next(request)
        response.headers["x-request-id"] = rid
        for name, value in SECURITY_HEADERS.items():
            response.headers.setdefault(name, value)
        if not request.url.path.startswith("/static/"):  # data and tokens: never cached
            response.headers.setdefault("cache-control", "no-store")
        ms = round(1000 * (time.perf_counter() - t), 1)
        fields = {
            "request_id": rid,
            "method": request.method,
            "path": request.url.path,
            "status": response.status_code,
            "ms": ms,
        }
        log.info(
            "%s %s %s %d %.1fms",
            rid,
            request.method,
            request.url.path,
            response.status_code,
            ms,
            extra=fields,
        )
        return response


async def read_body(
    request: Request, limit: int, content_types: tuple[str, ...] | None = None
) -> bytes:
    """The request body, refused with 413 as soon as it passes `limit` bytes (checked on the
    declared length first, then while streaming, so an oversized body is never held whole).
    Compressed bodies are refused (415): a small gzip could expand past any limit."""
    if content_types is not None:  # a missing Content-Type is taken as the first
        given = request.headers.get("content-type", content_types[0])
        given = given.split(";")[0].strip().lower()
        if given not in content_types:
            raise UnsupportedEncoding(f"Content-Type {given!r}: send {' or '.join(content_types)}")
    encoding = request.headers.get("content-encoding", "identity").strip().lower()
    if encoding not in ("", "identity"):
        raise UnsupportedEncoding(
            f"Content-Encoding {encoding!r} is not accepted: send the body uncompressed"
        )
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            length = int(declared)
        except ValueError as exc:
            raise BadInput(f"Bad Content-Length {declared!r}") from exc
        if length > limit:
            raise PayloadTooLarge(f"Body of {length} bytes exceeds the {limit}-byte limit")
    chunks, size = [], 0
    stream = request.stream().__aiter__()
    while True:
        try:
            chunk = await asyncio.wait_for(anext(stream), BODY_CHUNK_TIMEOUT_S)
        except StopAsyncIteration:
            break
        except TimeoutError as exc:
            raise RequestTimeout(
                f"No body bytes for {BODY_CHUNK_TIMEOUT_S:.0f} s after {size} bytes"
            ) from exc
        size += len(chunk)
        if size > limit:
            raise PayloadTooLarge(f"Body exceeds the {limit}-byte limit")
        chunks.append(chunk)
    body = b"".join(chunks)
    request._body = body  # Starlette's form parser then reads these bytes, not the socket
    return body


class PixelBudget:
    """Decoded image pixels in flight in this process. A request holds its share while its
    images are decoded and aligned; others wait for room, up to `wait_s`, then get 503 with
    Retry-After. One request over the whole budget is refused with 413."""

    def __init__(self, capacity: int, wait_s: float = 30.0, requests: int = 2):
        self.capacity, self.wait_s, self.used = capacity, wait_s, 0
        self._cond = asyncio.Condition()
        self._slots = asyncio.Semaphore(requests)

    @contextlib.asynccontextmanager
    async def slot(self):
        """One of `requests` places for a heavy request, taken before its body is read
        (so waiting requests hold no memory); up to `wait_s`, then 503 with Retry-After."""
        try:
            await asyncio.wait_for(self._slots.acquire(), self.wait_s)
        except TimeoutError as exc:
            raise Unavailable(
                "The aligner is busy with other requests; try again", retry_after=10
            ) from exc
        try:
            yield
        finally:
            self._slots.release()

    @contextlib.asynccontextmanager
    async def hold(self, pixels: int):
        if pixels > self.capacity:
            raise PayloadTooLarge(
                f"{pixels} pixels in one request exceed the {self.capacity}-pixel budget: "
                "send fewer or smaller views"
            )
        async with self._cond:
            try:
                await asyncio.wait_for(
                    self._cond.wait_for(lambda: self.used + pixels <= self.capacity), self.wait_s
                )
            except TimeoutError as exc:
                raise Unavailable(
                    "The aligner is busy with other requests' images; try again",
                    retry_after=10,
                ) from exc
            self.used += pixels
        try:
            yield
        finally:
            async with self._cond:
                self.used -= pixels
                self._cond.notify_all()


def is_loopback(host: str | None) -> bool:
    """Whether a listening address is reachable from this machine only."""
    if host is None:
        return False
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def auth_summary(settings, host: str | None = None) -> str:
    """One line for the start-up log; never the tokens themselves. `host`: the listening
    address when known; an open service on loopback is no alarm (this machine only)."""
    op = settings.operator_token is not None
    n = len(settings.robot_tokens)
    if not op and not n:
        if is_loopback(host):
            return "access control off: no tokens, on loopback: this machine only"
        return "access control OFF: no tokens configured, anyone on the network may read and write"
    return f"access control on: operator token {'set' if op else 'not set'}, {n} robot tokens"


def _same(a: str, b: str) -> bool:
    return hmac.compare_digest(a.encode(), b.encode())


def check_access(request: Request, robot: str | None = None, operator: bool = False) -> str:
    """Who may do this: 'open' without configured tokens, else 'operator' or 'robot:<id>'.

    robot: the robot whose data is written (its own token or the operator's may).
    operator: only the operator token may. Comparisons are constant-time."""
    st = request.app.state.settings
    if st.operator_token is None and not st.robot_tokens:
        return "open"
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token:
        raise Unauthorized("Missing 'Authorization: Bearer <token>' header")
    if st.operator_token is not None and _same(token, st.operator_token.get_secret_value()):
        return "operator"
    owner = None
    for rid, secret in st.robot_tokens.items():  # no early exit: constant time per robot
        if _same(token, secret.get_secret_value()):
            owner = rid
    if owner is None:
        raise Unauthorized("Invalid token")
    if operator:
        raise Forbidden("This action needs the operator token")
    if robot is not None and owner != robot:
        raise Forbidden(f"The token of robot {owner!r} may not write robot {robot!r}")
    return f"robot:{owner}"


#: The bearer scheme, declared so OpenAPI and Swagger UI (its Authorize button) know it;
#: `check_access` does the checking, with the robot-or-operator rules FastAPI's class lacks.
bearer = HTTPBearer(
    auto_error=False,
    description="The operator's token, or a robot's for its own keyframes; none on an open "
    "deployment.",
)


def operator_only(request: Request, _: object = Security(bearer)) -> None:
    """Dependency: the operator token (or an open deployment)."""
    check_access(request, operator=True)


def any_token(request: Request, _: object = Security(bearer)) -> None:
    """Dependency: any valid token (or an open deployment)."""
    check_access(request)


class ErrorBody(BaseModel):
    detail: str = Field(examples=["Unknown robot 'alpha'"])
    error: str = Field(examples=["UnknownRobot"], description="the error class")


#: Every error status the services answer, for each route's OpenAPI entry.
ERROR_RESPONSES = {
    code: {"model": ErrorBody, "description": text}
    for code, text in {
        400: "undecodable frame",
        401: "missing or unknown token",
        403: "a valid token without the right",
        404: "unknown robot, keyframe or cloud",
        408: "the request body stalled",
        409: "conflicting re-send, or a robot deleted meanwhile",
        413: "body, image or pixel budget too large",
        415: "compressed body or wrong Content-Type",
        422: "valid but unusable input",
        500: "stored data failed its integrity check",
        503: "busy (Retry-After) or a dependency unreachable",
    }.items()
}


def install_docs(app: FastAPI) -> None:
    """/docs served with Swagger UI's own files from this service (the swagger-ui-bundle
    package), so it works on a robot network with no internet."""
    import swagger_ui_bundle
    from fastapi.openapi.docs import get_swagger_ui_html
    from fastapi.staticfiles import StaticFiles

    app.mount("/static/swagger", StaticFiles(directory=swagger_ui_bundle.swagger_ui_path))

    @app.get("/docs", include_in_schema=False)
    def docs():
        return get_swagger_ui_html(
            openapi_url="/openapi.json",
            title=f"{app.title} - API",
            swagger_js_url="/static/swagger/swagger-ui-bundle.js",
            swagger_css_url="/static/swagger/swagger-ui.css",
            swagger_favicon_url="/static/swagger/favicon-32x32.png",
        )


class JsonFormatter(logging.Formatter):
    """One JSON object per log line, with the request fields the middleware attaches."""

    FIELDS = ("request_id", "method", "path", "status", "ms")

    def format(self, record: logging.LogRecord) -> str:
        import json

        out = {
            "time": self.formatTime(record),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        out.update({k: getattr(record, k) for k in self.FIELDS if hasattr(record, k)})
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(out)


def header_timeout_protocol(timeout_s: float = 10.0):
    """uvicorn's h11 protocol with a deadline for every request's headers: a client that
    opens connections and sends its headers a byte at a time (slowloris) is cut off after
    `timeout_s` (request bodies have their own, `BODY_CHUNK_TIMEOUT_S`)."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class HeaderTimeoutH11(H11Protocol):
        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._deadline = self.loop.call_later(timeout_s, self._headers_late)

        def _headers_late(self) -> None:
            idle = self.cycle is None or self.cycle.response_complete
            if idle and not self.transport.is_closing():  # its headers never came
                log.warning(
                    "closing a connection whose request headers took over %.0f s", timeout_s
                )
                self.transport.close()

        def handle_events(self) -> None:
            super().handle_events()
            if self.cycle is not None and not self.cycle.response_complete and self._deadline:
                self._deadline.cancel()  # headers complete: the request runs
                self._deadline = None

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if self._deadline is None and not self.transport.is_closing():
                self._deadline = self.loop.call_later(timeout_s, self._headers_late)

        def connection_lost(self, exc) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
            super().connection_lost(exc)

    return HeaderTimeoutH11


def refuse_flat_names(prefix: str, params_class, nested: str, renamed=()) -> None:
    """Parameters are nested settings now (PREFIX_ALIGN__MIN_INLIERS); a variable of the
    old flat form (PREFIX_MIN_INLIERS) is refused with its new name, never ignored."""
    import dataclasses

    names = [(f.name, f.name) for f in dataclasses.fields(params_class)] + list(renamed)
    for was, now in names:
        old = f"{prefix}{was.upper()}"
        if old in os.environ:
            raise BadInput(f"{old} is no longer read: set {prefix}{nested}__{now.upper()} instead")


def secrets_dir() -> str | None:
    """Where settings may also come from files, one per variable named like it in lower case
    (`fleetmap_place_db_operator_token`): FLEETMAP_SECRETS_DIR, else Docker's /run/secrets
    where it exists. Tokens need not sit in the environment or in a compose file."""
    path = os.environ.get("FLEETMAP_SECRETS_DIR") or "/run/secrets"
    return path if os.path.isdir(path) else None
