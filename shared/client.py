"""Python clients of the two services (httpx), used by the CLI and the tests."""

from __future__ import annotations

import logging
import time

import httpx

from fleetmap.errors import BadInput, FleetmapError, NotSolved, Unavailable
from fleetmap.frame import Frame, encode
from fleetmap.wire import ALIGN_META, ServiceError, error_from, view_part

OCTET = {"content-type": "application/octet-stream"}
log = logging.getLogger(__name__)


def _raise_for(resp: httpx.Response) -> httpx.Response:
    if resp.status_code < 400:
        return resp
    try:
        body = resp.json()
    except ValueError:
        body = resp.text
    raise error_from(resp.status_code, body, resp.request.url.path)


class _Client:
    """`url` may list several replicas of one service, comma-separated
    ("http://a:8100,http://b:8100"): a request that cannot connect, or gets a 503, moves
    on to the next one at once, and waits only once every replica has been tried."""

    def __init__(self, url: str, timeout: float = 60.0, token: str | None = None):
        headers = {"authorization": f"Bearer {token}"} if token else {}
        self.urls = [u.strip().rstrip("/") for u in url.split(",") if u.strip()]
        if not self.urls:
            raise BadInput(f"No service URL in {url!r}")
        # idle connections dropped well before uvicorn closes them (5 s): one reused as the
        # server closed it reset the robot's POST under load ("Connection reset by peer")
        limits = httpx.Limits(
            max_connections=100, max_keepalive_connections=20, keepalive_expiry=2.0
        )
        self._clients = [
            httpx.Client(base_url=u, timeout=timeout, headers=headers, limits=limits)
            for u in self.urls
        ]
        self._current = 0

    @property
    def url(self) -> str:
        return self.urls[self._current]

    @property
    def http(self) -> httpx.Client:
        return self._clients[self._current]

    #: Waits before the retries of a request that could not connect or got a 503.
    RETRY_WAITS_S = (0.5, 1.5)

    def _call(self, method: str, path: str, retry: bool = True, **kw) -> httpx.Response:
        """One request, retried after a refused connection (nothing was sent) or a 503
        (the service asked for it, `Retry-After` honoured up to 10 s), on the next replica
        first; other failures are raised at once, so a request is never sent twice after
        it reached the service."""
        waits = list(self.RETRY_WAITS_S) if retry else []
        tries = len(self.urls) * (len(waits) + 1)
        for attempt in range(1, tries + 1):
            last = attempt == tries
            try:
                resp = self.http.request(method, path, **kw)
            except httpx.ConnectError as exc:
                if last:
                    raise Unavailable(f"Cannot reach {self.url}{path}: {exc}") from exc
                self._next(waits, "")
                continue
            except httpx.TransportError as exc:
                raise Unavailable(f"Cannot reach {self.url}{path}: {exc}") from exc
            if resp.status_code == 503 and not last:
                self._next(waits, resp.headers.get("retry-after", ""))
                continue
            return _raise_for(resp)
        raise AssertionError("unreachable")

    def _next(self, waits: list[float], retry_after: str) -> None:
        """Move to the next replica; after a full round, wait (Retry-After up to 10 s)."""
        self._current = (self._current + 1) % len(self.urls)
        if self._current == 0 or len(self.urls) == 1:
            wait = waits.pop(0) if waits else 0.0
            time.sleep(min(float(retry_after), 10.0) if retry_after.isdigit() else wait)

    def health(self, retry: bool = True) -> dict:
        return self._call("GET", "/healthz", retry=retry).json()

    def config(self) -> dict:
        """The service's parameters in force (`GET /config`: its settings, no secrets)."""
        return self._call("GET", "/config").json()

    def wait_ready(self, timeout: float = 30.0, alive=None, poll_s: float = 0.1) -> None:
        """Until /healthz answers; Unavailable after `timeout`, or at once when `alive()`
        (e.g. the service's process still running) turns false."""
        end = time.monotonic() + timeout
        while True:
            if alive is not None and not alive():
                raise Unavailable(f"{self.url} went away before it was ready")
            try:
                self.health(retry=False)
                return
            except (Unavailable, ServiceError):
                if time.monotonic() > end:
                    raise Unavailable(f"{self.url} not ready after {timeout:.0f} s") from None
                time.sleep(poll_s)

    def close(self) -> None:
        for c in self._clients:
            c.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class PlaceDBClient(_Client):
    """Client of the place database service."""

    def add_keyframe(
        self, frame: Frame | bytes, robot_id: str | None = None, view: dict | None = None
    ) -> dict:
        """POST one keyframe; `view` ({"rgb": JPEG, "depth": 16-bit PNG} bytes, from
        `fleetmap.view.encode_view`) is stored with it for the live map's aligner."""
        data = frame if isinstance(frame, bytes) else encode(frame)
        rid = robot_id or frame.robot_id
        if view is None:
            kw = {"content": data, "headers": OCTET}
        else:
            files = {"frame": ("frame.bin", data, "application/octet-stream")}
            files |= {k: (k, view[k], "application/octet-stream") for k in ("rgb", "depth")}
            kw = {"files": files}
        return self._call("POST", f"/robots/{rid}/keyframes", **kw).json()

    def live_map(self) -> dict:
        """The live fleet map (`GET /map`)."""
        return self._call("GET", "/map").json()

    def map_file(self, name: str, **params) -> bytes:
        """cloud.ply (params: voxel) or overview.png of the live map."""
        return self._call("GET", f"/map/{name}", params=params, timeout=600).content

    def map_pose_graph(self) -> str | None:
        """The live map's keyframe graph as g2o text (`GET /map/pose_graph.g2o`); None
        while none is solved on the current placement."""
        try:
            return self._call("GET", "/map/pose_graph.g2o", timeout=600).text
        except NotSolved:
            return None

    def map_trajectories(self) -> dict:
        return self._call("GET", "/map/trajectories", timeout=600).json()

    def robots(self) -> list[dict]:
        return self._call("GET", "/robots").json()["robots"]

    def query(self, frame: Frame, **params) -> dict:
        params = {k: v for k, v in params.items() if v is not None}
        return self._call(
            "POST", "/query", content=encode(frame), headers=OCTET, params=params
        ).json()

    def overlaps(
        self, robot_a: str, robot_b: str, wait: float = 0.0, source: str = "all"
    ) -> list[dict]:
        return self._call(
            "GET",
            "/overlaps",
            params={"robot_a": robot_a, "robot_b": robot_b, "wait": wait, "source": source},
            timeout=wait + 60,
        ).json()["overlaps"]

    def put_link(self, robot_a: str, robot_b: str, T_a_b) -> int:
        """Register a gated map alignment; returns the link overlaps recorded."""
        body = {"transform": [[float(v) for v in row] for row in T_a_b]}
        r = self._call("PUT", f"/links/{robot_a}/{robot_b}", json=body, timeout=600)
        return r.json()["link_overlaps"]

    def links(self) -> list[dict]:
        return self._call("GET", "/links").json()

    def overlap_graph(self, wait: float = 0.0) -> list[dict]:
        return self._call("GET", "/overlaps", params={"wait": wait}, timeout=wait + 60).json()[
            "graph"
        ]

    def frame(self, kf_id: int) -> bytes:
        return self._call("GET", f"/keyframes/{kf_id}/frame").content

    def vocabulary(self) -> dict:
        return self._call("GET", "/vocabulary").json()

    def delete_robot(self, robot_id: str) -> dict:
        return self._call("DELETE", f"/robots/{robot_id}").json()

    def stats(self) -> dict:
        return self._call("GET", "/stats").json()


