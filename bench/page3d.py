"""The operator page's 3D view against a running place database: the size of each robot's
binary cloud (GET /map/robots/R/cloud.bin at the default voxel) and the time from opening
the page to the first 3D picture (the view sets `data-first3d-ms`, from the page's
navigation start, once it has drawn every placed robot), in Debian's headless chromium with
software WebGL (SwiftShader: slower than a desktop's GPU), a few times.

    .venv/bin/python bench/page3d.py [--case hololens3] [--seed 0] [--runs 3]
    .venv/bin/python bench/page3d.py --place-db http://127.0.0.1:8100 [--token T]

Without --place-db, bench/live_stream.py's case (hololens3: three robots cut from the
HoloLens lounge, 380-odd keyframes) is streamed into real services first.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np


class Chromium:
    """Headless chromium driven over the DevTools protocol on a pipe (fds 3 and 4, no
    websocket library needed): real time, unlike a virtual-time budget, which stops the
    clock while fetches are pending."""

    def __init__(self, size: str = "1200,900"):
        self.profile = tempfile.TemporaryDirectory()
        to_chrome, self._w = os.pipe()
        self._r, from_chrome = os.pipe()
        # chromium reads fd 3 and writes fd 4: moved there in the child only
        high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_chrome, from_chrome)]

        def onto_3_and_4() -> None:
            os.dup2(high[0], 3)
            os.dup2(high[1], 4)

        self.proc = subprocess.Popen(
            [
                shutil.which("chromium"),
                "--headless",
                "--no-sandbox",
                "--use-gl=swiftshader",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                f"--user-data-dir={self.profile.name}",
                f"--window-size={size}",
                "--remote-debugging-pipe",
            ],
            preexec_fn=onto_3_and_4,
            pass_fds=(3, 4),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for fd in (to_chrome, from_chrome, *high):
            os.close(fd)
        self._id, self._buf = 0, b""

    def call(self, method: str, session: str | None = None, **params) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        os.write(self._w, json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in self._buf:
                self._buf += os.read(self._r, 1 << 16)
            raw, self._buf = self._buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                return reply.get("result", {})

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(30)
        self.profile.cleanup()


def first_picture_ms(url: str, timeout_s: float = 60.0) -> tuple[int, int] | None:
    """The page's own times from navigation start to its first 3D picture and to three.js
    loaded (ms)."""
    chrome = Chromium()
    try:
        target = chrome.call("Target.createTarget", url="about:blank")["targetId"]
        session = chrome.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        chrome.call("Page.navigate", session, url=url)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            expr = "JSON.stringify(document.body?.dataset || {})"
            got = chrome.call("Runtime.evaluate", session, expression=expr)
            marks = json.loads(got.get("result", {}).get("value") or "{}")
            if marks.get("first3dMs"):
                return int(marks["first3dMs"]), int(marks["three3dMs"])
            time.sleep(0.05)
        return None
    finally:
        chrome.close()


def measure(url: str, token: str | None, runs: int) -> None:
    headers = {"authorization": f"Bearer {token}"} if token else {}
    m = httpx.get(url + "/map", headers=headers, timeout=60).json()
    kfs = sum(f["keyframes"] for f in m["fleet"])
    print(f"map version {m['version']}: {len(m['transforms'])} robots placed, {kfs} keyframes")
    for r in m["transforms"]:
        for attempt in ("first", "cached"):
            t = time.perf_counter()
            resp = httpx.get(f"{url}/map/robots/{r}/cloud.bin", headers=headers, timeout=600)
            dt = time.perf_counter() - t
            print(
                f"  {r}: {len(resp.content) / 1e6:.2f} MB, "
                f"{resp.headers['x-points']} points ({attempt}: {dt:.2f} s)"
            )
    page = f"{url}/#view=3d" + (f"&token={token}" if token else "")
    for _ in range(runs):
        first, three = first_picture_ms(page) or (None, None)
        print(f"  first 3D picture {first} ms after navigation start (three.js ready: {three})")


def streamed(case: str, seed: int, work: Path) -> tuple:
    """bench/live_stream.py's case streamed into real services, once every robot that
    should merge is placed and the worker is quiet: (aligner, place database)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from live_stream import FLEETMAP, prepare
    from real_pairs import DATA, cases

    from tests.servers import Service

    dirs, frames = prepare(cases(DATA)[case], work, np.random.default_rng(seed), False, DATA)
    aligner = Service("aligner").start()
    db = Service("place-db", work / "db", args=["--aligner", aligner.url]).start()
    subprocess.run([FLEETMAP, "-q", "stream", *dirs, "--place-db", db.url, "--speed", "0"])
    should = {r for r, T in frames.items() if T is not None}
    while True:
        m = httpx.get(db.url + "/map", timeout=60).json()
        w = m["worker"] or {}
        if should <= set(m["transforms"]) and w.get("quiet") and not w.get("aligning"):
            return aligner, db
        time.sleep(1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--place-db", help="a running place database (else: --case is streamed)")
    ap.add_argument("--case", default="hololens3", help="bench/live_stream.py's cases")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--token")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    if args.place_db:
        measure(args.place_db, args.token, args.runs)
        return
    with tempfile.TemporaryDirectory(prefix="fleetmap-page3d-") as tmp:
        aligner, db = streamed(args.case, args.seed, Path(tmp))
        try:
            measure(db.url, None, args.runs)
        finally:
            db.stop()
            aligner.stop()


if __name__ == "__main__":
    main()
