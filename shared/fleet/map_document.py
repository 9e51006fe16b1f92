"""What `GET /map` serves: the map document (the placement, why a robot is not placed, the
merge worker's pair states and its last word), read from the store through `PlaceDB`, so
any replica answers the same."""

from __future__ import annotations

from fleetmap.fleet.merge_rules import robot_order
from fleetmap.fleet.state import load_states, read_graph, read_placement, read_worker
from fleetmap.fleet.types import transform_to_json

#: A robot's drift correction in `GET /map` (`fleet` items) and report.json (`robots`).
DRIFT_KEYS = ("applied", "moved_median_m", "moved_max_m", "bend_m", "flagged", "rigid_placement")


def map_document(db) -> dict:
    """{"version", "reference", "transforms" (robot: T_ref_robot), "unmerged" [{"robot",
    "reason"}], "robots", "updated_at"} and, for the operator, "fleet" (per robot:
    keyframes, views, state and, once the keyframe graph is solved on this placement, its
    drift correction), "pairs" (the merge worker's pair states), "overlaps" and
    "fleet_graph" (the keyframe graph's figures). A drift-corrected robot's transform is
    its corrected map's best rigid approximation, as in `fleetmap merge`'s report."""
    m = read_placement(db)
    robots = db.robots()
    names = robot_order(db, robots)
    states = load_states(db)
    graph = db.overlap_graph()
    worker = read_worker(db)
    placed, flagged = m.T_ref, m.flagged  # flagged: copies, or fits that disagree
    counts = {r["robot_id"]: r["keyframes"] for r in robots}
    fleet = []
    for r in names:
        n_views = len(db.view_ids(r))
        state = "reference" if r == m.reference else "merged" if r in placed else "unmerged"
        fleet.append({"robot": r, "keyframes": counts.get(r, 0), "views": n_views, "state": state})
    transforms = {r: transform_to_json(T) for r, T in placed.items() if r in counts}
    solved = read_graph(db)
    solved = solved if solved is not None and solved["version"] == m.version else None
    for f in fleet if solved is not None else []:
        if (row := solved["robots"].get(f["robot"])) is not None:
            f["drift_correction"] = {k: row[k] for k in DRIFT_KEYS}
            if row["applied"]:  # the corrected map's best rigid T_ref_R; else placed stands
                transforms[f["robot"]] = row["rigid"]
    return {
        "version": m.version,
        "reference": m.reference,
        "transforms": transforms,
        "unmerged": [
            {
                "robot": f["robot"],
                "reason": flagged.get(f["robot"])
                or unmerged_reason(f, states, graph, placed, worker),
            }
            for f in fleet
            if f["state"] == "unmerged"
        ],
        "robots": names,
        "updated_at": m.updated_at,
        "fleet": fleet,
        "pairs": sorted(states.values(), key=lambda s: (s["robot_a"], s["robot_b"])),
        "overlaps": graph,
        "worker": worker,
    } | ({"fleet_graph": solved["summary"]} if solved is not None else {})


def unmerged_reason(
    robot: dict, states: dict, graph: list[dict], placed: dict, worker: dict | None = None
) -> str:
    """One line: why this robot is not in the map (yet). `worker`: the merge worker's row
    (`read_worker`; None where none has run: a place database without an aligner)."""
    r = robot["robot"]
    if robot["views"] == 0:
        return "its keyframes were posted without RGB-D views: they can be queried, not aligned"
    mine = [s for s in states.values() if r in (s["robot_a"], s["robot_b"])]
    merged = [s for s in mine if s["status"] == "merged"]
    if merged:
        others = sorted({s["robot_a"] if s["robot_b"] == r else s["robot_b"] for s in merged})
        return (
            f"merged with {', '.join(others)}, a group that shares no aligned place with "
            "the reference's"
        )
    verified = [e for e in graph if r in (e["robot_a"], e["robot_b"])]
    if not verified:
        return "no verified overlap with another robot yet"
    refused = [s for s in mine if s["status"] in ("refused", "no_views")]
    if refused:
        last = max(refused, key=lambda s: s["at"])
        other = last["robot_a"] if last["robot_b"] == r else last["robot_b"]
        return (
            f"alignment with {other} refused on {last['evidence']} verified overlaps: "
            f"{last['reason']}; tried again when more overlaps are found"
        )
    if worker is None:  # "pending" for ever said nothing (an outside tester's review)
        return (
            "overlaps found, alignment pending; no merge worker has reported yet (a place "
            "database started without --aligner never aligns)"
        )
    if worker.get("aligner_error"):
        return f"overlaps found; the aligner failed, tried again: {worker['aligner_error']}"
    return "overlaps found, alignment pending"
