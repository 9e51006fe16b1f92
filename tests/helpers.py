"""Helpers several test modules share (fixtures live in conftest.py)."""

from __future__ import annotations

from pathlib import Path

import httpx
import numpy as np
from scipy.spatial.transform import Rotation

from fleetmap.frame import Frame

OCTET = {"content-type": "application/octet-stream"}


def built_once(tmp_path_factory, name: str, build) -> Path:
    """The folder `name` in this run's temporary root, shared by its xdist workers: built by
    `build(folder)` for the first worker to ask (the others wait for it, under a lock), then
    read by all (a session fixture's data, built once per run, not once per worker). A run
    without xdist builds it in its own temporary folder."""
    import fcntl
    import os
    import shutil

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # pytest-N: this run's, with the workers' own folders in it
    folder, done = base / f"shared-{name}", base / f"shared-{name}.done"
    with (base / f"shared-{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            done.touch()
    return folder


def make_frame(**kw) -> Frame:
    """A small valid Frame of random content; `kw` overrides its fields."""
    rng = np.random.default_rng(0)
    base = dict(
        robot_id="r1",
        stamp=1.0,
        gist=rng.random(384).astype(np.float16),
        keypoints=rng.random((5, 2)).astype(np.float32) * 100,
        descriptors=rng.integers(0, 255, (5, 128), dtype=np.uint8),
        bow_ids=np.array([1, 2], np.uint32),
        bow_counts=np.array([3, 2], np.uint16),
    )
    base.update(kw)
    return Frame(**base)


def moved(deg: float, metres: float) -> np.ndarray:
    """T_new_old: a robot's map frame turned `deg` about z and shifted `metres` along x."""
    S = np.eye(4)
    S[:3, :3] = Rotation.from_euler("z", deg, degrees=True).as_matrix()
    S[0, 3] = metres
    return S


def post_frame(client, robot, data):
    """A keyframe alone (octet-stream)."""
    return client.post(f"/robots/{robot}/keyframes", content=data, headers=OCTET)


def post_with_view(client, robot: str, frame: bytes, view: dict) -> int:
    """A keyframe with its RGB-D view (multipart), 200 or 201."""
    files = {"frame": ("frame", frame, "application/octet-stream")}
    files |= {k: (k, v, "application/octet-stream") for k, v in view.items()}
    r = client.post(f"/robots/{robot}/keyframes", files=files)
    assert r.status_code in (200, 201), r.text
    return r.status_code


def real_align(calls: list):
    """The aligner's pipeline in-process, as `LiveMap` calls it; each call's number of
    pairs appended to `calls`."""
    from fleetmap.align import align_views

    def align(pairs):
        calls.append(len(pairs))
        views = {id(v): v.decoded() for pair in pairs for v in pair}
        return align_views([(views[id(a)], views[id(b)]) for a, b in pairs]).to_dict()

    return align


def ingest(url, robot, frames, acked, errors, stop=None) -> None:
    """Post `frames` for `robot`; (robot, id, data) of each 201 into `acked`, else into
    `errors`; a transport error (the server killed) ends the robot."""
    with httpx.Client(base_url=url, timeout=30) as c:
        for data in frames:
            if stop is not None and stop.is_set():
                return
            try:
                r = c.post(f"/robots/{robot}/keyframes", content=data, headers=OCTET)
            except httpx.TransportError:
                return  # the server died mid-request: not acknowledged
            if r.status_code == 201:
                acked.append((robot, r.json()["id"], data))
            else:
                errors.append((robot, r.status_code, r.text))


def resized_recording(src: Path, dst: Path, factor: float) -> Path:
    """A copy of the recording `src` at `factor` times its image size (colour cubic, depth
    nearest, camera.json scaled with it): the same robot seen by a camera of more pixels
    (`simulate.other_camera` on every row of a whole cut)."""
    from fleetmap.dataset import cut_recording
    from fleetmap.simulate import other_camera

    return other_camera(cut_recording(src, slice(None), dst, np.eye(4)), rows=1.0, factor=factor)
