"""The fleet's stored state (the store's `live` rows), read and changed safely: through a
`PlaceDB` (`fleetmap.place.fleet_access`) or, inside the place database, its `Store`.

Two rows matter: "pairs" (the merge worker's `PairState`s, JSON keyed "A|B") and "map" (the
`Placement`); "graph" (the keyframe graph's solution) and "graph_g2o" (that graph as a g2o
file) hold for the "map" version they name. Every change of the pair states is a
compare-and-set (`update_states`): a replica that lost its lock, or a state computed before
a robot was deleted, cannot write over a newer one. Deleting a robot forgets what was
derived from it in the store's delete transaction (`forget_robot`), so a robot id that comes
back starts fresh.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Callable

from fleetmap.fleet.types import PairState, Placement

CAS_TRIES = 100


def load_states(store) -> dict[str, PairState]:
    """The pair states by `pair_key` (`store`: a `PlaceDB` or a `Store`)."""
    raw = store.live_get("pairs")
    return {} if raw is None else json.loads(raw)


def read_placement(store) -> Placement:
    """The stored placement (an empty one before the first)."""
    raw = store.live_get("map")
    return Placement.from_json({} if raw is None else json.loads(raw))


def write_placement(store, placement: Placement) -> None:
    store.live_put("map", json.dumps(placement.to_json()))


def read_graph(store) -> dict | None:
    """The live map's keyframe graph solution (`fleetmap.fleet.live_graph.graph_row`), or
    None before the first."""
    raw = store.live_get("graph")
    return None if raw is None else json.loads(raw)


def write_graph(store, row: dict, g2o: str | None = None) -> None:
    """The solution, and its keyframe graph in g2o's format (`Solution.g2o_text`; None
    where no graph was built) in a row of its own ("graph_g2o", for the same placement
    version): `GET /map` reads the first on every call, the second only when asked for."""
    store.live_put("graph_g2o", json.dumps({"version": row["version"], "g2o": g2o}))
    store.live_put("graph", json.dumps(row))


def read_graph_g2o(store, version: int) -> str | None:
    """The keyframe graph (g2o text) solved on placement `version`, or None where none is."""
    raw = store.live_get("graph_g2o")
    row = None if raw is None else json.loads(raw)
    return row["g2o"] if row is not None and row["version"] == version else None


def read_worker(store) -> dict | None:
    """The merge worker's last word: the pairs it is aligning and how many more wait; None
    before it first ran (or without a worker)."""
    raw = store.live_get("worker")
    return None if raw is None else json.loads(raw)


def write_worker(store, work: dict) -> None:
    store.live_put("worker", json.dumps(work))


def update_states(store, change: Callable[[dict], None]) -> dict:
    """Apply `change` (which edits the states in place) to the stored pair states as a
    compare-and-set, read again and retried if another writer came first. Returns them."""
    for k in range(CAS_TRIES):
        raw = store.live_get("pairs")
        states = {} if raw is None else json.loads(raw)
        change(states)
        if store.live_cas("pairs", raw, json.dumps(states)):
            return states
        time.sleep(random.uniform(0, 0.002 * (k + 1)))  # jitter: racing writers spread out
    raise RuntimeError("live map: the pair states kept changing under this writer")


def forget_robot(pairs_raw: str | None, map_raw: str | None, name: str) -> tuple:
    """The "pairs" and "map" rows without what was derived from robot `name`: its pair
    states go, and so does every placement that depended on it (the robot, and every robot
    no longer joined to the reference by a merged pair; all if it was the reference). The
    worker places the fleet again. (new pairs, new map), each None where nothing changed."""
    states = {} if pairs_raw is None else json.loads(pairs_raw)
    kept = {k: s for k, s in states.items() if name not in (s["robot_a"], s["robot_b"])}
    new_pairs = json.dumps(kept) if len(kept) != len(states) else None
    m = Placement.from_json({} if map_raw is None else json.loads(map_raw))
    if name not in m.T_ref and m.reference != name and name not in m.flagged:
        return new_pairs, None
    m.flagged = {r: why for r, why in m.flagged.items() if r != name}
    reach = _reachable(m.reference, kept) if m.reference != name else set()
    m.T_ref = {r: T for r, T in m.T_ref.items() if r in reach}
    m.links = [e for e in m.links if e[0] in reach and e[1] in reach]
    if not m.T_ref:
        m.reference = None
    m.version, m.updated_at = m.version + 1, time.time()
    return new_pairs, json.dumps(m.to_json())


def _reachable(ref: str | None, states: dict) -> set[str]:
    """Robots joined to `ref` through merged pairs."""
    seen, todo = {ref}, [ref]
    while todo:
        r = todo.pop()
        for s in states.values():
            if s["status"] == "merged" and r in (s["robot_a"], s["robot_b"]):
                other = s["robot_b"] if s["robot_a"] == r else s["robot_a"]
                if other not in seen:
                    seen.add(other)
                    todo.append(other)
    return seen
