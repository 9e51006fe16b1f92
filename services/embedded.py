"""The services started by the CLI itself when no URL is given: the place database as a
child process (its overlap worker gets a core and an interpreter lock of its own), the
aligner in a thread of this process; both on free loopback ports, stopped at the end."""

from __future__ import annotations

import contextlib
import importlib
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from fleetmap.client import AlignerClient, PlaceDBClient
from fleetmap.errors import Unavailable


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def embedded_service(kind: str, data_dir: Path | None = None):
    """A service on a free loopback port in a background thread; yields its URL."""
    import uvicorn

    if kind == "place-db":
        from fleetmap.services.place_db.config import Settings
        from fleetmap.services.place_db.main import create_app

        app = create_app(Settings(data_dir=data_dir) if data_dir else Settings(), announce=False)
    else:
        from fleetmap.services.aligner.main import create_app as create_aligner

        app = create_aligner(announce=False)  # on loopback, for this command only
    port = _free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, name=f"embedded-{kind}", daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{port}"
    client = PlaceDBClient(url)
    try:
        client.wait_ready(60)
        yield url
    finally:
        client.close()
        server.should_exit = True
        thread.join(30)


@contextlib.contextmanager
def embedded_process(kind: str, data_dir: Path | None = None):
    """A service as a child process on a free loopback port; yields its URL. The place
    database runs so: its overlap worker then has a core (and an interpreter lock) of its
    own while this process posts keyframes."""
    port = _free_port()
    cmd = [sys.executable, "-m", "fleetmap.services.cli", "serve", kind, "--port", str(port)]
    if data_dir is not None:
        cmd += ["--data-dir", str(data_dir)]
    url = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryFile() as errors:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=errors)
        client = PlaceDBClient(url)
        try:
            try:
                client.wait_ready(60, alive=lambda: proc.poll() is None, poll_s=0.05)
            except Unavailable:
                if proc.poll() is None:
                    raise
                errors.seek(0)
                tail = errors.read().decode(errors="replace").strip().splitlines()[-1:]
                raise Unavailable(f"embedded {kind} exited ({proc.returncode}): {tail}") from None
            yield url
        finally:
            client.close()
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def check_reachable(place_db: str | None, aligner: str | None, token: str | None) -> None:
    """Given service URLs answer /healthz (one try, a few seconds), or Unavailable."""
    for url, client in ((place_db, PlaceDBClient), (aligner, AlignerClient)):
        if url is not None:
            with client(url, timeout=10, token=token) as c:
                c.health()


def start_services(stack: contextlib.ExitStack, place_db: str | None, aligner: str | None):
    """The given service URLs, or both services embedded on free loopback ports."""
    if place_db is None:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="fleetmap-")))
        place_db = stack.enter_context(embedded_process("place-db", tmp))
    if aligner is None:
        aligner = stack.enter_context(embedded_service("aligner"))
        # Open3D and the MLP's torch (1.6 s to import) load while the robots are ingested
        threading.Thread(target=_warm_up, args=("open3d", "torch"), daemon=True).start()
    return place_db, aligner


def _warm_up(*modules: str) -> None:
    for name in modules:
        importlib.import_module(name)
