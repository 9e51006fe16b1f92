"""report.json: one builder for `fleetmap merge` and `fleetmap map` (CONTRACT sections 2
and 6), so both write the same keys:

- `schema_version`, `transform_convention`: this layout, and what `transforms` mean;
- `reference`: the robot whose map frame is the global one (None: no robot placed yet);
- `source`: where the map comes from: {"job": "merge"}, or {"job": "map", "place_db",
  "live_map_version"};
- `robots`: per robot at least {"keyframes"}; merge adds "frames", "source" (its folder),
  "chain" (the robots its placement went through), "image_size" (as read, at most
  `dataset.WORK_PIXELS`) and "file_image_size", map "views" and "state";
- `transforms`: T_ref_R per merged robot R (row-major 4x4: R's map frame into the
  reference's);
- `overlaps`: verified keyframe pairs [{robot_a, stamp_a, robot_b, stamp_b, inliers,
  source}] ("cascade": found by the place database, "link": co-visible under a fit);
- `overlap_graph`: per robot pair with overlaps, {robot_a, robot_b, pairs, best_inliers,
  total_inliers};
- `fits`: the pairwise fits: merge, the aligner's answers (`Fit.to_json`); map, the merge
  worker's pair states (`PairState`);
- `unmerged`: the robots not placed, `unmerged_reasons`: robot -> why;
- `pose_graph`: {"edges": the fits the placement used, "optimised": whether the pose graph
  reconciled cycles (None: the live map does not say)};
- `parameters`: every parameter of the command in force; with the services' own (their
  `GET /config`: settings, no secrets) under `place_db` (merge and map) and `aligner`
  (merge), or `{"unavailable": why}` where a service would not say;
- `updated_at`: unix time of the placement;
- `timing_s`: seconds per stage (the command adds it last); with `merge --correct-drift`
  also `fleet_graph` and per robot `drift_correction`.
"""

from __future__ import annotations

import dataclasses
import time

from fleetmap.fleet.cycles import CycleParams
from fleetmap.fleet.types import Fit, MergeParams, Placement, transform_to_json

#: report.json layout version (2: schema_version, transform_convention, parameters).
REPORT_VERSION = 2
TRANSFORM_CONVENTION = (
    "transforms[R] is T_ref_R: it maps points of robot R's map frame into the "
    "reference robot's map frame (row-major 4x4, metres)"
)
#: The keys of an `overlaps` item.
OVERLAP_KEYS = ("robot_a", "stamp_a", "robot_b", "stamp_b", "inliers", "source")


def build_report(
    *,
    reference: str | None,
    source: dict,
    robots: dict,
    transforms: dict,
    overlaps: list[dict],
    overlap_graph: list[dict],
    fits: list[dict],
    unmerged_reasons: dict[str, str],
    pose_graph: dict,
    parameters: dict,
    updated_at: float | None,
) -> dict:
    """report.json's content but its timings, in the documented key order."""
    return {
        "schema_version": REPORT_VERSION,
        "reference": reference,
        "transform_convention": TRANSFORM_CONVENTION,
        "source": source,
        "robots": robots,
        "transforms": transforms,
        "overlaps": overlaps,
        "overlap_graph": overlap_graph,
        "fits": fits,
        "unmerged": list(unmerged_reasons),
        "unmerged_reasons": unmerged_reasons,
        "pose_graph": pose_graph,
        "parameters": parameters,
        "updated_at": updated_at,
    }


def merge_report(recs, kf_index, placement: Placement, overlaps, fits: list[Fit], edges, params):
    """`fleetmap merge`'s report: `recs` (the robots' `Recording`s, the reference first),
    their keyframe indices, the placement, the overlap items, the fits and the edges the
    placement used; `params`: `merge_parameters`."""
    ids = [r.robot_id for r in recs]
    robots = {
        r.robot_id: {
            "keyframes": len(kf_index[r.robot_id]),
            "frames": len(r),
            "source": str(r.source or r.root),  # a bag as given, not its cache folder
            "chain": placement.chain.get(r.robot_id),
            # the images as read (`dataset.WORK_PIXELS`) and as the files hold them
            "image_size": [r.intrinsics.width, r.intrinsics.height],
            "file_image_size": [
                (r.file_intrinsics or r.intrinsics).width,
                (r.file_intrinsics or r.intrinsics).height,
            ],
            # the camera read (camera.json, the flags or the TUM fr1 defaults), as the files hold it
            "camera": (r.file_intrinsics or r.intrinsics).to_dict(),
        }
        for r in recs
    }
    unplaced = [r for r in ids if r not in placement.T_ref]
    return build_report(
        reference=ids[0],
        source={"job": "merge"},
        robots=robots,
        transforms={r: transform_to_json(placement.T_ref[r]) for r in ids if r in placement.T_ref},
        overlaps=overlaps,
        overlap_graph=graph_of(overlaps),
        fits=[f.to_json() for f in fits],
        unmerged_reasons={r: merge_unmerged_reason(r, placement, fits) for r in unplaced},
        pose_graph={"edges": len(edges), "optimised": placement.optimised},
        parameters=params,
        updated_at=time.time(),
    )


