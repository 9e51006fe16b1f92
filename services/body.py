"""Request bodies read with a limit: refused as soon as they pass it, never held whole."""

from __future__ import annotations

import asyncio

from fastapi import Request

from fleetmap.errors import BadInput, PayloadTooLarge, RequestTimeout, UnsupportedEncoding

#: Longest wait for the next piece of a request body (a client that stalls is cut off).
BODY_CHUNK_TIMEOUT_S = 30.0


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
