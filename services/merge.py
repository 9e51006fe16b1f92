"""`fleetmap merge`: the main job, from N robot folders to one global map, as named stages.

extract (every core) while the services start -> ingest (POST keyframes) -> overlaps
(verified keyframe pairs of every robot pair) -> align (each overlapping pair's views to
the aligner) -> place (`fleetmap.fleet.placement.place_fleet`: spanning tree, pose graph)
-> write (`fleetmap.services.outputs`; report.json: `fleetmap.fleet.report`). A robot with
no trustworthy link is listed as unmerged, never placed on a guess.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fleetmap.client import AlignerClient, PlaceDBClient, services_config
from fleetmap.dataset import Recording
from fleetmap.errors import BadVocabulary
from fleetmap.extract import keyframe_indices
from fleetmap.extract_pool import extract_keyframes
from fleetmap.fleet.correct import closures_meanwhile, correct_fleet
from fleetmap.fleet.placement import place_fleet
from fleetmap.fleet.report import OVERLAP_KEYS, merge_parameters, merge_report
from fleetmap.fleet.types import DEFAULT_MERGE, Fit, MergeParams
from fleetmap.fleet.view_choice import (
    after_second_views,
    local_views,
    overlaps_to_align,
    pair_views,
)
from fleetmap.mapcloud import MapCloud
from fleetmap.services.embedded import check_reachable, start_services, warm_up
from fleetmap.services.foxglove import write_fleet_mcap
from fleetmap.services.outputs import write_maps, write_pictures
from fleetmap.vocabulary import load_vocabulary

log = logging.getLogger(__name__)

STAGES = ("extract", "ingest", "overlaps", "align", "outputs")  # report.json's timing_s


@contextlib.contextmanager
def timed(timing: dict, stage: str):
    """Add the block's wall time to timing[stage]."""
    t = time.perf_counter()
    try:
        yield
    finally:
        timing[stage] = timing.get(stage, 0.0) + time.perf_counter() - t


def run_merge(
    recs: list[Recording],
    out: Path,
    params: MergeParams = DEFAULT_MERGE,
    vocab_path=None,
    place_db: str | None = None,
    aligner: str | None = None,
    quiet: bool = False,
    token: str | None = None,
    workers: int | None = None,
) -> dict:
    """The whole job; writes OUT/report.json, merged.ply, pose_graph.g2o, trajectories/,
    overview.png, overlap_matrix.png, fleet.mcap; the links are registered meanwhile.
    `params.correct_drift` (on by default): the keyframe pose graph over the fleet corrects
    maps that bend; it costs nothing where none may (`fleet.correct.correct_fleet`)."""
    check_reachable(place_db, aligner, token)  # before any long work
    load_vocabulary(vocab_path)  # a --vocab it cannot read: named before any work
    out.mkdir(parents=True, exist_ok=True)
    timing, t_all = dict.fromkeys(STAGES, 0.0), time.perf_counter()
    kf_index = {r.robot_id: keyframe_indices(r, params.keyframes) for r in recs}
    ids, voxel, max_views = [r.robot_id for r in recs], params.voxel_m, params.views.max_views
    with contextlib.ExitStack() as stack:
        keyframes = extract_keyframes(recs, kf_index, vocab_path, workers)  # runs meanwhile
        stack.callback(keyframes.close)
        with timed(timing, "start"):  # the time the job waited for its services
            services = start_services(stack, place_db, aligner, vocab_path)  # meanwhile
            db = stack.enter_context(PlaceDBClient(services.ready("place-db"), token=token))
        checked_vocabulary(db, vocab_path)
        clouds, parts = ingest(keyframes, db, sum(map(len, kf_index.values())), timing, quiet)
        clouds = voxelising(clouds, voxel)  # for merged.ply, while the robots are aligned
        with timed(timing, "overlaps"):
            detected(db, sum(map(len, kf_index.values())), quiet)
            overlaps, by_pair = find_overlaps(db, ids)
        found = closures_meanwhile(parts, list(overlaps)) if params.correct_drift else None
        with timed(timing, "start"):
            al = stack.enter_context(AlignerClient(services.ready("aligner"), 900, token))
        with timed(timing, "align"):
            edges, fits, links = align_pairs(db, al, recs, kf_index, by_pair, max_views, quiet)
        warm = warm_up("matplotlib.pyplot", "mcap_protobuf.writer")  # imported while linking
        with timed(timing, "outputs"):
            placement, edges = placed_fleet(ids, edges)
        placed, drift = placement.T_ref, params.correct_drift
        with timed(timing, "links"):  # the keyframe graph's depth closures are at the links
            overlaps += link_overlaps(db, edges, fits, links)
        with timed(timing, "fleet_graph"):
            fleet = fleet_graph(parts, placed, edges, overlaps, ids[0], found) if drift else None
        with timed(timing, "outputs"):
            drawing = write_maps(out, recs, kf_index, clouds, placed, edges, params, fleet)
        in_force = merge_parameters(params, vocab_path, services_config(place_db=db, aligner=al))
    report = merge_report(recs, kf_index, placement, overlaps, fits, edges, in_force)
    if fleet is not None:
        add_fleet_report(report, fleet)
    with timed(timing, "outputs"):
        warm.join()  # matplotlib must not be half imported when the pictures select Agg
        write_pictures(out, ids, drawing, report)
        write_fleet_mcap(out, report)  # Foxglove's schemas, from the files written
    timing["total"] = time.perf_counter() - t_all
    report["timing_s"] = {k: round(v, 3) for k, v in timing.items()}
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report


