"""The live merge worker: the place database aligns robots itself as overlaps appear; it
decides what to align (`LiveMap.due_pairs`, rules in `fleetmap.fleet.merge_rules`) and
places the fleet (`LiveMap.place`, as `fleetmap merge`: `fleetmap.fleet.placement`).

One thread (on PostgreSQL one replica at a time, under an advisory lock) looks at the
verified overlaps of every robot pair once a second. A pair is aligned on new evidence:
first overlaps, more after a refusal, many more (`refine_factor`) since its merge; once the
robots are quiet, a pair with no verified overlap once from the nominated keyframe pairs
(`fleetmap.place.nominate`), again only after either robot gained keyframes. Its views are
the stored RGB-D views near its keyframes, chosen as `fleetmap merge` chooses them, and
refused ones again along both paths near the best overlap (`fleetmap.fleet.live_views`).
A gated result becomes a link (`PlaceDB.add_link`);
pair states and the placement are stored (`fleetmap.fleet.state`): a restart aligns nothing
twice. The worker reads and writes the place database only through `PlaceDB`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass

import numpy as np

from fleetmap.errors import Conflict, FleetmapError
from fleetmap.fleet.live_graph import LiveGraph
from fleetmap.fleet.live_views import StoredViews
from fleetmap.fleet.merge_rules import (
    copier_robots,
    due_order,
    evidence,
    is_due,
    merged_edges,
    new_merge,
    nominated_pairs,
    reference,
    refit_or_kept,
    robot_order,
    whole_map_views,
)
from fleetmap.fleet.placement import place_fleet
from fleetmap.fleet.state import (
    load_states,
    read_placement,
    update_states,
    write_placement,
    write_worker,
)
from fleetmap.fleet.types import (
    DEFAULT_VIEWS,
    Fit,
    PairState,
    Placement,
    pair_key,
    state_transform,
    transform_to_json,
)
from fleetmap.fleet.view_choice import after_second_views
from fleetmap.place.nominate import nominated_overlaps

log = logging.getLogger(__name__)


@dataclass
class LiveParams:
    """When the merge worker aligns a robot pair."""

    poll_s: float = 1.0  # how often the overlaps are looked at
    max_views: int = DEFAULT_VIEWS.max_views  # per robot and pair, as `fleetmap merge`
    first_views: int = 8  # a pair's first fit: 8x8 views, about half the time of 12x12
    retry_min_new: int = 1  # a refused pair: tried again after this many new overlaps
    retry_factor: float = 1.25  # ... and once its overlaps grew by this factor
    retry_backoff_s: float = 2.0  # ... and this long after its attempt, doubled per refusal
    retry_backoff_max_s: float = 120.0
    refine_factor: float = 2.0  # a merged pair: aligned again once its overlaps doubled
    refine_min_new: int = 5  # ... and at least this many are new
    failure_backoff_s: float = 10.0  # after the aligner could not be reached
    parallel: int = 2  # pairs aligned at once (the aligner serves two requests at a time)
    settle_s: float = 5.0  # no keyframe for this long: merged pairs get a last fit
    correct_drift: bool = True  # the keyframe graph over the placed robots (issue 22)
    graph_budget_s: float = 1.0  # closures judged per idle step of the worker at most
    graph_interval_s: float = 5.0  # between the graph's steps on an unchanged placement


class LiveMap:
    """The merge worker. `align(pairs)` is the aligner's `/align` (a list of (RGBDView of
    A, RGBDView of B)) returning its JSON answer: `AlignerClient.align`."""

    def __init__(self, db, align: Callable[[list], dict], params: LiveParams | None = None):
        self.db, self.align, self.params = db, align, params or LiveParams()
        self.views = StoredViews(db)  # the views to align, keyframe poses read once
        self._backoff: dict[str, float] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.failures = 0
        self._robots_placed: tuple = ()  # robots known (and copiers) at the last placement
        self._noted: dict | None = None
        self._aligner_error: str | None = None  # the last failure since the last answer
        self._kf_total, self._kf_changed = -1, time.monotonic()
        self.quiet = False
        self._linker = ThreadPoolExecutor(1, thread_name_prefix="live-link")
        self._leading = True  # False once the store's lock was lost: nothing is stored
        self._same: dict[tuple[int, int], bool] = {}  # keyframe pair -> one picture twice
        self.copiers: dict[str, str] = {}  # robot -> why its keyframes are no evidence
        self._nominated: dict[str, bool] = {}  # pair -> its last attempt was nominated
        self.graph = LiveGraph(
            db, budget_s=self.params.graph_budget_s, interval_s=self.params.graph_interval_s
        )

    # --- the worker thread --------------------------------------------------------------

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="fleetmap-live-map", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self._linker.shutdown(wait=True, cancel_futures=True)

    def _run(self) -> None:
        """Lead the merging while this process holds the store's "live map" lock (always
        on SQLite; one replica at a time on PostgreSQL)."""
        while not self._stop.is_set():
            try:
                with self.db.exclusive("live map") as held:
                    self._lead(held)
            except Conflict:
                pass  # another replica is merging
            except Exception:  # a store or aligner hiccup must not end the worker
                self.failures += 1
                log.exception("live map: merge worker failed; starting again")
            self._stop.wait(self.params.poll_s)

    def _lead(self, held: Callable[[], bool] | None = None) -> None:
        """Keep up to `parallel` pairs aligning at once (the aligner takes two requests
        at a time, one per core); store each result and place the fleet as it comes.
        Stops at once when `held()` says the store's lock was lost (another replica may
        lead now): results still aligning are then dropped, never stored."""
        flying: dict[str, Future] = {}
        self._leading = True
        with ThreadPoolExecutor(self.params.parallel, thread_name_prefix="live-align") as pool:
            while not self._stop.is_set():
                if held is not None and not held():
                    log.warning("live map: the merge lock was lost; no longer leading")
                    self._leading = False
                    return
                for key in [k for k, f in flying.items() if f.done()]:
                    self._finish(key, flying.pop(key))
                states = load_states(self.db)
                due = [d for d in self.due_pairs(states) if pair_key(d[0], d[1]) not in flying]
                for a, b, overlaps in self._next(due, flying):
                    key, n = pair_key(a, b), len(overlaps)
                    log.info("live map: aligning %s-%s on %d verified overlaps", a, b, n)
                    self._nominated[key] = overlaps[0].source == "nominated"
                    flying[key] = pool.submit(self.attempt, a, b, overlaps, states.get(key))
                self._note(flying, len(due))
                if not flying:
                    self._place_new_robots(states)
                if all(self._nominated.get(k) for k in flying):  # none that moves the map
                    self._correct(states)
                wait(list(flying.values()) or [Future()], self.params.poll_s, FIRST_COMPLETED)

    def _next(self, due: list, flying: dict) -> list:
        """Due pairs for the free slots, in order. While a pair that places a new robot is
        aligning, a second pair for the same robot, or a refinement, waits: on two cores it
        would slow the one that grows the map."""
        placed = set(read_placement(self.db).T_ref)
        busy = {r for k in flying for r in k.split("|") if r not in placed}
        out = []
        for a, b, overlaps in due:
            if len(flying) + len(out) >= self.params.parallel:
                break
            joins = {r for r in (a, b) if r not in placed}
            if joins & busy or (busy and not joins):  # refinements wait for new robots too
                continue
            out.append((a, b, overlaps))
            busy |= joins
        return out

    def _finish(self, key: str, future: Future) -> None:
        try:
            result = future.result()
        except Exception as exc:  # the aligner failed: tried again after the backoff
            self.failures += 1
            log.warning("live map: %s", exc)
            self._aligner_error = str(exc)[:300]
            return
        self._aligner_error = None  # it answers again
        if self._store_result(key, result):
            self.place(load_states(self.db))
            self._link(result)

    def _store_result(self, key: str, result: dict) -> bool:
        """Store a pair's new state (compare-and-set), unless a robot of the pair was
        deleted (or deleted and posted again) while it was aligned: False then."""
        if not self._leading:
            return False
        a, b = result["robot_a"], result["robot_b"]
        stale = [self.db.incarnation(r) for r in (a, b)] != result.get("since")
        if stale:
            log.info("live map: %s-%s changed while aligned; result dropped", a, b)
            return False
        update_states(self.db, lambda states: states.__setitem__(key, result))
        return True

    def _link(self, st: PairState) -> None:
        """Register a new merge as a link (its co-visible keyframe pairs become overlaps),
        in the background: placing the robot does not wait for it (12 s for 280 keyframes
        on a busy machine)."""
        if new_merge(st):
            self._linker.submit(self._register, st["robot_a"], st["robot_b"], state_transform(st))

    def _register(self, a: str, b: str, T_a_b: np.ndarray) -> None:
        try:
            self.db.add_link(a, b, T_a_b)
        except Exception:  # a robot deleted meanwhile, the store down: the merge stands
            log.exception("live map: link %s-%s not registered", a, b)

    def _note(self, flying: dict, due: int) -> None:
        """The worker row `GET /map` shows: the pairs aligning and how many wait."""
        work = {"aligning": [k.split("|") for k in flying], "due": max(0, due - len(flying))}
        work["quiet"] = self.quiet  # no keyframe for settle_s: last fits done once idle
        if self._aligner_error is not None:  # `GET /map` says why pairs wait (down?)
            work["aligner_error"] = self._aligner_error
        if work != self._noted:
            write_worker(self.db, work | {"since": time.time()})
            self._noted = work

    def _place_new_robots(self, states: dict) -> None:
        robots = (self.db.robot_count(), sorted(self.copiers))
        if robots != self._robots_placed:  # a new robot or copier: the reference may change
            self.place(states)
            self._robots_placed = robots

    def _correct(self, states: dict) -> None:
        """A step of the keyframe graph (`LiveGraph.step`) while no pair with verified
        evidence is aligning: a nominated pair is mostly refused (15-34 s on the live
        bench), and the graph used to wait for three of them after the last refit."""
        if not self.params.correct_drift or not self._leading:
            return
        placement = read_placement(self.db)
        try:
            self.graph.step(placement, states)
        except FleetmapError as exc:  # a robot deleted meanwhile: the next step starts anew
            log.info("live map: keyframe graph step skipped: %s", exc)
        except Exception:  # never the merging's failure: tried again after the interval
            log.exception("live map: keyframe graph step failed")
            self.graph.hold(placement.version)

    def tick(self) -> bool:
        """One step in the caller's thread: align the most useful pair with new evidence
        and place the fleet again; True if a pair was aligned (else a step of the keyframe
        graph was taken)."""
        states = load_states(self.db)
        due = self.due_pairs(states)
        if not due:
            self._place_new_robots(states)
            self._correct(states)
            return False
        a, b, overlaps = due[0]
        st = self.attempt(a, b, overlaps, states.get(pair_key(a, b)))
        if not self._store_result(pair_key(a, b), st):
            return True
        self.place(load_states(self.db))
        if new_merge(st):
            self._register(a, b, state_transform(st))
        return True

    # --- which pair -------------------------------------------------------------------

    def due_pairs(self, states: dict) -> list[tuple[str, str, list]]:
        """Pairs with new evidence, those that would place a new robot first, then by
        verified overlaps; each with its cascade overlaps."""
        placed = set(read_placement(self.db).T_ref)
        now, due = time.monotonic(), []
        quiet, wall = self._quiet(now), time.time()
        copied: dict[str, dict] = {}  # robot -> {its keyframe: the robot it repeats}
        for e in self.db.overlap_graph():
            a, b = e["robot_a"], e["robot_b"]
            if self._backoff.get(pair_key(a, b), 0.0) > now:
                continue
            overlaps = evidence(self.db, a, b, self._same, copied)
            st = states.get(pair_key(a, b))
            if not overlaps:
                continue
            waits = st is not None and st["status"] == "no_views"
            changed = waits and self._view_counts(a, b) != tuple(st["views"])
            if is_due(st, len(overlaps), self.params, quiet, changed, wall):
                joins = (a in placed) != (b in placed) or not placed
                due.append((due_order(joins, st, len(overlaps), a, b), a, b, overlaps))
        counts = {r["robot_id"]: r["keyframes"] for r in self.db.robots()}
        self.copiers = copiers = copier_robots(copied, counts)
        due = [d for d in due if d[1] not in copiers and d[2] not in copiers]
        if quiet:  # no pair verified: where the bags of words point (issue 21)
            graph = {pair_key(e["robot_a"], e["robot_b"]) for e in self.db.overlap_graph()}
            for a, b in nominated_pairs(states, graph, counts, set(copiers)):
                if overlaps := nominated_overlaps(self.db, a, b):
                    joins = (a in placed) != (b in placed) or not placed
                    due.append(
                        (due_order(joins, states.get(pair_key(a, b)), 0, a, b), a, b, overlaps)
                    )
        return [(a, b, o) for _, a, b, o in sorted(due, key=lambda d: d[0])]

    def _quiet(self, now: float) -> bool:
        """No keyframe arrived for `settle_s` and none waits for overlap detection: the
        evidence will not grow by itself."""
        total = sum(r["keyframes"] for r in self.db.robots())
        if total != self._kf_total:
            self._kf_total, self._kf_changed = total, now
        self.quiet = now - self._kf_changed >= self.params.settle_s and self.db.pending() == 0
        return self.quiet

    def _view_counts(self, a: str, b: str) -> tuple[int, int]:
        return tuple(len(self.db.view_ids(r)) for r in (a, b))

    # --- aligning one pair --------------------------------------------------------------

    def attempt(self, a: str, b: str, overlaps: list, before: PairState | None) -> PairState:
        """Align A and B from their stored views near the verified overlaps; the pair's new
        state (a gated refusal of a merged pair keeps the merge)."""
        st = {"robot_a": a, "robot_b": b, "evidence": len(overlaps), "at": time.time()}
        nominated = bool(overlaps) and overlaps[0].source == "nominated"
        if nominated:  # no verified evidence: one try, with every view, until keyframes grow
            counts = {r["robot_id"]: r["keyframes"] for r in self.db.robots()}
            st |= {"evidence": 0, "nominated": [counts.get(a, 0), counts.get(b, 0)]}
        st["since"] = [self.db.incarnation(r) for r in (a, b)]  # who was aligned
        st["attempts"] = (before or {}).get("attempts", 0) + 1
        ranked = sorted(overlaps, key=lambda o: -o.inliers)
        first = before is None and not nominated
        k = self.params.first_views if first else self.params.max_views
        st["budget"] = k  # views per robot this fit could use
        ids = [
            self.views.choose(a, [o.kf_a for o in ranked], k),
            self.views.choose(b, [o.kf_b for o in ranked], k),
        ]
        if not all(ids):
            missing = [r for r, v in zip((a, b), ids, strict=True) if not v]
            reason = f"no RGB-D view stored near the overlaps for {', '.join(missing)}"
            st["views"] = list(self._view_counts(a, b))
            return st | {"status": "no_views", "reason": reason}
        st["views"] = [len(v) for v in ids]
        fit = self._fit(a, b, ids)
        if not fit.merged and not nominated and (local := self.views.local(a, b, ranked, k, ids)):
            fit = after_second_views(fit, self._fit(a, b, local))  # a map that bends
            if fit.merged:
                st["views"] = [len(v) for v in local]
        if fit.merged:
            log.info("live map: %s-%s merged (%d views each side)", a, b, st["views"][0])
            T_a_b = transform_to_json(fit.T_a_b)
            new = st | fit.state_fields() | {"status": "merged", "transform": T_a_b}
            return refit_or_kept(before, new, lambda: [whole_map_views(self.db, r) for r in (a, b)])
        log.info("live map: %s-%s refused by the gate: %s", a, b, fit.reason)
        if before is not None and before["status"] == "merged":
            keep = {k: st[k] for k in ("evidence", "attempts", "budget", "since")}
            return before | keep | {"last_refusal": fit.reason}
        st["refusals"] = (before or {}).get("refusals", 0) + 1  # its back-off doubles
        return st | fit.state_fields() | {"status": "refused"}

    def _fit(self, a: str, b: str, ids: list[list[int]]) -> Fit:
        """The aligner's answer for A's and B's stored views of keyframes `ids`."""
        views = [self.views.load(x) for x in ids]
        try:
            answer = self.align([(x, y) for x in views[0] for y in views[1]])
        except FleetmapError as exc:  # the aligner down or refusing the request
            self._backoff[pair_key(a, b)] = time.monotonic() + self.params.failure_backoff_s
            raise RuntimeError(f"aligner failed on {a}-{b}: {exc}") from exc
        return Fit.from_json(answer, a, b)

    # --- placing the fleet ---------------------------------------------------------------

    def place(self, states: dict[str, PairState]) -> Placement:
        """Place every robot reachable from the reference through merged pairs; store the
        placement, its version raised only when it changed."""
        names = robot_order(self.db)
        flagged = {r: why for r, why in self.copiers.items() if r in names}
        edges = merged_edges(states, set(names) - set(flagged))
        old = read_placement(self.db)
        counts = {r["robot_id"]: r["keyframes"] for r in self.db.robots()}
        ref = reference(names, edges, counts)
        new = Placement(ref, flagged=flagged)
        if ref is not None:
            new, _ = place_fleet([ref] + [n for n in names if n != ref], edges)
            new.flagged = flagged | new.flagged
        if new.same_as(old):
            return old
        new.version, new.updated_at = old.version + 1, time.time()
        new.optimised = bool(new.optimised)
        write_placement(self.db, new)
        log.info("live map version %d: %d robots placed", new.version, len(new.T_ref))
        return new
