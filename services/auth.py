"""Who may call: bearer tokens (the operator's, or a robot's for its own keyframes), checked
in constant time; an open deployment when none is configured."""

from __future__ import annotations

import hmac
import ipaddress
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import HTTPBearer

from fleetmap.errors import Forbidden, Unauthorized


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


def require_token(request: Request, _: object = Security(bearer)) -> str:
    """Dependency: the caller's identity with any valid token (or an open deployment)."""
    return check_access(request)


def require_operator(request: Request, _: object = Security(bearer)) -> str:
    """Dependency: the caller's identity, which must be the operator's (or open)."""
    return check_access(request, operator=True)


def require_robot_writer(robot_id: str, request: Request, _: object = Security(bearer)) -> str:
    """Dependency: who writes robot `robot_id`'s data: its own token or the operator's."""
    return check_access(request, robot=robot_id)


def identify(request: Request) -> str | None:
    """Dependency: the caller's identity, or None for an anonymous caller of a secured
    service (who may still learn that it is alive)."""
    try:
        return check_access(request)
    except (Unauthorized, Forbidden):
        return None


#: The caller's identity: "open", "operator" or "robot:<id>", as route parameters.
Caller = Annotated[str, Depends(require_token)]
Operator = Annotated[str, Depends(require_operator)]
RobotWriter = Annotated[str, Depends(require_robot_writer)]
MaybeCaller = Annotated[str | None, Depends(identify)]
