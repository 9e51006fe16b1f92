"""The live map's stored state (the store's `live` rows), read and changed safely.

Two rows matter: "pairs" (the merge worker's pair states, JSON keyed "A|B") and "map" (the
placement). Every change of the pair states is a compare-and-set (`update_states`): a
replica that lost its lock, or a state computed before a robot was deleted, cannot write
over a newer one. Deleting a robot forgets what was derived from it in the store's delete
transaction (`forget_robot`), so a robot id that comes back starts fresh.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Callable

CAS_TRIES = 100


def pair_key(a: str, b: str) -> str:
    return "|".join(sorted((a, b)))


def load_states(store) -> dict:
    raw = store.live_get("pairs")
    return {} if raw is None else json.loads(raw)


def read_placement(store) -> dict:
    raw = store.live_get("map")
    return {} if raw is None else json.loads(raw)


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
    m = {} if map_raw is None else json.loads(map_raw)
    placed = m.get("transforms", {})
    ref = m.get("reference")
    flagged = m.get("flagged", {})
    if name not in placed and ref != name and name not in flagged:
        return new_pairs, None
    m["flagged"] = {r: why for r, why in flagged.items() if r != name}
    reach = _reachable(ref, kept) if ref != name else set()
    m["transforms"] = {r: T for r, T in placed.items() if r in reach}
    m["edges"] = [e for e in m.get("edges", []) if e[0] in reach and e[1] in reach]
    if not m["transforms"]:
        m["reference"] = None
    m |= {"version": m.get("version", 0) + 1, "updated_at": time.time()}
    return new_pairs, json.dumps(m)


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


def incarnation(store, name: str) -> int | None:
    """Which life of robot `name` this is: its first keyframe id (ids are never reused,
    so a robot deleted and posted again has another); None for an unknown robot."""
    code = store.robot_code(name)
    ids = [] if code is None else store.robot_keyframe_ids(code)
    return min(ids) if ids else None
