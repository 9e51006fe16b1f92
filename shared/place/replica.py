"""What a replica over a shared store (PostgreSQL) adds to `PlaceDB`: its in-memory index
follows what every replica commits (`Follower`), and overlap detection takes its work from
the store's queue (`ClaimWorker`)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from fleetmap.errors import Unavailable
from fleetmap.place.index import PlaceIndex
from fleetmap.place.store import SharedStore

log = logging.getLogger(__name__)


class Follower:
    """Keeps the index equal to the store: keyframes by id (ids follow commit order),
    robots deleted by any replica, the newest codebook. `catch_up` runs every `interval_s`
    in a thread and after this replica's own commits, so a query on any replica sees every
    committed keyframe within about `interval_s`."""

    def __init__(self, store: SharedStore, index: PlaceIndex, interval_s: float = 0.1):
        self.store, self.index, self.interval_s = store, index, interval_s
        self._lock = threading.Lock()
        self._stop = threading.Event()
        deletions = store.deletions_after(0)
        self._deletion = deletions[-1][0] if deletions else 0
        self._codebook = store.codebook_version()
        self._thread: threading.Thread | None = None
        self._down = False

    def catch_up(self, keyframes_only: bool = False) -> int:
        """Bring the index up to date (only the keyframes: after this replica's own
        commit, for read-your-writes at one round trip); returns the keyframes added."""
        n = 0
        with self._lock:
            for rows in self.store.index_rows(after=self.index.last_id):
                self.index.add_many(
                    rows.ids, rows.robots, rows.stamps, rows.gists, rows.bow_ids, rows.bow_counts
                )
                n += len(rows.ids)
            if keyframes_only:
                return n
            for did, robot in self.store.deletions_after(self._deletion):
                self.index.remove_robot(robot)
                self.store.forget_robot(robot)
                self._deletion = did
            version = self.store.codebook_version()
            if version != self._codebook:
                self.index.set_codebook(self.store.codebook())
                self._codebook = version
        return n

    def codebook_saved(self) -> None:
        """This replica retrained and saved the codebook its index already uses."""
        with self._lock:
            self._codebook = self.store.codebook_version()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="index-follower", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.catch_up()
                if self._down:
                    log.warning("the shared store answers again: index following resumed")
                self._down = False
            except Unavailable as exc:
                if not self._down:
                    log.error("index follower: %s (retrying)", exc)
                self._down = True
            except Exception:
                log.exception("index follower failed (retrying)")

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)


class ClaimWorker:
    """Overlap detection from the store's queue: claim the oldest unprocessed keyframe no
    other replica holds, detect, record, commit. Same face as `OverlapWorker`."""

    def __init__(
        self, store: SharedStore, compute: Callable[[int], tuple | None], idle_s: float = 0.05
    ):
        self.store, self.compute, self.idle_s = store, compute, idle_s
        self.failures = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def parked(self) -> dict[int, str]:
        return self.store.parked()

    def put(self, kf_id: int) -> None:
        """Nothing to do: every committed keyframe is in the store's queue already."""

    def pending(self) -> int:
        return self.store.pending_count()

    def wait_idle(self, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while self.pending():
            if time.monotonic() > end:
                return False
            time.sleep(0.05)
        return True

    def _one(self) -> int | None:
        try:
            return self.store.claim(self.compute)
        except Unavailable:
            raise
        except Exception:
            log.exception("overlap detection failed (the keyframe goes back to the queue)")
            self.failures += 1
            return -1

    def process_pending(self) -> None:
        """Work the queue down now, in this thread."""
        while self._one() is not None:
            pass

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="overlap-claimer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                if self._one() is None:
                    self._stop.wait(self.idle_s)
            except Unavailable as exc:
                log.error("overlap worker: %s (retrying)", exc)
                self._stop.wait(1.0)

    def stop(self, timeout: float) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