def merge_parameters(params: MergeParams, vocab_path, services: dict | None = None) -> dict:
    """`merge`'s parameters in force: its own (`MergeParams`), the vocabulary, the
    aligner's method and the placement's cycle tolerances (and the drift correction's);
    `services`: the services' own, {"place_db": its `GET /config`, "aligner": ...}."""
    from fleetmap.fleet.correct import CorrectionParams

    out = {
        "keyframes": dataclasses.asdict(params.keyframes),
        "vocabulary": str(vocab_path) if vocab_path else "default",
        "max_views": params.views.max_views,
        "voxel_m": params.voxel_m,
        "pcd": params.pcd,
        "correct_drift": params.correct_drift,
        "view_radius_m": params.views.radius_m,
        "view_local_path_m": params.views.local_path_m,  # a refused pair's second views
        "align_method": "default",
        "cycles": dataclasses.asdict(CycleParams()),
    }
    if params.correct_drift:
        out["drift_correction"] = dataclasses.asdict(CorrectionParams())
    return out | (services or {})


def merge_unmerged_reason(robot: str, placement: Placement, fits: list[Fit]) -> str:
    """One line: why `merge` left this robot out."""
    if robot in placement.flagged:
        return placement.flagged[robot]
    mine = [f for f in fits if robot in (f.robot_a, f.robot_b)]
    if any(f.merged for f in mine):
        return "merged with robots that share no aligned place with the reference's group"
    if mine:
        f = mine[-1]
        other = f.robot_a if f.robot_b == robot else f.robot_b
        return f"alignment with {other} refused: {f.reason}"
    return "no verified overlap with another robot"


def graph_of(overlaps: list[dict]) -> list[dict]:
    """The overlap graph of verified (cascade) overlap items, as `GET /map` gives it."""
    acc: dict[tuple[str, str], list[int]] = {}
    for o in overlaps:
        if o.get("source", "cascade") != "cascade":
            continue
        n = acc.setdefault(tuple(sorted((o["robot_a"], o["robot_b"]))), [0, 0, 0])
        n[0], n[1], n[2] = n[0] + 1, max(n[1], o["inliers"]), n[2] + o["inliers"]
    return [
        {"robot_a": a, "robot_b": b, "pairs": n, "best_inliers": best, "total_inliers": total}
        for (a, b), (n, best, total) in sorted(acc.items())
    ]


#: A robot's keys in `fleetmap map`'s report (as `GET /map` gives them).
LIVE_ROBOT_KEYS = ("keyframes", "views", "state", "drift_correction")


def live_report(
    m: dict, place_db: str, overlaps: list[dict], edges: dict, voxel_m: float, served=None
):
    """`fleetmap map`'s report from the live map `m` (`GET /map`), the overlap items of its
    robot pairs, the edges between placed robots, the cloud's voxel size and `served`: the
    place database's parameters in force (its `GET /config`)."""
    return build_report(
        reference=m["reference"],
        source={"job": "map", "place_db": place_db, "live_map_version": m["version"]},
        robots={f["robot"]: {k: f[k] for k in LIVE_ROBOT_KEYS if k in f} for f in m["fleet"]},
        transforms=m["transforms"],
        overlaps=overlaps,
        overlap_graph=m["overlaps"],
        fits=m["pairs"],
        unmerged_reasons={u["robot"]: u["reason"] for u in m["unmerged"]},
        pose_graph={"edges": len(edges), "optimised": None},
        parameters={"voxel_m": voxel_m} | ({} if served is None else {"place_db": served}),
        updated_at=m["updated_at"],
    )