def _png(img) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise BadInput("Cannot encode image as PNG")
    return buf.tobytes()


def align_request(pairs, **options) -> dict:
    """The multipart parts of a `POST /align` (see services/aligner/schemas.py): keyword
    arguments `data` (the JSON `meta` field) and `files` (PNG colour and depth per view).
    The indexed layout: a view object in several pairs is sent once. A view with an
    `encoded` dict ({"rgb", "depth"} image bytes, `fleetmap.view.StoredView`) is sent as
    stored, not decoded and encoded again.
    options: method, cloud, colour."""
    import json

    meta = {"pairs": [], "views_a": [], "views_b": [], **options}
    files = {}
    index: list[dict[int, int]] = [{}, {}]
    for a, b in pairs:
        ij = []
        for k, (side, v) in enumerate((("a", a), ("b", b))):
            seen = index[k]
            if id(v) not in seen:
                i = seen[id(v)] = len(seen)
                meta[f"views_{side}"].append(
                    {
                        "stamp": v.stamp,
                        "T_map_cam": v.T_map_cam.tolist(),
                        "intrinsics": v.intrinsics.to_dict(),
                    }
                )
                for kind in ("rgb", "depth"):
                    name = view_part(side, i, kind)
                    data = v.encoded[kind] if hasattr(v, "encoded") else _png(getattr(v, kind))
                    files[name] = (name, data, "application/octet-stream")
            ij.append(seen[id(v)])
        meta["pairs"].append(ij)
    return {"data": {ALIGN_META: json.dumps(meta)}, "files": files}


class AlignerClient(_Client):
    """Client of the aligner service."""

    def align(
        self, pairs, method: str = "default", cloud: bool = False, colour: str = "robot"
    ) -> dict:
        """pairs: list of (RGBDView of robot A, RGBDView of robot B)."""
        parts = align_request(pairs, method=method, cloud=cloud, colour=colour)
        return self._call("POST", "/align", **parts).json()

    def cloud(self, cloud_id: str) -> bytes:
        return self._call("GET", f"/clouds/{cloud_id}").content


def services_config(**clients: _Client) -> dict:
    """Each service's parameters in force (its `GET /config`), by name, for report.json; a
    service that would not say (an older one, a token without the right) is recorded with
    why, `{"unavailable": ...}`, and logged: never fatal to the job that asked."""
    out = {}
    for name, client in clients.items():
        try:
            out[name] = client.config()
        except FleetmapError as exc:
            log.warning("%s's parameters not recorded: %s", name, exc)
            out[name] = {"unavailable": str(exc)}
    return out
