"""`fleetmap stream` (recordings replayed as robots would stream them) and `fleetmap map`
(the live map's files, as `fleetmap merge` writes them)."""

from __future__ import annotations

import argparse
import json
import os
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

DONE = object()


def stream(recs, kf_index, client, vocab_path, speed: float, quiet: bool, workers=None) -> dict:
    """Post every robot's keyframes with their views, each robot from its own thread in
    time order, all starting together; keyframe k of a robot is posted (its stamp - the
    robot's first stamp) / speed seconds after the start (speed 0: as fast as extracted).
    The robots' first keyframes go in the order given, so the first robot is the first
    the place database knows (the live map's reference when it is merged).
    Returns {robot: keyframes posted} and the seconds to the last acknowledgement."""
    from fleetmap.extract_pool import extract_keyframes

    ids = [r.robot_id for r in recs]
    first = {r.robot_id: r.frames[0].stamp if len(r) else 0.0 for r in recs}
    total = sum(map(len, kf_index.values()))
    queues = {r: queue.Queue(maxsize=64) for r in ids}
    registered = [threading.Event() for _ in ids]
    counts = dict.fromkeys(ids, 0)
    errors: list[BaseException] = []
    bar = tqdm(total=total, desc="stream", unit="kf", disable=quiet)
    t0 = time.monotonic()
    stop = threading.Event()  # an interrupt or a failure: posters stop at once (they went on)

    def post(k: int, robot: str) -> None:
        try:
            while (kf := _next(queues[robot], stop)) is not DONE:
                due = t0 + (kf.frame.stamp - first[robot]) / speed if speed > 0 else 0.0
                if stop.wait(max(0.0, due - time.monotonic())):
                    break
                while counts[robot] == 0 and k > 0 and not registered[k - 1].wait(0.2):
                    if stop.is_set():
                        return
                client.add_keyframe(kf.frame, view=kf.view)
                counts[robot] += 1
                registered[k].set()
                bar.update()
        except BaseException as exc:  # reported by the main thread
            errors.append(exc)
        finally:
            registered[k].set()

    posters = [threading.Thread(target=post, args=(k, r), daemon=True) for k, r in enumerate(ids)]
    for p in posters:
        p.start()
    keyframes = extract_keyframes(recs, kf_index, vocab_path, workers, views=True, by_time=True)
    try:
        _feed(keyframes, queues, errors)
    except BaseException:
        stop.set()
        raise
    finally:
        if errors:  # a poster failed: the others need not finish
            stop.set()
        for r in ids:
            _put_done(queues[r], stop)
        for p in posters:  # stopped: a request in flight is not waited for (daemon threads)
            p.join(None if not stop.is_set() else 0.0)
        bar.close()
    if errors:
        raise errors[0]
    return {"keyframes": counts, "seconds": time.monotonic() - t0}


def _next(q: queue.Queue, stop: threading.Event):
    """The queue's next keyframe, or DONE once `stop` is set."""
    while not stop.is_set():
        try:
            return q.get(timeout=0.2)
        except queue.Empty:
            continue
    return DONE


def _put_done(q: queue.Queue, stop: threading.Event) -> None:
    """DONE after the queued keyframes; not waited for once `stop` is set (a poster that
    stopped empties its queue no more)."""
    while True:
        try:
            return q.put(DONE, timeout=0.2)
        except queue.Full:
            if stop.is_set():
                return


def _feed(keyframes, queues: dict, errors: list) -> None:
    """Hand each extracted keyframe to its robot's poster; stop at the first failure."""
    try:
        for kf in keyframes:
            while not errors:
                try:
                    queues[kf.robot_id].put(kf, timeout=0.5)
                    break
                except queue.Full:
                    continue
            if errors:
                return
    finally:
        if hasattr(keyframes, "close"):
            keyframes.close()


def cmd_stream(args: argparse.Namespace) -> int:
    """Replay robot recordings into a place database as the robots would stream them."""
    from fleetmap.client import PlaceDBClient
    from fleetmap.extract import keyframe_indices
    from fleetmap.robot_args import distinct_ids
    from fleetmap.services.commands import _policy, _read_robots
    from fleetmap.services.merge import checked_vocabulary

    recs = distinct_ids(_read_robots(args, args.robots))
    kf_index = {r.robot_id: keyframe_indices(r, _policy(args)) for r in recs}
    if args.nice > 0 and hasattr(os, "nice"):  # the extraction workers inherit it
        os.nice(args.nice)
    with PlaceDBClient(args.place_db, token=args.token) as client:
        checked_vocabulary(client, args.vocab)
        done = stream(recs, kf_index, client, args.vocab, args.speed, args.quiet)
        m = client.live_map()
    for r, n in done["keyframes"].items():
        print(f"{r}: {n} keyframes streamed")
    print(
        f"streamed in {done['seconds']:.1f} s; live map version {m['version']}: "
        f"{len(m['transforms'])} of {len(m['robots'])} robots placed so far "
        f"(fleetmap map --place-db {args.place_db.split(',')[0]} -o DIR writes it)"
    )
    return 0


