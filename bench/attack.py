"""Issue 15's memory attack on the aligner, measured: concurrent maximal /align requests
against a real `fleetmap serve aligner` process, its peak RSS and /healthz's latency.

    .venv/bin/python bench/attack.py [--clients 8] [--views 12] [--size 1280x1024]

Each request carries `views` views per robot of `size` colour and depth images (textured
noise, so features are found and the whole pipeline runs), just under the default pixel
budget (64 Mi pixels in flight) at the defaults; every view of A is paired with every view
of B. Also sent: a 2.6 MB-class PNG declaring 30000x30000 (must be a fast 413). Prints the
answers' statuses, the server's peak resident memory and /healthz's worst latency.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import cv2
import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetmap.camera import Intrinsics  # noqa: E402
from fleetmap.client import align_request  # noqa: E402
from fleetmap.correspondences import RGBDView  # noqa: E402
from tests.api.test_aligner_api import _png_declaring  # noqa: E402
from tests.servers import Service  # noqa: E402


def _views(n: int, w: int, h: int, seed: int) -> list[RGBDView]:
    rng = np.random.default_rng(seed)
    K = Intrinsics(fx=0.8 * w, fy=0.8 * w, cx=w / 2, cy=h / 2, depth_scale=1000, width=w, height=h)
    out = []
    for k in range(n):
        noise = rng.integers(0, 255, (h // 8, w // 8, 3), dtype=np.uint8)
        rgb = cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
        depth = np.full((h, w), 1500 + 10 * k, np.uint16)
        T = np.eye(4)
        T[0, 3] = 0.1 * k
        out.append(RGBDView(rgb, depth, K, T, float(k)))
    return out


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--size", default="1280x1024")
    args = ap.parse_args()
    w, h = map(int, args.size.split("x"))
    va, vb = _views(args.views, w, h, 0), _views(args.views, w, h, 1)
    body = align_request([(a, b) for a in va for b in vb])
    svc = Service("aligner").start()
    peak, worst, stop = [0.0], [0.0], threading.Event()

    def watch() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], _rss_mb(svc.proc.pid))
            t = time.perf_counter()
            try:
                httpx.get(svc.url + "/healthz", timeout=30)
            except httpx.TransportError:
                pass
            worst[0] = max(worst[0], time.perf_counter() - t)
            time.sleep(0.2)

    statuses: list[str] = []

    def client() -> None:
        t = time.perf_counter()
        try:
            r = httpx.post(svc.url + "/align", timeout=900, **body)
            statuses.append(f"{r.status_code} in {time.perf_counter() - t:.0f} s")
        except httpx.TransportError as exc:
            statuses.append(f"transport error {exc}")

    try:
        base = _rss_mb(svc.proc.pid)
        bomb = align_request([(va[0], vb[0])])
        bomb["files"]["a0_rgb"] = ("bomb.png", _png_declaring(30000, 30000))
        t = time.perf_counter()
        r = httpx.post(svc.url + "/align", timeout=60, **bomb)
        print(f"PNG declaring 30000x30000: {r.status_code} in {time.perf_counter() - t:.2f} s")
        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        threads = [threading.Thread(target=client) for _ in range(args.clients)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        stop.set()
        watcher.join()
        pixels = 2 * 2 * args.views * w * h
        print(
            f"{args.clients} concurrent /align of {args.views}+{args.views} views {w}x{h} "
            f"({pixels / 2**20:.0f} Mi pixels each): {sorted(statuses)}"
        )
        print(f"aligner RSS: {base:.0f} MB idle, {peak[0]:.0f} MB peak")
        print(f"/healthz worst latency during the attack: {worst[0]:.2f} s")
    finally:
        stop.set()
        svc.stop()


if __name__ == "__main__":
    main()