def fleet_graph(parts, placed, edges, overlaps, reference: str, search):
    """`correct_fleet`, with the feature closures `search` found meanwhile (a future of
    `closures_meanwhile`, or None: searched now)."""
    found = search.result() if search is not None else None
    return correct_fleet(parts, placed, edges, overlaps, reference, found=found)


class _Voxelised:
    """A robot's map cloud voxelised in the background; `voxelised` as `MapCloud`'s."""

    def __init__(self, future, voxel: float):
        self.future, self.voxel = future, voxel

    def voxelised(self, voxel: float) -> tuple[np.ndarray, np.ndarray]:
        if voxel != self.voxel:
            raise ValueError(f"Expected the voxel size {self.voxel} m, got {voxel}")
        return self.future.result()


def voxelising(clouds: dict[str, MapCloud], voxel: float) -> dict[str, _Voxelised]:
    """Each robot's cloud voxelised in one background thread (1-2 s for 180 keyframes)."""
    pool = ThreadPoolExecutor(1, thread_name_prefix="voxelise")
    out = {r: _Voxelised(pool.submit(c.voxelised, voxel), voxel) for r, c in clouds.items()}
    pool.shutdown(wait=False)
    return out


def placed_fleet(ids: list[str], edges: dict) -> tuple:
    """`place_fleet` in the first robot's frame, each robot it could not place logged."""
    placement, used = place_fleet(ids, edges)
    for robot, why in placement.flagged.items():
        log.warning("%s not placed: %s", robot, why)
    return placement, used


def add_fleet_report(report: dict, fleet) -> None:
    """The fleet graph's figures; per robot the best rigid T_ref_R of its corrected map and
    how far the drift correction moved it."""
    report["fleet_graph"] = fleet.summary()
    for r, c in fleet.robots.items():
        report["transforms"][r] = c.rigid.tolist()
        report["robots"][r]["drift_correction"] = c.summary()


def checked_vocabulary(client: PlaceDBClient, path):
    """The vocabulary to extract with: the place database's must be the same."""
    vocab = load_vocabulary(path)
    served = client.vocabulary()["vocab_id"]
    if served != vocab.vocab_id:
        raise BadVocabulary(
            f"The place database uses vocabulary {served}, this CLI loaded "
            f"{vocab.vocab_id}: pass the same file with --vocab"
        )
    return vocab


