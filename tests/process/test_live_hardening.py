"""The place database's HTTP surface under the live map's load (issue 26.8, 26.10, 26.11):
/healthz answers while map requests wait, security headers on every response, a client
hanging up mid-body logs one INFO line. Real uvicorn servers on loopback."""

from __future__ import annotations

import base64
import contextlib
import hashlib
import logging
import re
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest
import uvicorn
from fastapi.testclient import TestClient

from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.main import create_app
from tests.servers import Service, free_port


@contextlib.contextmanager
def serving(app):
    """The app on a real uvicorn server in this process (its state reachable): (URL, the
    server)."""
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}", server
    finally:
        server.should_exit = True
        thread.join(30)


def test_healthz_answers_while_sixty_map_requests_wait(tmp_path):
    """Issue 26.8: 60 overview and cloud requests that cannot progress (the renderer held)
    used to take every worker thread of the server; /healthz then waited with them."""
    app = create_app(Settings(data_dir=tmp_path))
    with serving(app) as (url, server):
        paths = ["/map/overview.png", "/map/cloud.ply"] * 30
        with ThreadPoolExecutor(60) as pool:
            with app.state.renderer._lock:
                waiting = [pool.submit(httpx.get, url + p, timeout=300) for p in paths]
                end = time.monotonic() + 60  # the 60 requests in the app (was: a 3 s sleep)
                while len(server.server_state.tasks) < 60:
                    assert time.monotonic() < end, len(server.server_state.tasks)
                    time.sleep(0.02)
                health = httpx.get(url + "/healthz", timeout=20)
                assert health.status_code == 200 and health.json()["status"] == "ok"
                assert httpx.get(url + "/robots", timeout=20).status_code == 200
            assert [f.result().status_code for f in waiting] == [200] * 60  # no 5xx after


def test_every_response_carries_the_security_headers(tmp_path):
    """Issue 26.10: CSP (scripts, frame ancestors), nosniff, no caching of data; the page's
    token leaves the address bar once read."""
    with TestClient(create_app(Settings(data_dir=tmp_path))) as client:
        for path in ("/", "/map", "/robots", "/healthz", "/keyframes/1/view", "/nope"):
            r = client.get(path)
            assert r.headers["x-content-type-options"] == "nosniff", path
            assert r.headers["x-frame-options"] == "DENY", path
            assert "frame-ancestors 'none'" in r.headers["content-security-policy"], path
            assert r.headers["cache-control"] == "no-store", path
        page = client.get("/")
        script = re.search(r"<script>(.*?)</script>", page.text, re.S).group(1)
        digest = base64.b64encode(hashlib.sha256(script.encode()).digest()).decode()
        csp = page.headers["content-security-policy"]
        assert f"'sha256-{digest}'" in csp and "default-src 'none'" in csp
        assert "unsafe-inline" not in csp.split("script-src")[1].split(";")[0]
        assert "history.replaceState" in script


def test_head_is_answered_as_get_without_a_body(tmp_path, caplog):
    """Session 58's round: uptime checkers probe with HEAD, which every GET route answered
    405 (with a body). Now the GET's status and headers, no body; no GET: still 405."""
    from fleetmap.services.aligner.main import create_app as create_aligner

    with TestClient(create_app(Settings(data_dir=tmp_path))) as client:
        for path in ("/", "/healthz", "/robots", "/map", "/map/overview.png"):
            got, head = client.get(path), client.head(path)
            assert (head.status_code, head.content) == (200, b""), path
            assert head.headers["content-type"] == got.headers["content-type"], path
            assert head.headers["x-content-type-options"] == "nosniff", path
        assert client.head("/nope").status_code == 404
        with caplog.at_level(logging.INFO, logger="fleetmap.http"):
            client.head("/healthz")
        assert any(" HEAD /healthz 200 " in r.getMessage() for r in caplog.records)
    with TestClient(create_aligner()) as client:
        assert client.head("/healthz").status_code == 200
        assert client.head("/align").status_code == 405  # POST only


def test_a_client_hanging_up_mid_body_logs_one_info_line(tmp_path):
    """Issue 26.11: 60 such clients wrote 340 KB of ERROR tracebacks."""
    svc = Service("place-db", tmp_path).start()
    try:
        for _ in range(5):
            with socket.create_connection(("127.0.0.1", svc.port)) as sock:
                sock.sendall(
                    b"POST /robots/alpha/keyframes HTTP/1.1\r\nHost: x\r\n"
                    b"Content-Type: application/octet-stream\r\nContent-Length: 100000\r\n\r\n"
                    + bytes(1000)
                )
        deadline = time.monotonic() + 20
        while svc.read_log().count("disconnected") < 5 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert httpx.get(svc.url + "/healthz").status_code == 200
    finally:
        svc.stop()
    log = svc.read_log()
    assert "Traceback" not in log and "ERROR" not in log, log[-3000:]
    assert log.count("client disconnected mid-request") == 5, log[-3000:]


def test_an_interrupted_stream_posts_nothing_more(tmp_path, tum_rpy):
    """Ctrl-C on `fleetmap stream --speed 0.1` of a robot with more keyframes than its
    queue holds (64) interrupted the feeding, then waited for the posters to post every
    keyframe queued, about one a second at that speed (an outside tester's review: 8 s to
    exit): now they stop with it."""
    import os
    import signal
    import subprocess
    import sys

    robot = tum_rpy  # 241 frames, over 64 keyframes
    app = create_app(Settings(data_dir=tmp_path))
    with serving(app) as (url, _):

        def posted() -> int:
            robots = httpx.get(url + "/robots", timeout=20).json()["robots"]
            return sum(r["keyframes"] for r in robots)

        # Ctrl-C's handler as a terminal gives it: a suite run in the background of a shell
        # without job control (`cmd &`) ignores SIGINT, and its children inherit that; the
        # stream then never saw the signal (session 60's clean clones, launched so: 60 s)
        run = "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler)"
        run += "; from fleetmap.services.cli import main; sys.exit(main(sys.argv[1:]))"
        cmd = [sys.executable, "-c", run, "-q", "stream", str(robot)]
        log = tmp_path / "stream.err"  # a file: the extraction's processes hold no pipe open
        with open(log, "w") as err_file:
            proc = subprocess.Popen(
                [*cmd, "--place-db", url, "--speed", "0.1"],
                stderr=err_file,
                env={**os.environ, "FLEETMAP_PLACE_DB_URL": url, "PYTHONFAULTHANDLER": "1"},
            )
        try:
            end = time.monotonic() + 120
            while posted() < 2:
                assert proc.poll() is None and time.monotonic() < end, log.read_text()
                time.sleep(0.1)
            before = posted()
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:  # its threads' stacks, for the next look
                proc.send_signal(signal.SIGABRT)
                proc.wait(timeout=30)
                pytest.fail(f"no exit 60 s after SIGINT:\n{log.read_text()[-8000:]}")
        finally:
            proc.kill()
        err = log.read_text()
        assert proc.returncode == 130 and "interrupted" in err, err
        assert posted() <= before + 1  # at most the one in flight
