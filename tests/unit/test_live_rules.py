"""The merge worker's rules (issue 26.6): a pair that keeps failing costs a bounded number
of attempts however fast its robots post, due pairs take turns, and the reference is not
won by arriving first."""

from __future__ import annotations

from fleetmap.fleet.merge_rules import backoff_s, due_order, is_due, reference
from fleetmap.fleet.merge_worker import LiveParams

P = LiveParams()


def refused(evidence: int, refusals: int, at: float) -> dict:
    return {"status": "refused", "evidence": evidence, "refusals": refusals, "at": at}


def attempts_by_a_flooding_robot(seconds: int, new_per_second: int) -> int:
    """Attempts a pair gets whose robot adds overlaps every second and is always refused
    (the worker polls once a second)."""
    st, n, tries = None, 10, 0
    for now in range(seconds):
        n += new_per_second
        if is_due(st, n, P, False, False, float(now)):
            tries += 1
            st = refused(n, (st or {}).get("refusals", 0) + 1, float(now))
    return tries


def test_a_pair_that_keeps_failing_backs_off():
    assert backoff_s(refused(10, 1, 0), P) == P.retry_backoff_s
    assert backoff_s(refused(10, 30, 0), P) == P.retry_backoff_max_s
    # before: due again on every single new overlap, i.e. every poll (170 in 170 s)
    assert attempts_by_a_flooding_robot(170, 1) <= 10
    assert attempts_by_a_flooding_robot(600, 50) <= 12  # more copies buy nothing
    st = refused(100, 1, 0.0)
    assert not is_due(st, 101, P, False, False, 100.0)  # one more overlap: not new evidence
    assert is_due(st, 125, P, False, False, 100.0)
    assert not is_due(st, 125, P, False, False, 1.0)  # within the back-off


def test_due_pairs_take_turns():
    """The pair tried longest ago goes first, whatever the evidence of the others."""
    keys = sorted(
        [
            due_order(True, refused(500, 4, 900.0), 700, "A", "evil"),
            due_order(True, None, 3, "A", "B"),
            due_order(True, refused(20, 1, 100.0), 30, "B", "C"),
        ]
    )
    assert [k[4:] for k in keys] == [("A", "B"), ("B", "C"), ("A", "evil")]
    assert due_order(False, None, 3, "A", "B") > due_order(True, refused(1, 9, 9e9), 1, "X", "Y")


def test_verified_pairs_go_before_nominated_ones():
    """A merged pair's last fit (verified evidence) before a pair the bags of words alone
    nominate, even one that would place a new robot and was never tried."""
    merged = {"status": "merged", "evidence": 3, "at": 9e9}
    last_fit = due_order(False, merged, 5, "A", "B")
    nominated = due_order(True, None, 0, "A", "D")
    assert last_fit < nominated
    assert due_order(True, None, 1, "C", "D") < last_fit  # a new robot on verified evidence


def test_the_reference_is_not_won_by_arriving_first():
    names = ["evil", "A", "B"]  # evil arrived first
    edges = {("A", "B"): {}, ("A", "evil"): {}}
    counts = {"evil": 5, "A": 300, "B": 250}
    assert reference(names, edges, counts) == "A"
    assert reference(names, {("A", "B"): {}}, counts | {"evil": 900}) == "A"  # not in the group
    assert reference(["B", "A"], {}, {"A": 3, "B": 3}) == "A"  # ties by name
