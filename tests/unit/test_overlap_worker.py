"""The overlap worker's threads: a batch queued at once is shared between them, a failing
keyframe is parked without holding up the others, and `stop` ends every thread."""

from __future__ import annotations

import threading
import time

from fleetmap.place.worker import OverlapWorker


def test_two_threads_share_a_batch_park_a_failure_and_stop():
    done, threads = [], set()

    def process(kf: int) -> None:
        threads.add(threading.current_thread())
        time.sleep(0.01)  # as a detection waits in OpenCV, without the interpreter lock
        if kf == 7:
            raise ValueError("corrupt frame")
        done.append(kf)

    w = OverlapWorker(process, threads=2)
    for kf in range(20):
        w.put(kf)
    w.start()
    assert w.wait_idle(10.0)
    assert sorted(done) == [k for k in range(20) if k != 7]
    assert w.failures == 1 and "corrupt frame" in w.parked[7]
    assert len(threads) == 2 and all(t.name.startswith("overlap-worker-") for t in threads)
    w.stop(5.0)
    assert not any(t.is_alive() for t in threads)
