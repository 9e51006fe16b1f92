"""Errors over HTTP: every domain error answered by one handler, and the error body's
schema each route's OpenAPI entry names."""

from __future__ import annotations

import logging
from http import HTTPStatus

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from fleetmap.errors import FleetmapError
from fleetmap.wire import error_body, status_of

log = logging.getLogger("fleetmap.http")


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
        404: "unknown robot or keyframe, or nothing solved yet",
        408: "the request body stalled",
        409: "conflicting re-send, or a robot deleted meanwhile",
        413: "body, image or pixel budget too large",
        415: "compressed body or wrong Content-Type",
        422: "valid but unusable input",
        500: "stored data failed its integrity check",
        503: "busy (Retry-After) or a dependency unreachable",
    }.items()
}


def install_error_handlers(app: FastAPI) -> None:
    """One exception handler for every domain error (its status and body from
    `fleetmap.wire`), and one for a client that hung up mid-body."""

    @app.exception_handler(FleetmapError)
    async def _domain_error(request: Request, exc: FleetmapError) -> JSONResponse:
        headers = {}
        if getattr(exc, "retry_after", None) is not None:
            headers["retry-after"] = str(max(1, round(exc.retry_after)))
        return JSONResponse(status_code=status_of(exc), content=error_body(exc), headers=headers)

    @app.exception_handler(StarletteHTTPException)
    async def _framework_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        """The framework's own refusals (a body it cannot parse, a method not allowed) in the
        same body as every other error: `error` was missing (an outside tester's review)."""
        name = HTTPStatus(exc.status_code).phrase.replace(" ", "").replace("-", "")
        body = {"detail": str(exc.detail), "error": name}
        return JSONResponse(status_code=exc.status_code, content=body, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        """A query, path or JSON field that does not validate: 422, one readable line per
        field in `detail` (FastAPI's list of dicts, without `error`, before)."""
        lines = [
            f"{'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg', 'invalid')}"
            for e in exc.errors()
        ]
        body = {"detail": "; ".join(lines) or "invalid request", "error": "ValidationError"}
        return JSONResponse(status_code=422, content=body)

    @app.exception_handler(ClientDisconnect)
    async def _gone(request: Request, exc: ClientDisconnect) -> Response:
        """A client that hung up mid-body: one INFO line, no traceback (nobody reads this)."""
        log.info("%s %s: client disconnected mid-request", request.method, request.url.path)
        return Response(status_code=400)
