"""Every request's id, security headers and access-log line; HEAD answered as GET."""

from __future__ import annotations

import logging
import re
import time
import uuid

from fastapi import FastAPI, Request

log = logging.getLogger("fleetmap.http")
_REQUEST_ID = re.compile(r"[A-Za-z0-9._:-]{1,64}")
#: On every response: no MIME sniffing, never inside another site's frame, no referrer (a
#: token never leaves in one). A route may set a stricter Content-Security-Policy itself.
SECURITY_HEADERS = {
    "x-content-type-options": "nosniff",
    "x-frame-options": "DENY",
    "content-security-policy": "frame-ancestors 'none'",
    "referrer-policy": "no-referrer",
}


class HeadAsGet:
    """HEAD answered as the GET of the same path without its body (RFC 9110, 9.3.2): uptime
    checkers and load balancers probe with HEAD, which FastAPI's GET routes answer 405. A
    path without GET still answers 405 (or 404)."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def headless(message) -> None:
            if message["type"] == "http.response.body":
                if message.get("more_body", False):
                    return
                message = {"type": "http.response.body", "body": b"", "more_body": False}
            await send(message)

        await self.app({**scope, "method": "GET", "fleetmap_head": True}, receive, headless)


def install_middleware(app: FastAPI) -> None:
    """The request-id middleware: an id per request (the caller's if sane), the security
    headers, no caching of data, and one log line (with fields for JSON logs); outside it,
    HEAD as GET (`HeadAsGet`)."""

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
        method = "HEAD" if request.scope.get("fleetmap_head") else request.method
        fields = {
            "request_id": rid,
            "method": method,
            "path": request.url.path,
            "status": response.status_code,
            "ms": ms,
        }
        log.info(
            "%s %s %s %d %.1fms",
            rid,
            method,
            request.url.path,
            response.status_code,
            ms,
            extra=fields,
        )
        return response

    app.add_middleware(HeadAsGet)  # added last: outermost