def cmd_map(args: argparse.Namespace) -> int:
    """Write the live map's files: what `fleetmap merge` writes."""
    from fleetmap.client import PlaceDBClient, services_config
    from fleetmap.fleet.map_render import BASE_VOXEL_M
    from fleetmap.services.outputs import prepare_out

    out = Path(args.out)
    previous = prepare_out(out)  # --voxel: at least 1 mm, the parser's type (`cli._voxel_m`)
    t0, voxel = time.perf_counter(), max(args.voxel, BASE_VOXEL_M)
    with PlaceDBClient(args.place_db, token=args.token, timeout=600) as client:
        m = client.live_map()
        cloud = client.map_file("cloud.ply", voxel=voxel)
        picture = client.map_file("overview.png")
        tracks = client.map_trajectories()
        lines = json.loads(client.map_file("lines"))["overlaps"]
        overlaps = overlap_items(client, m)
        served = services_config(place_db=client)["place_db"]
        pose_graph = client.map_pose_graph()
    files = LiveFiles(cloud, picture, tracks, lines, overlaps, voxel, served, pose_graph)
    write_live_outputs(out, m, files, args.place_db, time.perf_counter() - t0)
    previous.remove_unwritten()
    where = f"in {m['reference']}'s frame" if m["reference"] else "placed (none yet)"
    print(
        f"live map version {m['version']}: {len(m['transforms'])} of {len(m['robots'])} robots "
        f"{where}; results: {out / 'report.json'}, {out / 'merged.ply'}, "
        f"{out / 'overview.png'}, {out / 'fleet.mcap'} (Foxglove)"
    )
    for u in m["unmerged"]:
        print(f"unmerged {u['robot']}: {u['reason']}")
    return 0


@dataclass
class LiveFiles:
    """What `fleetmap map` fetched besides `GET /map`: the cloud (PLY bytes, at `voxel_m`),
    the overview (PNG bytes), the keyframe trajectories, the overlap lines (`GET
    /map/lines`), the overlap items of the map's robot pairs (`GET /overlaps`), the place
    database's parameters in force (`GET /config`) and the keyframe pose graph (g2o text,
    `GET /map/pose_graph.g2o`; None where none is solved: the robots' graph is written)."""

    cloud: bytes
    picture: bytes
    tracks: dict
    lines: list | None
    overlaps: list[dict]
    voxel_m: float
    served: dict | None = None
    pose_graph: str | None = None


def overlap_items(client, m: dict) -> list[dict]:
    """The overlaps of every robot pair of the live map's overlap graph, items as in
    report.json (`fleetmap.fleet.report.OVERLAP_KEYS`)."""
    from fleetmap.fleet.report import OVERLAP_KEYS

    return [
        {k: o[k] for k in OVERLAP_KEYS}
        for e in m["overlaps"]
        for o in client.overlaps(e["robot_a"], e["robot_b"])
    ]


def write_live_outputs(out: Path, m: dict, files: LiveFiles, source: str, seconds: float) -> None:
    """report.json, merged.ply, overview.png, overlap_matrix.png, pose_graph.g2o,
    trajectories/ (keyframe poses: the live map holds keyframes only) and fleet.mcap."""
    from fleetmap import pictures
    from fleetmap.fleet.merge_rules import merged_edges
    from fleetmap.fleet.report import live_report
    from fleetmap.fleet.types import pair_key, transform_from_json
    from fleetmap.services.foxglove import write_fleet_mcap
    from fleetmap.services.outputs import write_g2o, write_tum
    from fleetmap.services.schemas import redact_url

    (out / "trajectories").mkdir(parents=True, exist_ok=True)
    (out / "merged.ply").write_bytes(files.cloud)
    (out / "overview.png").write_bytes(files.picture)
    for r, rows in files.tracks.items():
        write_tum(out / "trajectories" / f"{r}.txt", rows, m["reference"])
    T_ref = {r: transform_from_json(T) for r, T in m["transforms"].items()}
    edges = merged_edges({pair_key(p["robot_a"], p["robot_b"]): p for p in m["pairs"]}, set(T_ref))
    names = ([m["reference"]] if m["reference"] else []) + [
        r for r in m["robots"] if r != m["reference"]
    ]
    if files.pose_graph is not None:  # the keyframe graph, as `fleetmap merge` writes it
        (out / "pose_graph.g2o").write_text(files.pose_graph)
    else:
        write_g2o(out / "pose_graph.g2o", names, T_ref, edges)
    pairs = [
        {"robot_a": e["robot_a"], "robot_b": e["robot_b"]}
        for e in m["overlaps"]
        for _ in range(e["pairs"])
    ]
    place_db = redact_url(source.split(",")[0])  # a password in the URL stays out
    report = live_report(m, place_db, files.overlaps, edges, files.voxel_m, files.served)
    if "fleet_graph" in m:  # the live map's keyframe graph, as `fleetmap merge` reports it
        report["fleet_graph"] = m["fleet_graph"]
    report["timing_s"] = {"total": round(seconds, 3)}
    if names:
        pictures.overlap_matrix(out / "overlap_matrix.png", names, {"overlaps": pairs})
    (out / "report.json").write_text(json.dumps(report, indent=2))
    write_fleet_mcap(out, report, files.lines)