def ingest(
    keyframes, db, total: int, timing: dict, quiet: bool, in_flight: int = 8
) -> tuple[dict[str, MapCloud], dict[str, list]]:
    """POST every extracted keyframe, up to `in_flight` at once (the place database commits
    concurrent keyframes together); returns each robot's map cloud (all keyframes) and its
    keyframes in time order.

    timing["extract"]: time spent waiting for the extraction workers; timing["ingest"]:
    from the last keyframe extracted to the last one acknowledged."""
    parts: dict[str, list] = {}
    bar = tqdm(total=total, desc="extract+ingest", unit="kf", disable=quiet)
    pending: deque = deque()
    with ThreadPoolExecutor(4) as posters:
        t = time.perf_counter()
        for kf in keyframes:
            timing["extract"] += time.perf_counter() - t
            pending.append(posters.submit(db.add_keyframe, kf.frame))
            parts.setdefault(kf.robot_id, []).append(kf)
            while len(pending) > in_flight or (pending and pending[0].done()):
                pending.popleft().result()  # raises the first failure
                bar.update()
            t = time.perf_counter()
        t = time.perf_counter()
        while pending:
            pending.popleft().result()
            bar.update()
        timing["ingest"] = time.perf_counter() - t
    bar.close()
    return {r: MapCloud.from_keyframes(kfs) for r, kfs in parts.items()}, parts


def detected(db, total: int, quiet: bool, timeout_s: float = 600.0) -> None:
    """Wait for the place database's overlap detection of the `total` keyframes posted (the
    embedded database starts it at this first overlaps request), with a progress bar."""
    db.overlap_graph()  # starts a deferred detection
    bar = tqdm(total=total, desc="overlaps", unit="kf", disable=quiet)
    end = time.monotonic() + timeout_s
    while (pending := db.stats()["pending"]) and time.monotonic() < end:
        bar.update(max(total - pending, 0) - bar.n)
        time.sleep(0.05)
    bar.update(total - bar.n)
    bar.close()


def find_overlaps(db, ids: list[str]) -> tuple[list[dict], dict]:
    """Verified keyframe pairs of every robot pair (the report's cascade overlaps)."""
    overlaps, by_pair = [], {}
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            pairs = overlaps_to_align(db, a, b, wait=600)
            by_pair[(a, b)] = pairs
            overlaps += [
                {k: p[k] for k in OVERLAP_KEYS}
                for p in pairs
                if p["source"] == "cascade"  # link pairs are listed after aligning
            ]
    return overlaps, by_pair


def align_pairs(db, al, recs, kf_index, by_pair, max_views: int, quiet: bool, workers: int = 2):
    """Send each overlapping pair's views near its overlaps to the aligner (two pairs at a
    time); register each gated alignment with the place database, in the background.
    Returns (edges, fits, links: fit index -> future of the link overlaps recorded)."""
    recs_by_id = {r.robot_id: r for r in recs}

    def one(item) -> Fit | None:
        (a, b), pairs = item
        chosen = (pairs, recs_by_id[a], recs_by_id[b], kf_index[a], kf_index[b], max_views)
        views = pair_views(*chosen)
        if not views:
            return None
        fit = aligned(al, views, a, b)
        if not fit.merged and (local := local_views(*chosen)):  # a map that bends: again
            fit = after_second_views(fit, aligned(al, local, a, b))
        return fit

    edges, fits, links = {}, [], {}
    linker = ThreadPoolExecutor(1)
    with (
        ThreadPoolExecutor(workers) as pool,
        tqdm(total=len(by_pair), desc="align", unit="pair", disable=quiet) as bar,
    ):
        for fit in pool.map(one, by_pair.items()):
            bar.update()
            if fit is None:
                continue
            fits.append(fit)
            if fit.merged:
                a, b = fit.robot_a, fit.robot_b
                edges[(a, b)] = fit.edge()
                # the place database records the keyframe pairs co-visible under it
                links[len(fits) - 1] = linker.submit(db.put_link, a, b, fit.T_a_b)
    linker.shutdown(wait=False)  # the submitted links still run
    return edges, fits, links


def aligned(al: AlignerClient, views: list, a: str, b: str) -> Fit:
    """The aligner's fit of robots a and b from the view pairs, with the views' counts."""
    fit = Fit.from_json(al.align(views), a, b)
    fit.views = [len({id(v) for v, _ in views}), len({id(v) for _, v in views})]
    return fit


def link_overlaps(db: PlaceDBClient, edges: dict, fits: list[Fit], links: dict) -> list[dict]:
    """Wait for the links registered in the background; the co-visible keyframe pairs they
    gave (the report's "link" overlaps). Each fit gets its count."""
    for k, future in links.items():
        fits[k].link_overlaps = future.result()
    return [
        {k: p[k] for k in OVERLAP_KEYS} for a, b in edges for p in db.overlaps(a, b, source="link")
    ]
