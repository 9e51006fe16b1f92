"""The services started by the CLI itself when no URL is given: both in threads of this
process (`embedded_service`), on free loopback ports, stopped at the end. A child process
for the place database cost a second interpreter's start and imports, 2.5-8 s before the
first keyframe could be posted, and bought an interpreter lock of its own: that shows only
in the link registration, which now shares the lock with the aligner and the outputs
(three HoloLens robots: links 13 -> 21 s, the whole merge 177 -> 114 s; issue 23).

Both come up in the background: `start_services` returns their URLs at once, and the job
waits for one (`Services.ready`) only when it first needs it, so their start-up overlaps
the keyframe extraction instead of holding it up (the aligner is not needed before the
overlaps are known)."""

from __future__ import annotations

import contextlib
import importlib
import socket
import tempfile
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from fleetmap.client import AlignerClient, PlaceDBClient
from fleetmap.errors import Unavailable
from fleetmap.services.settings import unreadable


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Services:
    """The service URLs of a job; `ready(kind)` blocks until that one answers /healthz
    (at once for a service given by URL, checked before any long work)."""

    place_db: str
    aligner: str
    waits: dict[str, Callable[[], None]] = field(default_factory=dict)

    def ready(self, kind: str) -> str:
        """Wait for "place-db" or "aligner" to be up; its URL."""
        wait = self.waits.pop(kind, None)
        if wait is not None:
            wait()
        return self.place_db if kind == "place-db" else self.aligner


def _app(kind: str, data_dir: Path | None, vocabulary: Path | None = None):
    if kind == "place-db":
        from fleetmap.extract_pool import default_workers
        from fleetmap.services.place_db.config import Settings
        from fleetmap.services.place_db.main import create_app

        # the job asks for overlaps once every keyframe is in (`defer_overlaps`), then
        # detects them on every core (`OverlapWorker`)
        batch = {"defer_overlaps": True, "overlap_threads": min(default_workers(), 64)}
        if vocabulary is not None:  # the job's --vocab: its keyframes' words are of it
            batch["vocabulary"] = Path(vocabulary)
        settings = Settings(data_dir=data_dir, **batch) if data_dir else Settings()
        return create_app(settings, announce=False)
    from fleetmap.services.aligner.main import create_app as create_aligner

    return create_aligner(announce=False)  # on loopback, for this command only


@contextlib.contextmanager
def embedded_service(
    kind: str,
    data_dir: Path | None = None,
    after: Callable | None = None,
    vocabulary: Path | None = None,
):
    """A service on a free loopback port in a background thread, which also imports and
    builds the app (once `after()` returned, if given; a place database with `vocabulary`,
    None: the shipped one); yields (URL, wait until ready)."""
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    built, box = threading.Event(), {}

    def run() -> None:
        try:
            if after is not None:
                after()
            import uvicorn

            app = _app(kind, data_dir, vocabulary)
            # the job's own client on loopback: idle keep-alive connections stay open (60 s,
            # not uvicorn's 5), so that a connection the client reuses, on a machine whose
            # cores are busy, is never closed under a request (a drift merge once failed
            # with "Connection reset by peer" posting a keyframe at load 14)
            config = uvicorn.Config(
                app, host="127.0.0.1", port=port, log_level="warning", timeout_keep_alive=60
            )
            box["server"] = uvicorn.Server(config)
        except Exception as exc:  # raised by wait(), in the job's thread
            box["error"] = exc
            return
        finally:
            built.set()
        box["server"].run()

    thread = threading.Thread(target=run, name=f"embedded-{kind}", daemon=True)
    thread.start()
    client = PlaceDBClient(url)

    def wait() -> None:
        try:
            client.wait_ready(60, alive=thread.is_alive, poll_s=0.05)
        except Unavailable:
            if "error" in box:
                why = unreadable(box["error"])  # an unreadable setting: one line naming it
                if why is not None:
                    raise why from None
                raise Unavailable(f"embedded {kind} failed: {box['error']}") from box["error"]
            raise

    try:
        yield url, wait
    finally:
        client.close()
        built.wait(60)
        if "server" in box:
            box["server"].should_exit = True
        thread.join(30)


def check_reachable(place_db: str | None, aligner: str | None, token: str | None) -> None:
    """Given service URLs answer /healthz (one try, a few seconds), or Unavailable."""
    for url, client in ((place_db, PlaceDBClient), (aligner, AlignerClient)):
        if url is not None:
            with client(url, timeout=10, token=token) as c:
                c.health()


def start_services(
    stack: contextlib.ExitStack,
    place_db: str | None,
    aligner: str | None,
    vocabulary: Path | None = None,
):
    """`Services`: the given service URLs, or both services starting on free loopback
    ports in the background (wait with `Services.ready`); the place database started here
    with `vocabulary` (the job's `--vocab`; None: the shipped one)."""
    waits, first = {}, None
    if place_db is None:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="fleetmap-")))
        place_db, first = stack.enter_context(embedded_service("place-db", tmp, None, vocabulary))
        waits["place-db"] = lambda: (first(), default_kernel_threads())
    if aligner is None:  # its imports (Open3D) after the place database's: needed later
        aligner, waits["aligner"] = stack.enter_context(embedded_service("aligner", after=first))
    return Services(place_db, aligner, waits)


def default_kernel_threads() -> None:
    """OpenCV's and the BLAS and OpenMP libraries' threads back to one per core: the place
    database's start-up makes them one per process (`single_threaded_kernels`: its queries
    are single vectors), which would slow the aligner's matching beside it in this one."""
    import cv2
    from threadpoolctl import threadpool_limits

    from fleetmap.extract_pool import default_workers

    cv2.setNumThreads(-1)
    threadpool_limits(default_workers())


def warm_up(*modules: str) -> threading.Thread:
    """Import `modules` in a background thread (where a core would otherwise wait)."""
    thread = threading.Thread(target=_import, args=modules, name="warm-up", daemon=True)
    thread.start()
    return thread


def _import(*modules: str) -> None:
    for name in modules:
        importlib.import_module(name)
