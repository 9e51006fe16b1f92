"""The overlap worker: a background thread that runs each new keyframe through the
cascade against the other robots' keyframes. One keyframe's failure blocks none of the
others: it is counted and parked with its reason, and stays unprocessed in storage, so the
next start tries it again."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

log = logging.getLogger(__name__)


class OverlapWorker:
    """A queue of keyframe ids and the threads (optional) that process them: one for a live
    fleet, where keyframes arrive one by one; more where a whole batch is queued at once
    (`PlaceDB`'s `defer_detection`), whose detections are independent of each other and
    spend most of their time in OpenCV's MAGSAC, which runs without the interpreter lock."""

    def __init__(self, process: Callable[[int], object], threads: int = 1):
        self._process = process
        self._n = max(1, int(threads))
        self._queue: queue.Queue[int | None] = queue.Queue()
        self._stopping = False
        self.failures = 0  # keyframes whose overlap detection raised
        self.parked: dict[int, str] = {}  # keyframe -> reason, the last 100
        self._threads: list[threading.Thread] = []

    def start(self) -> None:
        """Process queued keyframes in background threads from now on."""
        self._threads = [
            threading.Thread(target=self._run, name=f"overlap-worker-{k}", daemon=True)
            for k in range(self._n)
        ]
        for t in self._threads:
            t.start()

    def put(self, kf_id: int) -> None:
        self._queue.put(kf_id)

    def pending(self) -> int:
        """Keyframes still waiting for overlap detection."""
        return self._queue.unfinished_tasks

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every queued keyframe is processed; False on timeout."""
        end = time.monotonic() + timeout
        while self._queue.unfinished_tasks:
            if time.monotonic() > end:
                return False
            time.sleep(0.02)
        return True

    def _one(self, kf: int | None) -> None:
        try:
            # stopping: what is left stays unprocessed, re-queued at the next start
            if kf is not None and not self._stopping:
                self._process(kf)
        except Exception as exc:  # one keyframe's failure blocks none of the others
            self._park(kf, exc)
        finally:
            self._queue.task_done()

    def _run(self) -> None:
        while True:
            kf = self._queue.get()
            self._one(kf)
            if kf is None:
                return

    def _park(self, kf: int, exc: Exception) -> None:
        log.exception("overlap detection failed for keyframe %s", kf)
        self.failures += 1
        self.parked[kf] = f"{type(exc).__name__}: {exc}"[:300]
        while len(self.parked) > 100:
            self.parked.pop(next(iter(self.parked)))

    def process_pending(self) -> None:
        """Process the queued keyframes now, in this thread (without the background one)."""
        while True:
            try:
                kf = self._queue.get_nowait()
            except queue.Empty:
                return
            self._one(kf)

    def stop(self, timeout: float) -> None:
        """Let the threads finish the keyframes they are on, at most `timeout` seconds."""
        if self._threads:
            self._stopping = True
            end = time.monotonic() + timeout
            for _ in self._threads:
                self._queue.put(None)
            for t in self._threads:
                t.join(timeout=max(0.0, end - time.monotonic()))
