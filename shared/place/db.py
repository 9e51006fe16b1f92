"""The place database: a store (durable state), the in-memory place index, the overlap
worker and the codebook's retraining, composed.

On start the index is rebuilt from the store's small per-keyframe columns (GIST and BoW);
full frames (local features) stay in storage until a candidate needs them. Overlaps between
robots are found incrementally: each new keyframe is queued, and the worker runs the cascade
against the other robots' keyframes and records the verified winner per robot. Keyframes
not yet processed when the process stopped are queued again on start, so a crash loses no
overlap either.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np

from fleetmap.errors import BadInput, UnknownKeyframe, UnknownRobot
from fleetmap.frame import Frame, check_robot_id, decode
from fleetmap.geometry import check_transform, invert
from fleetmap.place.cascade import run_cascade
from fleetmap.place.fleet_access import FleetAccess
from fleetmap.place.index import PlaceIndex
from fleetmap.place.links import LinkOverlaps, pair_link_rows
from fleetmap.place.replica import ClaimWorker, Follower
from fleetmap.place.retrain import CodebookUpkeep
from fleetmap.place.store import Pending, Store, open_store
from fleetmap.place.types import (
    DEFAULT_CASCADE,
    CascadeParams,
    CascadeResult,
    Filter,
    Overlap,
    RetrainPolicy,
)
from fleetmap.place.worker import OverlapWorker
from fleetmap.view import MAX_VIEW_PIXELS, check_view
from fleetmap.vocabulary import Vocabulary

log = logging.getLogger(__name__)


class PlaceDB(FleetAccess):
    """Keyframes of a fleet, their place index and the overlaps found between robots; what
    the fleet level reads and keeps here is `FleetAccess`'s.

    `store` is where the data lives, as `open_store` takes it (a SQLite file or folder, the
    embedded default, or a postgresql:// URL: replicas over one database), or a `Store`."""

    def __init__(
        self,
        store: str | Path | Store,
        vocabulary: Vocabulary,
        params: CascadeParams = DEFAULT_CASCADE,
        retrain: RetrainPolicy | None = None,
        background: bool = True,
        defer_detection: bool = False,
        detect_threads: int = 1,
    ):
        if isinstance(store, str | Path):
            store = open_store(store, vocabulary.vocab_id)
        self.store = store
        self.path = store.path
        self.vocabulary = vocabulary
        self.params = params
        self.retrain_policy = retrain or RetrainPolicy()
        self._closed = False
        book = store.codebook()
        self.index = PlaceIndex(
            vocabulary.gist_centroids if book is None else book, vocabulary.n_words
        )
        self.shared = store.shared
        self.follower = Follower(store, self.index) if self.shared else None
        if self.shared:
            self.worker = ClaimWorker(store, self._claimed)
        else:
            self.worker = OverlapWorker(self.process, detect_threads)
        self._links = LinkOverlaps(store, self.load_frame)
        self.upkeep = CodebookUpkeep(self.retrain_policy, self.index, store, self.follower)
        self._load()
        self._detecting = threading.Lock()
        self._started = not background  # without a background worker: `process_pending`
        if background and self.follower is not None:
            self.follower.start()  # the index follows the other replicas' commits
        if not defer_detection:
            self.start_detection()

    def start_detection(self) -> None:
        """Detect the queued keyframes' overlaps in the background from now on (once; a
        database opened with `defer_detection` holds them until this is called)."""
        with self._detecting:
            if self._started:
                return
            self._started = True
            self.worker.start()

    def _load(self) -> None:
        t, pending = time.perf_counter(), []
        if self.follower is not None:
            self.follower.catch_up()
            log.info("place index rebuilt from %s: %d keyframes", self.store.where, len(self.index))
            return
        for rows in self.store.index_rows():
            self.index.add_many(
                rows.ids, rows.robots, rows.stamps, rows.gists, rows.bow_ids, rows.bow_counts
            )
            pending += rows.unprocessed
        for kf in pending:
            self.worker.put(kf)
        log.info(
            "place index rebuilt: %d keyframes of %d robots in %.1f s (%d to process)",
            len(self.index),
            self.store.robot_count(),
            time.perf_counter() - t,
            len(pending),
        )

    @property
    def startup_warning(self) -> str:
        return self.store.startup_warning

    def _code(self, name: str) -> int:
        code = self.store.robot_code(name)
        if code is None:
            raise UnknownRobot(f"Unknown robot {name!r}")
        return code

    # --- keyframes ------------------------------------------------------------------

    def add_keyframe(
        self, robot_id: str, data: bytes, view: dict[str, bytes] | None = None
    ) -> tuple[int, bool]:
        """Store one encoded frame for robot_id, with its RGB-D view if given ({"rgb",
        "depth"}: `fleetmap.view`); returns (keyframe id, newly created).

        Re-sending the identical frame is idempotent; a different frame at the same
        stamp is a Conflict. Returns only once the keyframe is durably committed.
        """
        return self.add_keyframes(robot_id, [data], [view])[0]

    def add_keyframes(self, robot_id: str, datas: list[bytes], views=None) -> list[tuple]:
        """Store encoded frames (and views) of one robot durably; (id, created) for each."""
        check_robot_id(robot_id)
        items = [Pending(robot_id, self._check(robot_id, d), bytes(d)) for d in datas]
        for it, view in zip(items, views or [], strict=False):
            it.view = None if view is None else check_view(it.frame, view, MAX_VIEW_PIXELS)
        self.store.add_frames(items, self._committed)
        for it in items:
            if it.error is not None:
                raise it.error
        return [it.result for it in items]

    def _check(self, robot_id: str, data: bytes) -> Frame:
        frame = decode(data)
        if frame.robot_id != robot_id:
            raise BadInput(f"Frame is of robot {frame.robot_id!r}, posted for {robot_id!r}")
        self._check_vocabulary(frame)
        if len(frame.gist) != self.index.dim:
            raise BadInput(f"Expected a GIST of {self.index.dim} values, got {len(frame.gist)}")
        if len(frame.bow_ids) and int(frame.bow_ids.max()) >= self.vocabulary.n_words:
            raise BadInput(
                f"BoW word id {int(frame.bow_ids.max())} outside the "
                f"{self.vocabulary.n_words}-word vocabulary"
            )
        return frame

    def _check_vocabulary(self, frame: Frame) -> None:
        if frame.vocab_id != self.vocabulary.vocab_id:
            raise BadInput(
                f"Frame BoW is over vocabulary {frame.vocab_id!r}, this database "
                f"uses {self.vocabulary.vocab_id!r}"
            )

    def _committed(self, added: list[Pending]) -> None:
        """Newly stored keyframes: into the index, then the worker's queue (a shared store:
        the index catches up with every replica's commits, the queue is the store's)."""
        if self.follower is not None:
            self.follower.catch_up(keyframes_only=True)
            self.upkeep.maybe(len(added))
            return
        self.index.add_many(
            [it.result[0] for it in added],
            [self.store.robot_code(it.robot_id) for it in added],
            [it.frame.stamp for it in added],
            np.stack([it.frame.gist for it in added]),
            [it.frame.bow_ids for it in added],
            [it.frame.bow_counts for it in added],
        )
        for it in added:
            self.worker.put(it.result[0])
        self.upkeep.maybe(len(added))

    def frame_bytes(self, kf_id: int) -> bytes:
        """The stored encoded frame of a keyframe."""
        return self.store.frame_bytes(kf_id)

    def load_frame(self, kf_id: int) -> Frame:
        """The full stored frame of a keyframe (local features included)."""
        return decode(self.store.frame_bytes(kf_id))

    def keyframe_info(self, kf_id: int) -> dict:
        return self.store.keyframe_info(kf_id)

    def view_bytes(self, kf_id: int) -> tuple[bytes, bytes]:
        """A keyframe's stored (colour, depth) images; UnknownKeyframe without a view."""
        view = self.store.view_bytes(kf_id)
        if view is None:
            self.store.keyframe_info(kf_id)  # UnknownKeyframe if there is no such keyframe
            raise UnknownKeyframe(f"Keyframe {kf_id} was posted without its RGB-D view")
        return view

    # --- queries --------------------------------------------------------------------

    def robot_name(self, code: int) -> str | None:
        """The robot's name; None once it has been deleted (a query may race a delete)."""
        return self.store.robot_name(code)

    def robots(self) -> list[dict]:
        return self.store.robots()

    def keyframes(self, robot_id: str, offset: int = 0, limit: int = 1000) -> list[dict]:
        return self.store.keyframes(self._code(robot_id), offset, limit)

    def make_filter(
        self, robot: str | None = None, exclude_robot: str | None = None, max_stamp=None
    ) -> Filter:
        excluded = None if exclude_robot is None else self.store.robot_code(exclude_robot)
        return Filter(
            robots=None if robot is None else {self._code(robot)},
            exclude_robots=set() if excluded is None else {excluded},
            max_stamp=max_stamp,
        )

    def query(self, frame: Frame, flt: Filter | None = None) -> CascadeResult:
        """The cascade's answer for one frame against the stored keyframes."""
        self._check_vocabulary(frame)
        return run_cascade(frame, self.index, self.load_frame, self.params, flt)

    def overlaps(self, robot_a: str, robot_b: str) -> list[Overlap]:
        """Verified keyframe pairs between two robots, oriented a -> b, by stamp of a; a pair
        each keyframe found as the other's winner once, with the larger count of inliers."""
        ra, rb = self._code(robot_a), self._code(robot_b)
        out: dict[tuple, Overlap] = {}
        for r in self.store.overlap_rows(ra, rb):
            ka, sa, kb, sb = r.kf_a, r.stamp_a, r.kf_b, r.stamp_b
            if r.robot_a != ra:
                ka, sa, kb, sb = kb, sb, ka, sa
            o = Overlap(robot_a, ka, sa, robot_b, kb, sb, r.inliers, r.matches, r.source)
            if (ka, kb, r.source) not in out or out[(ka, kb, r.source)].inliers < r.inliers:
                out[(ka, kb, r.source)] = o
        return sorted(out.values(), key=lambda o: (o.stamp_a, o.stamp_b))

    def pending(self) -> int:
        """Keyframes still waiting for overlap detection."""
        return self.worker.pending()

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every queued keyframe is processed; False on timeout."""
        return self.worker.wait_idle(timeout)

    def ping(self) -> bool:
        """The storage answers a trivial read."""
        return self.store.ping()

    def stats(self) -> dict:
        sizes = self.index.cluster_sizes()
        return {
            "keyframes": len(self.index),
            "robots": self.store.robot_count(),
            "pending": self.pending(),
            "clusters": int(len(sizes)),
            "cluster_mean": float(sizes.mean()) if len(sizes) else 0.0,
            "cluster_max": int(sizes.max()) if len(sizes) else 0,
            "nonempty_clusters": int(np.count_nonzero(sizes)),
            "overlaps": self.store.overlap_total(),
            "vocab_id": self.vocabulary.vocab_id,
            "db_path": str(self.path) if self.path else f"postgresql://{self.store.where}",
            "db_bytes": self.store.size_bytes(),
            "storage_errors": self.store.storage_errors,
            "worker_failures": self.worker.failures,
            "parked": dict(self.worker.parked),
            "startup_warning": self.startup_warning,
        }

    # --- administration --------------------------------------------------------------

    def delete_robot(self, robot_id: str) -> int:
        """Delete a robot, its keyframes and its overlaps; returns keyframes removed."""
        return self.store.delete_robot(self._code(robot_id), self.index.remove)

    def retrain(self, n_clusters: int | None = None) -> dict:
        """k-means the coarse codebook anew from the stored GISTs and swap the index in;
        queries and ingest go on meanwhile (thesis Fig. 2.12: uneven clusters)."""
        return self.upkeep.retrain(n_clusters)

    def needs_retrain(self) -> bool:
        return self.upkeep.needed()

    # --- links: map alignments registered by the aligner --------------------------------

    def add_link(self, robot_a: str, robot_b: str, T_a_b: np.ndarray) -> int:
        """Register a map alignment (B's map frame into A's, from a gated aligner result)
        and record, as overlaps with source "link", each keyframe's most co-visible
        keyframe of the other robot under it (`fleetmap.place.links`). Replaces the pair's
        earlier link. Returns the number of link overlaps recorded."""
        T = check_transform(T_a_b, "A link's transform")
        if robot_a == robot_b:
            raise BadInput("A link joins two different robots")
        ra, rb = self._code(robot_a), self._code(robot_b)
        if ra > rb:  # one row per robot pair
            ra, rb, T = rb, ra, invert(T)
        rows = pair_link_rows(self.store, self.load_frame, ra, rb, T)
        n = self.store.put_link(ra, rb, T, rows)
        log.info("link %s-%s registered: %d co-visible keyframe pairs", robot_a, robot_b, n)
        return n

    def links(self) -> list[dict]:
        """Registered map alignments: {robot_a, robot_b, transform (B into A), created}."""
        out = []
        for a, b, T, created in self.store.links():
            names = self.store.robot_name(a), self.store.robot_name(b)
            if None not in names:
                out.append(
                    {"robot_a": names[0], "robot_b": names[1], "transform": T.tolist()}
                    | {"created": created}
                )
        return out

    # --- overlap worker ---------------------------------------------------------------

    def process(self, kf_id: int) -> list[Overlap]:
        """Find and record this keyframe's verified winner in each other robot."""
        found = self._detect(kf_id)
        if found is None:
            return []
        code, winners, links, overlaps = found
        if not self.store.record_overlaps(kf_id, code, winners, links):
            return []  # a keyframe was deleted meanwhile
        return overlaps

    def _claimed(self, kf_id: int) -> tuple | None:
        """A keyframe claimed from a shared store's queue: detect once the index holds
        every keyframe committed before it; (code, winners, link rows) to record."""
        if self.index.last_id < kf_id:
            self.follower.catch_up()
        found = self._detect(kf_id)
        return None if found is None else found[:3]

    def _detect(self, kf_id: int) -> tuple | None:
        """(robot code, winner rows, link rows, overlaps) of one keyframe: its verified
        winner in each other robot; None for a keyframe deleted meanwhile."""
        try:
            frame = self.load_frame(kf_id)
        except UnknownKeyframe:
            return None
        code = self.store.robot_code(frame.robot_id)
        if code is None:
            return None
        flt = Filter(exclude_robots={code})
        result = run_cascade(frame, self.index, self.load_frame, self.params, flt)
        best = {}
        for c in result.verified:  # most inliers first: the first per robot wins
            best.setdefault(c.robot_code, c)
        winners = [
            (c.kf_id, c.robot_code, c.verification.inliers, c.verification.matches)
            for c in best.values()
        ]
        links = self._links.for_keyframe(kf_id, frame, code)
        overlaps = [
            Overlap(
                frame.robot_id,
                kf_id,
                frame.stamp,
                self.store.robot_name(c.robot_code) or "?",
                c.kf_id,
                c.stamp,
                c.verification.inliers,
                c.verification.matches,
            )
            for c in best.values()
        ]
        return code, winners, links, overlaps

    def process_pending(self) -> None:
        """Synchronously process queued keyframes (for use without the background worker)."""
        self.worker.process_pending()

    def close(self, drain_timeout: float = 10.0) -> None:
        """Refuse new writes, let the worker finish the keyframe it is on (at most
        `drain_timeout`; unprocessed keyframes are queued again at the next start), then
        close the store cleanly."""
        self.store.refuse_writes()
        if self.follower is not None:
            self.follower.stop()
        self.worker.stop(drain_timeout)
        self.store.close()
