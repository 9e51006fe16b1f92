"""What both services share: error mapping, bounded body reading, request ids and logs."""

from __future__ import annotations

import logging
import time
import uuid

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from shared.errors import (
    BadFrame,
    BadInput,
    BadRobotData,
    BadVocabulary,
    Conflict,
    FleetmapError,
    NotEnoughCorrespondences,
    PayloadTooLarge,
    Unavailable,
    UnknownKeyframe,
    UnknownRobot,
)

log = logging.getLogger("fleetmap.http")

STATUS = [
    (PayloadTooLarge, 413),
    (BadFrame, 400),
    (UnknownRobot, 404),
    (UnknownKeyframe, 404),
    (Conflict, 409),
    (NotEnoughCorrespondences, 422),
    (BadInput, 422),
    (BadRobotData, 422),
    (BadVocabulary, 500),
    (Unavailable, 503),
]


def status_of(exc: FleetmapError) -> int:
    for cls, code in STATUS:
        if isinstance(exc, cls):
            return code
    return 400


def install(app: FastAPI) -> None:
    """One exception handler for every domain error, and a request-id middleware."""

    @app.exception_handler(FleetmapError)
    async def _domain_error(request: Request, exc: FleetmapError) -> JSONResponse:
        return JSONResponse(
            status_code=status_of(exc), content={"detail": str(exc), "error": type(exc).__name__}
        )

    @app.middleware("http")
    async def _request_id(request: Request, call_next):
        rid = request.headers.get("x-request-id", "")[:64] or uuid.uuid4().hex[:16]
        t = time.perf_counter()
        response = await call_next(request)
        response.headers["x-request-id"] = rid
        log.info(
            "%s %s %s %d %.1fms",
            rid,
            request.method,
            request.url.path,
            response.status_code,
            1000 * (time.perf_counter() - t),
        )
        return response


async def read_body(request: Request, limit: int) -> bytes:
    """The request body, refused with 413 as soon as it passes `limit` bytes (checked on the
    declared length first, then while streaming, so an oversized body is never held whole)."""
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            length = int(declared)
        except ValueError as exc:
            raise BadInput(f"Bad Content-Length {declared!r}") from exc
        if length > limit:
            raise PayloadTooLarge(f"Body of {length} bytes exceeds the {limit}-byte limit")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise PayloadTooLarge(f"Body exceeds the {limit}-byte limit")
        chunks.append(chunk)
    return b"".join(chunks)
