"""Issue 15's long-poll attack, measured: 40 concurrent `GET /overlaps?wait=20` against a
real `fleetmap serve place-db` process while its overlap worker has keyframes queued, and
/healthz's worst latency meanwhile (it stalled 18.6 s when each wait held a worker thread).

    .venv/bin/python bench/longpoll.py [--clients 40]

Keyframes: both HoloLens lounge robots (351), extracted on every core first.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetmap.dataset import read_recording  # noqa: E402
from fleetmap.extract import keyframe_indices  # noqa: E402
from fleetmap.extract_pool import extract_keyframes  # noqa: E402
from fleetmap.frame import encode  # noqa: E402
from tests.servers import Service  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "hololens_lounge"
OCTET = {"content-type": "application/octet-stream"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--clients", type=int, default=40)
    args = ap.parse_args()
    recs = [read_recording(DATA / "hl_a", "A"), read_recording(DATA / "hl_b", "B")]
    kf = {r.robot_id: keyframe_indices(r) for r in recs}
    frames = [(k.robot_id, encode(k.frame)) for k in extract_keyframes(recs, kf)]
    svc = Service("place-db", Path(tempfile.mkdtemp())).start()
    try:
        with httpx.Client(base_url=svc.url, timeout=60) as c:
            for rid, data in frames:
                c.post(f"/robots/{rid}/keyframes", content=data, headers=OCTET)
            pending = c.get("/stats").json()["pending"]
        answers: list[tuple[int, float]] = []

        def poll() -> None:
            t = time.perf_counter()
            params = {"robot_a": "A", "robot_b": "B", "wait": 20}
            r = httpx.get(svc.url + "/overlaps", params=params, timeout=60)
            answers.append((r.status_code, time.perf_counter() - t))

        threads = [threading.Thread(target=poll) for _ in range(args.clients)]
        for th in threads:
            th.start()
        worst = 0.0
        while any(th.is_alive() for th in threads):
            t = time.perf_counter()
            httpx.get(svc.url + "/healthz", timeout=30)
            worst = max(worst, time.perf_counter() - t)
            time.sleep(0.1)
        print(
            f"{args.clients} long polls with {pending} keyframes queued: statuses "
            f"{sorted({s for s, _ in answers})}, longest {max(x for _, x in answers):.1f} s; "
            f"/healthz worst {worst:.2f} s"
        )
    finally:
        svc.stop()


if __name__ == "__main__":
    main()
