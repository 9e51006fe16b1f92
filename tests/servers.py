"""Real service processes for end-to-end tests: `fleetmap serve` on a free loopback port."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
#: The merge worker's timing for tests: overlaps looked at 4 times a second (not once),
#: robots quiet after 2 s without a keyframe (not 5 s). What is asserted is unchanged.
LIVE_FAST = {"FLEETMAP_PLACE_DB_LIVE__POLL_S": "0.25", "FLEETMAP_PLACE_DB_LIVE__SETTLE_S": "2"}

#: The tests' own requests to the services they start. `httpx.get` builds a new client, and
#: with it a TLS context (some 30 ms of CPU loading the CA bundle, even for http://), on
#: every call: the health and map polls spent tens of seconds of CPU on it, taken from the
#: services under test. This client is built once; it keeps no idle connection, so every
#: request opens its own, as `httpx.get` did; the same default timeout (5 s).
http = httpx.Client(limits=httpx.Limits(max_connections=None, max_keepalive_connections=0))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Service:
    def __init__(
        self,
        kind: str,
        data_dir: Path | None = None,
        env: dict | None = None,
        args: list[str] | None = None,
    ):
        self.kind, self.data_dir, self.env = kind, data_dir, env or {}
        self.args = list(args or [])
        self.proc: subprocess.Popen | None = None
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"

    def start(self, timeout: float = 60.0) -> Service:
        cmd = [
            sys.executable,
            "-m",
            "fleetmap.services.cli",
            "-v",
            "serve",
            self.kind,
            "--port",
            str(self.port),
        ]
        if self.data_dir is not None:
            cmd += ["--data-dir", str(self.data_dir)]
        cmd += self.args
        # logs to a file, not a pipe: an unread pipe fills up and blocks the server
        self.log = tempfile.NamedTemporaryFile(
            prefix=f"fleetmap-{self.kind}-", suffix=".log", delete=False
        )
        self.proc = subprocess.Popen(
            cmd,
            cwd=ROOT,
            env={**os.environ, **self.env},
            stdout=subprocess.DEVNULL,
            stderr=self.log,
        )
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"{self.kind} exited: {self.read_log()}")
            with contextlib.suppress(httpx.TransportError):
                if http.get(self.url + "/healthz", timeout=1.0).status_code == 200:
                    return self
            time.sleep(0.1)
        raise RuntimeError(f"{self.kind} did not start within {timeout} s")

    def read_log(self) -> str:
        return Path(self.log.name).read_text(errors="replace")

    def kill(self) -> None:
        """SIGKILL: no chance to flush or clean up."""
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.kill()


@contextlib.contextmanager
def running(
    kind: str, data_dir: Path | None = None, url_env: str | None = None, env: dict | None = None
):
    """A service URL: from the environment variable `url_env` if set (e.g. against
    `docker compose up`), else a fresh process on a free port (with `env` added to its
    environment), stopped afterwards."""
    if url_env and os.environ.get(url_env):
        yield os.environ[url_env]
        return
    svc = Service(kind, data_dir, env=env).start()
    try:
        yield svc.url
    finally:
        svc.stop()
