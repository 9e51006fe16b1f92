"""Keyframes of many robots extracted on every core: one pipeline stage of the merge.

Each worker process reads a keyframe's colour and depth once and returns everything the
later stages need from those images: the frame structure (for the place database) and the
keyframe's share of the robot's map cloud (for the final refinement and `merged.ply`), so no
stage reads the images again. Workers fork from a server that has already imported the
extraction code (`forkserver`), so a pool starts in well under a second.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import sys
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fleetmap.dataset import ImageReader, Recording
from fleetmap.frame import Frame
from fleetmap.mapcloud import MAX_DEPTH_M, view_points
from fleetmap.view import encode_view

#: Every CLOUD_STRIDE-th pixel of a keyframe's depth goes into the map cloud.
CLOUD_STRIDE = 4
CLOUD_MAX_DEPTH_M = MAX_DEPTH_M

_extractor = None  # per worker process


@dataclass
class Keyframe:
    """One extracted keyframe: frame structure and map-cloud share.

    points : ndarray of shape (M, 3) float32, in the robot's map frame (metres).
    colours : ndarray of shape (M, 3) uint8, RGB.
    """

    robot_id: str
    index: int  # into the recording's frames
    frame: Frame
    points: np.ndarray
    colours: np.ndarray
    view: dict | None = None  # {"rgb": JPEG, "depth": PNG} when asked for (`encode_view`)


@dataclass(frozen=True)
class _Task:
    robot_id: str
    index: int
    stamp: float
    rgb_path: Path
    depth_path: Path
    reader: ImageReader  # the recording's images at its working resolution
    T_map_cam: np.ndarray
    view: bool = False


def _init(vocab_path, worker: bool = True) -> None:
    import cv2

    from fleetmap.extract import FrameExtractor
    from fleetmap.vocabulary import load_vocabulary

    if worker:  # one process per core already; never in the caller's own process, whose
        # aligner and place database would stay on one thread after. OpenBLAS too: its
        # threads spin after each product (the bag of words' one), and two workers' spinning
        # threads doubled the extraction of two HoloLens robots (py-spy: 4.7 s of
        # `Vocabulary.bow` in the workers for 0.13 s of work; 10.2 -> 4.5 s wall)
        from threadpoolctl import threadpool_limits

        cv2.setNumThreads(1)
        threadpool_limits(1)
    global _extractor
    _extractor = FrameExtractor(load_vocabulary(vocab_path))


def _extract(t: _Task) -> Keyframe:
    rgb, depth, k = t.reader.rgb(t.rgb_path), t.reader.depth(t.depth_path), t.reader.intrinsics
    frame = _extractor(t.robot_id, t.stamp, rgb, depth, k, t.T_map_cam)
    points, colours = view_points(rgb, depth, k, t.T_map_cam, CLOUD_STRIDE, CLOUD_MAX_DEPTH_M)
    # a frame without a depth reading (a sensor warming up, a covered lens) is a keyframe
    # without a view: the aligner could not use it, and the place database refuses it
    view = encode_view(rgb, depth) if t.view and depth.any() else None
    return Keyframe(t.robot_id, t.index, frame, points.astype(np.float32), colours, view)


def _tasks(
    recs: list[Recording], kf_index: dict[str, list[int]], views: bool, by_time: bool
) -> list[_Task]:
    out = []
    for rec in recs:
        f0 = rec.frames[0].stamp if len(rec) else 0.0
        for i in kf_index[rec.robot_id]:
            f = rec.frames[i]
            t = _Task(
                rec.robot_id,
                i,
                f.stamp,
                f.rgb_path,
                f.depth_path,
                rec.reader,
                f.T_map_cam,
                views,
            )
            out.append((f.stamp - f0 if by_time else 0.0, t))
    return [t for _, t in sorted(out, key=lambda x: x[0])]  # stable: robot order without


def _start_fork_server() -> None:
    """The fork server started without the working folder on its import path. Python 3.11
    starts it with `python -c`, whose path begins with the working folder, and ignores the
    `sys_path` multiprocessing hands it: run from a folder holding a `fleetmap` folder (the
    clone's parent), the server imported that as the package and every worker failed
    ("Cannot read vocabulary <cwd>/fleetmap/assets/..."). `PYTHONSAFEPATH` (3.11) leaves
    the working folder out."""
    from multiprocessing import forkserver

    saved = os.environ.get("PYTHONSAFEPATH")
    os.environ["PYTHONSAFEPATH"] = "1"
    try:
        forkserver.ensure_running()
    finally:
        if saved is None:
            del os.environ["PYTHONSAFEPATH"]
        else:
            os.environ["PYTHONSAFEPATH"] = saved


@contextlib.contextmanager
def _main_hidden():
    """Workers need only this package: keep multiprocessing from running the caller's main
    script again in each of them (a console script, a notebook, `python -` from stdin)."""
    main = sys.modules["__main__"]
    saved = {k: main.__dict__[k] for k in ("__spec__", "__file__") if k in main.__dict__}
    main.__spec__ = None
    main.__dict__.pop("__file__", None)
    try:
        yield
    finally:
        main.__dict__.update(saved)


def default_workers() -> int:
    """Worker processes: every core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def extract_keyframes(
    recs: list[Recording],
    kf_index: dict[str, list[int]],
    vocab_path=None,
    workers: int | None = None,
    views: bool = False,
    by_time: bool = False,
) -> Iterator[Keyframe]:
    """Every keyframe of every robot, robot by robot in time order (`by_time`: all robots
    interleaved by time since each one's first frame, as they would stream), extracted by
    `workers` processes (default: every core; 1 = in this process), with their encoded
    RGB-D views if `views`. The work starts at once, before the first keyframe is asked
    for; closing the iterator stops it."""
    tasks = _tasks(recs, kf_index, views, by_time)
    workers = default_workers() if workers is None else workers
    if workers <= 1 or len(tasks) < 8:
        _init(vocab_path, worker=False)
        return (_extract(t) for t in tasks)
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["fleetmap.extract", "fleetmap.extract_pool"])
    pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=(vocab_path,))
    _start_fork_server()  # once a process; the workers fork from it
    with _main_hidden():  # workers start here, on submission
        results = pool.map(_extract, tasks, chunksize=2)  # every task submitted now

    def ordered() -> Iterator[Keyframe]:
        try:
            yield from results
        finally:
            pool.shutdown(cancel_futures=True)

    return ordered()
