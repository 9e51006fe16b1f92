"""One merge leader at a time, and no lost pair-state update (issue 26.7): on a real
PostgreSQL server restarted under a replica that holds the merge lock, and with writers
racing on both backends."""

from __future__ import annotations

import json
import threading

import pytest

from fleetmap.fleet.merge_worker import LiveMap
from fleetmap.fleet.state import load_states, update_states
from fleetmap.place.postgres import PostgresStore
from fleetmap.place.sqlite import SQLiteStore
from tests import pg

VOCAB = "test-vocabulary"


@pytest.fixture
def cluster():
    """A PostgreSQL server of this test's own: it is restarted."""
    if not pg.available():
        pytest.skip(f"PostgreSQL binaries not found in {pg.PG_BIN}")
    c = pg.Cluster().start()
    yield c
    c.remove()


def test_a_replica_that_loses_the_merge_lock_stops_leading(cluster):
    """`pg_ctl restart -m fast` while replica one leads: its session and advisory lock are
    gone; it sees so at its next round and stops (no result of it stored), while replica
    two takes the lock."""
    url = cluster.database()
    one, two = PostgresStore(url, VOCAB), PostgresStore(url, VOCAB)
    try:
        with one.exclusive("live map") as held:
            assert held()
            with pytest.raises(Exception, match="another replica"):
                with two.exclusive("live map"):
                    pass
            cluster.stop("fast")
            cluster.start()
            assert not held()
            with two.exclusive("live map") as held_two:
                assert held_two()
                live = LiveMap(None, lambda pairs: pytest.fail("aligned without the lock"))
                live._lead(held)  # replica one's worker, one round after the restart
                assert live._leading is False
                assert live._store_result("A|B", {"robot_a": "A", "robot_b": "B"}) is False
    finally:
        one.close()
        two.close()


@pytest.fixture(params=["sqlite", "postgres"])
def store(request, tmp_path):
    if request.param == "postgres":
        s = PostgresStore(request.getfixturevalue("pg_url"), VOCAB)
    else:
        s = SQLiteStore(tmp_path / "place.db", VOCAB)
    yield s
    s.close()


def test_pair_state_updates_are_never_lost(store):
    """Eight writers each record 25 attempts of one pair and a state of their own: all
    200 attempts and 8 states are there (before: 5 alignments recorded as 3 attempts)."""

    def bump(k: int) -> None:
        for _ in range(25):

            def change(states: dict) -> None:
                st = states.setdefault("A|B", {"robot_a": "A", "robot_b": "B", "attempts": 0})
                st["attempts"] += 1
                states[f"A|R{k}"] = {"robot_a": "A", "robot_b": f"R{k}", "status": "refused"}

            update_states(store, change)

    writers = [threading.Thread(target=bump, args=(k,)) for k in range(8)]
    for w in writers:
        w.start()
    for w in writers:
        w.join()
    states = load_states(store)
    assert states["A|B"]["attempts"] == 200 and len(states) == 9
    assert json.loads(store.live_get("pairs")) == states
