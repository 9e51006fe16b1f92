"""The operator page's 3D view against a running place database: the size of each robot's
binary cloud (GET /map/robots/R/cloud.bin at the default voxel) and the time from opening
the page to the first 3D picture (the view sets `data-first3d-ms`, from the page's
navigation start, once it has drawn every placed robot), in Debian's headless chromium with
software WebGL (SwiftShader: slower than a desktop's GPU), a few times.

    .venv/bin/python bench/page3d.py --place-db http://127.0.0.1:8100 [--token T] [--runs 3]
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import shutil
import subprocess
import tempfile
import time

import httpx


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


def first_picture_ms(url: str, timeout_s: float = 60.0) -> int | None:
    """The page's own time from navigation start to its first 3D picture (ms)."""
    chrome = Chromium()
    try:
        target = chrome.call("Target.createTarget", url="about:blank")["targetId"]
        session = chrome.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        chrome.call("Page.navigate", session, url=url)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            got = chrome.call(
                "Runtime.evaluate", session, expression="document.body?.dataset.first3dMs || ''"
            )
            if got.get("result", {}).get("value"):
                return int(got["result"]["value"])
            time.sleep(0.05)
        return None
    finally:
        chrome.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--place-db", default="http://127.0.0.1:8100")
    ap.add_argument("--token")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    headers = {"authorization": f"Bearer {args.token}"} if args.token else {}
    m = httpx.get(args.place_db + "/map", headers=headers, timeout=60).json()
    kfs = sum(f["keyframes"] for f in m["fleet"])
    print(f"map version {m['version']}: {len(m['transforms'])} robots placed, {kfs} keyframes")
    for r in m["transforms"]:
        t = time.perf_counter()
        resp = httpx.get(f"{args.place_db}/map/robots/{r}/cloud.bin", headers=headers, timeout=600)
        dt = time.perf_counter() - t
        print(
            f"  {r}: {len(resp.content) / 1e6:.2f} MB, "
            f"{resp.headers['x-points']} points ({dt:.2f} s)"
        )
    url = f"{args.place_db}/#view=3d" + (f"&token={args.token}" if args.token else "")
    for _ in range(args.runs):
        print(f"  first 3D picture {first_picture_ms(url)} ms after navigation start")


if __name__ == "__main__":
    main()
