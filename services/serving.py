"""How a service process runs under uvicorn: JSON log lines (FLEETMAP_LOG_FORMAT=json) with
the request middleware's fields, and an HTTP protocol with a deadline for request headers."""

from __future__ import annotations

import json
import logging

log = logging.getLogger("fleetmap.http")

#: Seconds a client has to send a request's headers (`header_timeout_protocol`); the
#: services' `header_timeout_s` setting.
HEADER_TIMEOUT_S = 10.0


class JsonFormatter(logging.Formatter):
    """One JSON object per log line, with the request fields the middleware attaches."""

    FIELDS = ("request_id", "method", "path", "status", "ms")

    def format(self, record: logging.LogRecord) -> str:
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


def header_timeout_protocol(timeout_s: float = HEADER_TIMEOUT_S):
    """uvicorn's h11 protocol with a deadline for every request's headers: a client that
    opens connections and sends its headers a byte at a time (slowloris) is cut off after
    `timeout_s` (request bodies have their own, `fleetmap.services.body.BODY_CHUNK_TIMEOUT_S`)."""
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


def check_port(host: str, port: int) -> None:
    """Unavailable where the service could not listen on host:port (taken by another
    process, or not this machine's address): said before the start line, in one line."""
    import socket

    from fleetmap.errors import Unavailable

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        with socket.socket(infos[0][0], socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
            s.bind(infos[0][4])
    except OSError as exc:
        raise Unavailable(
            f"cannot listen on {host}:{port}: {exc.strerror or exc} (another service there? "
            "--port another)"
        ) from None
