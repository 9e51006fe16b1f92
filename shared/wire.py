"""The wire contract shared by the services and their clients: which HTTP status each
domain error travels as (and back), and the multipart layout of `POST /align`.

Services answer `{"detail": message, "error": class name}` with `status_of(error)`;
clients raise `error_from(status, body)`: the same class the server raised, so a caller
catches `UnknownRobot` or `Conflict` whichever side of the wire it is on."""

from __future__ import annotations

import json

from fleetmap import errors as E

#: (error class, HTTP status), the most specific class first.
STATUS: list[tuple[type[E.FleetmapError], int]] = [
    (E.Unauthorized, 401),
    (E.Forbidden, 403),
    (E.UnsupportedEncoding, 415),
    (E.PayloadTooLarge, 413),
    (E.RequestTimeout, 408),
    (E.BadFrame, 400),
    (E.UnknownRobot, 404),
    (E.UnknownKeyframe, 404),
    (E.NotSolved, 404),
    (E.Conflict, 409),
    (E.NotEnoughCorrespondences, 422),
    (E.BadInput, 422),
    (E.BadRobotData, 422),
    (E.BadVocabulary, 500),
    (E.Unavailable, 503),
    (E.StorageCorrupt, 500),
]
_BY_NAME = {cls.__name__: cls for cls, _ in STATUS}
#: What a client raises for an error status without a known class (a proxy's answer).
_BY_STATUS = {
    400: E.BadInput,
    401: E.Unauthorized,
    403: E.Forbidden,
    408: E.RequestTimeout,
    409: E.Conflict,
    413: E.PayloadTooLarge,
    415: E.UnsupportedEncoding,
    422: E.BadInput,
    502: E.Unavailable,
    503: E.Unavailable,
    504: E.Unavailable,
}


class ServiceError(E.FleetmapError):
    """A service answered with an error status that names no domain error."""

    def __init__(self, status: int, detail: str):
        super().__init__(f"HTTP {status}: {detail}")
        self.status = status


def status_of(exc: E.FleetmapError) -> int:
    """The HTTP status a domain error is answered with."""
    for cls, code in STATUS:
        if isinstance(exc, cls):
            return code
    return 400


def error_body(exc: E.FleetmapError) -> dict:
    return {"detail": str(exc), "error": type(exc).__name__}


def error_from(status: int, body: object, where: str = "") -> E.FleetmapError:
    """The exception a client raises for an error answer: the class the server named in
    `error` when it is one of ours, else by status, else ServiceError."""
    detail, name = body, None
    if isinstance(body, dict):
        detail, name = body.get("detail", body), body.get("error")
    detail = detail if isinstance(detail, str) else json.dumps(detail)[:2000]
    text = f"{where}: {detail}" if where else detail
    cls = _BY_NAME.get(name) or _BY_STATUS.get(status)
    return ServiceError(status, text) if cls is None else cls(text)


# --- POST /align: multipart/form-data ------------------------------------------------

#: The JSON field: {"pairs": [[i, j], ...], "views_a": [view...], "views_b": [...],
#: "method", "cloud", "colour"}; a view is {"stamp", "T_map_cam" 4x4, "intrinsics"}.
ALIGN_META = "meta"


def view_part(side: str, i: int, kind: str) -> str:
    """The file part of robot `side` ("a" or "b")'s view i: kind "rgb" (PNG or JPEG
    colour) or "depth" (16-bit PNG)."""
    return f"{side}{i}_{kind}"
