"""A bounded chaos run against real service processes (issue 15): robots ingest, an
operator queries and registers links, the aligner aligns, while the place database is
SIGKILLed and restarted at random moments (seeded). Afterwards every acknowledged keyframe
must be stored byte for byte and the last acknowledged link must be there."""

from __future__ import annotations

import random
import threading
import time

import httpx
import numpy as np
import pytest

from fleetmap.client import align_request
from tests.helpers import OCTET
from tests.servers import Service, http


@pytest.mark.slow
def test_chaos_loses_nothing_acknowledged(tmp_path, fleet_frames, tum_two_robots, aligner_url):
    rng = random.Random(7)
    db = Service("place-db", tmp_path / "db").start()
    acked: dict[int, bytes] = {}
    link = [None]
    statuses: list[int] = []
    lock, stop = threading.Lock(), threading.Event()
    robots = list(fleet_frames.items())[:4]
    pairs, _ = tum_two_robots

    def robot(name: str, datas: list[bytes]) -> None:
        for data in datas:
            if stop.is_set():
                return
            try:
                r = http.post(f"{db.url}/robots/{name}/keyframes", content=data, headers=OCTET)
            except httpx.TransportError:
                time.sleep(0.2)  # killed mid-request: not acknowledged, try the next
                continue
            statuses.append(r.status_code)
            if r.status_code in (200, 201):
                with lock:
                    acked[r.json()["id"]] = data

    def operator() -> None:
        k = 0
        while not stop.is_set():
            k += 1
            try:
                q = http.post(f"{db.url}/query", content=robots[0][1][k % 20], headers=OCTET)
                statuses.append(q.status_code)
                T = np.eye(4)
                T[0, 3] = k
                r = http.put(
                    f"{db.url}/links/{robots[0][0]}/{robots[1][0]}",
                    json={"transform": T.tolist()},
                    timeout=60,
                )
                statuses.append(r.status_code)
                if r.status_code == 200:
                    link[0] = k
                a = http.post(f"{aligner_url}/align", timeout=120, **align_request(pairs))
                statuses.append(a.status_code)
            except httpx.TransportError:
                time.sleep(0.2)

    threads = [threading.Thread(target=robot, args=r) for r in robots]
    threads.append(threading.Thread(target=operator))
    for t in threads:
        t.start()
    try:
        # three kills at least, however slowly a loaded machine restarts the database; more
        # while the robots still ingest, for up to 25 s
        deadline, kills = time.monotonic() + 25, 0
        while kills < 3 or (
            time.monotonic() < deadline and any(t.is_alive() for t in threads[:-1])
        ):
            time.sleep(rng.uniform(0.5, 3.0))
            db.kill()
            kills += 1
            time.sleep(rng.uniform(0.0, 0.5))
            db.start()
    finally:
        stop.set()
        for t in threads:
            t.join(60)
    try:
        assert kills >= 3 and acked and max(statuses) < 500, (kills, sorted(set(statuses)))
        with httpx.Client(base_url=db.url, timeout=60) as c:
            for kf_id, data in acked.items():
                assert c.get(f"/keyframes/{kf_id}/frame").content == data
            links = c.get("/links").json()
            if link[0] is not None:  # the last acknowledged, or one sent after it
                assert links and abs(links[0]["transform"][0][3]) >= link[0]
        assert "Traceback" not in db.read_log()
    finally:
        db.stop()
