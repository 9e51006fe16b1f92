"""The in-memory place index: GIST vectors in a faiss IVF index (float16), bags of words in
CSR form and their inverted file (`postings`), keyed by keyframe id. About 4 KB per
keyframe; local features stay in storage. The global stage of the cascade (thesis
Algorithm 3), the inverted-file stage and the BoW distances run here."""

from __future__ import annotations

import logging
import threading
import time

import faiss
import numpy as np

from fleetmap.errors import BadInput
from fleetmap.place.postings import Grow as _Grow
from fleetmap.place.postings import Postings
from fleetmap.place.types import Candidate, CascadeParams, Filter, Stage

log = logging.getLogger(__name__)


class PlaceIndex:
    """GIST IVF index plus bags of words in CSR form, keyed by keyframe id (increasing)."""

    def __init__(self, codebook: np.ndarray, n_words: int):
        self.dim = codebook.shape[1]
        self.n_words = n_words
        self._lock = threading.RLock()
        self.ids = _Grow(np.int64)
        self.robots = _Grow(np.int32)
        self.stamps = _Grow(np.float64)
        self.alive = _Grow(np.bool_)
        self.gists = _Grow(np.float16, self.dim)
        self.bow_ptr = _Grow(np.int64)
        self.bow_ptr.extend(np.zeros(1, np.int64))
        self.bow_ids = _Grow(np.uint32)
        self.bow_counts = _Grow(np.uint16)
        self.postings = Postings(n_words)
        self.n_alive = 0
        self.ivf = self._make_ivf(codebook)

    def _make_ivf(self, codebook: np.ndarray) -> faiss.IndexIVFScalarQuantizer:
        codebook = np.ascontiguousarray(codebook, dtype=np.float32)
        quantizer = faiss.IndexFlatL2(self.dim)
        quantizer.add(codebook)
        ivf = faiss.IndexIVFScalarQuantizer(
            quantizer, self.dim, len(codebook), faiss.ScalarQuantizer.QT_fp16, faiss.METRIC_L2
        )
        ivf.is_trained = True  # the coarse centroids are given; fp16 needs no training
        ivf.make_direct_map(False)
        return ivf

    @property
    def codebook(self) -> np.ndarray:
        return self.ivf.quantizer.reconstruct_n(0, self.ivf.nlist)

    def __len__(self) -> int:
        return self.n_alive

    def add(
        self,
        kf_id: int,
        robot: int,
        stamp: float,
        gist: np.ndarray,
        bow_ids: np.ndarray,
        bow_counts: np.ndarray,
    ) -> None:
        """Add one keyframe; ids must increase (SQLite rowids do)."""
        self.add_many(
            np.array([kf_id]),
            np.array([robot]),
            np.array([stamp]),
            gist.reshape(1, -1),
            [bow_ids],
            [bow_counts],
        )

    def add_many(self, kf_ids, robots, stamps, gists, bow_ids, bow_counts) -> None:
        gists = np.asarray(gists, dtype=np.float16).reshape(-1, self.dim)
        kf_ids = np.asarray(kf_ids, dtype=np.int64)
        with self._lock:
            if self.ids.n and len(kf_ids) and kf_ids[0] <= self.ids.view[-1]:
                raise BadInput(f"keyframe ids must increase: {kf_ids[0]} after {self.ids.view[-1]}")
            first_slot = self.ids.n
            self.ids.extend(kf_ids)
            self.robots.extend(np.asarray(robots, np.int32))
            self.stamps.extend(np.asarray(stamps, np.float64))
            self.alive.extend(np.ones(len(kf_ids), bool))
            self.gists.extend(gists)
            lengths = np.array([len(b) for b in bow_ids], dtype=np.int64)
            self.bow_ptr.extend(self.bow_ptr.view[-1] + np.cumsum(lengths))
            if len(bow_ids):
                self.bow_ids.extend(np.concatenate(bow_ids).astype(np.uint32))
                self.bow_counts.extend(np.concatenate(bow_counts).astype(np.uint16))
                new = slice(self.bow_ids.n - int(lengths.sum()), self.bow_ids.n)
                self.postings.add(
                    first_slot, lengths, self.bow_ids.view[new], self.bow_counts.view[new]
                )
            self.ivf.add_with_ids(gists.astype(np.float32), kf_ids)
            self.n_alive += len(kf_ids)

    def remove(self, kf_ids: np.ndarray) -> int:
        """Tombstone keyframes and drop them from the IVF lists; returns how many."""
        kf_ids = np.asarray(kf_ids, dtype=np.int64)
        with self._lock:
            slots = self._slots(kf_ids)
            slots = slots[self.alive.view[slots]]
            self.alive.buf[slots] = False
            self.n_alive -= len(slots)
            if len(slots):
                self.ivf.remove_ids(faiss.IDSelectorBatch(self.ids.view[slots]))
                self.postings.remove(self.alive.view)
            return len(slots)

    def _slots(self, kf_ids: np.ndarray) -> np.ndarray:
        """Buffer positions of the known ids among kf_ids."""
        ids = self.ids.view
        s = np.searchsorted(ids, kf_ids)
        ok = s < len(ids)
        ok[ok] = ids[s[ok]] == kf_ids[ok]
        return s[ok]

    def cluster_sizes(self) -> np.ndarray:
        """Keyframes per coarse cluster, shape (n_clusters,)."""
        inv = self.ivf.invlists
        return np.array([inv.list_size(i) for i in range(self.ivf.nlist)])

    def retrain(self, n_clusters: int, seed: int = 0) -> np.ndarray:
        """New k-means codebook over the stored GISTs and a rebuilt IVF, swapped in at once.

        Queries keep using the old index until the swap; returns the new cluster sizes.
        """
        from fleetmap.vocabulary import kmeans

        with self._lock:
            gists = self.gists.view[self.alive.view].astype(np.float32)
        if len(gists) < n_clusters:
            raise BadInput(f"{len(gists)} keyframes cannot make {n_clusters} clusters")
        return self.set_codebook(kmeans(gists, n_clusters, seed=seed))

    def set_codebook(self, codebook: np.ndarray) -> np.ndarray:
        """Rebuild the IVF over these coarse centroids and swap it in (queries use the old
        one meanwhile); returns the new cluster sizes."""
        with self._lock:
            alive = self.alive.view.copy()
            gists = self.gists.view[alive].astype(np.float32)
            ids = self.ids.view[alive].copy()
        ivf = self._make_ivf(codebook)
        ivf.add_with_ids(gists, ids)
        with self._lock:
            # keyframes added or removed while it was built
            n_before = len(alive)
            late = np.flatnonzero(self.alive.view[n_before:]) + n_before
            if len(late):
                ivf.add_with_ids(self.gists.view[late].astype(np.float32), self.ids.view[late])
            gone = ~self.alive.view[:n_before] & alive
            if gone.any():
                ivf.remove_ids(faiss.IDSelectorBatch(self.ids.view[:n_before][gone]))
            self.ivf = ivf
            return self.cluster_sizes()

    def remove_robot(self, robot: int) -> int:
        """Tombstone every keyframe of one robot code; returns how many."""
        with self._lock:
            slots = np.flatnonzero((self.robots.view == robot) & self.alive.view)
            return self.remove(self.ids.view[slots])

    @property
    def last_id(self) -> int:
        """The largest keyframe id ever added (0 if none)."""
        with self._lock:
            return int(self.ids.view[-1]) if self.ids.n else 0

    # --- cascade stages -------------------------------------------------------------

    def global_stage(
        self, gist: np.ndarray, p: CascadeParams, flt: Filter
    ) -> tuple[list[Candidate], list[Stage]]:
        """m nearest clusters, then the GIST threshold and the cap."""
        q = np.asarray(gist, dtype=np.float32).reshape(1, -1)
        if q.shape[1] != self.dim:
            raise BadInput(f"Expected a GIST of {self.dim} values, got {q.shape[1]}")
        t0 = time.perf_counter()
        with self._lock:
            ivf = self.ivf
            m = min(p.m_clusters, ivf.nlist)
            _, lists = ivf.quantizer.search(q, m)
            in_clusters = int(sum(ivf.invlists.list_size(int(c)) for c in lists[0] if c >= 0))
            ivf.nprobe = m
            lims, d2, found = ivf.range_search(q, p.gist_threshold**2)
            d2, found = d2[: int(lims[1])], found[: int(lims[1])]
            slots = np.searchsorted(self.ids.view, found)
            robots = self.robots.view[slots]
            stamps = self.stamps.view[slots]
        t1 = time.perf_counter()
        idx = np.flatnonzero(flt.mask(robots, stamps))
        idx = idx[np.argsort(d2[idx], kind="stable")][: p.max_candidates]
        dist = np.sqrt(np.maximum(d2[idx], 0))
        cands = [
            Candidate(int(found[i]), int(robots[i]), float(stamps[i]), float(d))
            for i, d in zip(idx, dist, strict=True)
        ]
        t2 = time.perf_counter()
        return cands, [
            Stage("clusters", in_clusters, 1000 * (t1 - t0) / 2),
            Stage("gist_threshold", len(cands), 1000 * ((t1 - t0) / 2 + t2 - t1)),
        ]

    def word_stage(
        self,
        query_bow: tuple[np.ndarray, np.ndarray],
        gist: np.ndarray,
        p: CascadeParams,
        flt: Filter,
        known: list[int],
    ) -> tuple[list[Candidate], Stage]:
        """Inverted file: among the keyframes holding one of the query's `p.ivf_words` most
        informative words (tf-idf), those passing the filter and not `known` (the GIST
        stage's candidates), the `p.ivf_candidates` of highest Bhattacharyya coefficient
        over those words. The stage keeps both sources' candidates."""
        t0 = time.perf_counter()
        q_ids, q_counts = query_bow
        if p.ivf_candidates <= 0 or len(q_ids) == 0 or np.sum(q_counts) == 0:
            return [], Stage("inverted_file", len(known), 0.0)
        with self._lock:
            words = self.postings.informative(q_ids, q_counts, p.ivf_words)
            score = self.postings.score(q_ids, q_counts, words, self.ids.n)
            score[self._slots(np.asarray(known, np.int64))] = 0.0  # nominated already
            # the filter over the contiguous columns: no gather of ~every keyframe's row
            slots = np.flatnonzero(flt.mask(self.robots.view, self.stamps.view) & (score > 0))
            k = p.ivf_candidates
            if len(slots) > k:  # the k best without sorting every keyframe
                slots = slots[np.argpartition(-score[slots], k - 1)[:k]]
            slots = slots[np.argsort(-score[slots], kind="stable")]
            g = self.gists.view[slots].astype(np.float32)
            dist = np.linalg.norm(g - np.asarray(gist, np.float32).reshape(1, -1), axis=1)
            cands = [
                Candidate(
                    int(self.ids.view[s]),
                    int(self.robots.view[s]),
                    float(self.stamps.view[s]),
                    float(d),
                )
                for s, d in zip(slots, dist, strict=True)
            ]
        ms = 1000 * (time.perf_counter() - t0)
        return cands, Stage("inverted_file", len(known) + len(cands), ms)

    def bow_distances(
        self, q_ids: np.ndarray, q_counts: np.ndarray, kf_ids: np.ndarray
    ) -> np.ndarray:
        """Bhattacharyya distances from a query BoW to the stored keyframes kf_ids."""
        with self._lock:
            slots = np.searchsorted(self.ids.view, np.asarray(kf_ids, np.int64))
            return self._bow_by_slot(q_ids, q_counts, slots)

    def _bow_by_slot(self, q_ids, q_counts, slots) -> np.ndarray:
        if len(slots) == 0:
            return np.zeros(0)
        qs = np.zeros(self.n_words, np.float64)
        total = float(np.sum(q_counts))
        if total == 0:
            return np.ones(len(slots))
        qs[q_ids.astype(np.int64)] = np.sqrt(q_counts / total)
        ptr = self.bow_ptr.view
        starts, ends = ptr[slots], ptr[slots + 1]
        lengths = ends - starts
        flat = np.repeat(starts - np.concatenate([[0], np.cumsum(lengths)[:-1]]), lengths)
        flat = flat + np.arange(lengths.sum())
        words = self.bow_ids.buf[flat].astype(np.int64)
        counts = self.bow_counts.buf[flat].astype(np.float64)
        owner = np.repeat(np.arange(len(slots)), lengths)
        tot = np.bincount(owner, weights=counts, minlength=len(slots))
        rho = np.bincount(owner, weights=qs[words] * np.sqrt(counts), minlength=len(slots))
        rho = np.where(tot > 0, rho / np.sqrt(np.maximum(tot, 1e-12)), 0.0)
        return np.sqrt(np.clip(1.0 - rho, 0.0, 1.0))

    def brute_force_bow(
        self, q_ids: np.ndarray, q_counts: np.ndarray, flt: Filter, k: int
    ) -> list[Candidate]:
        """Baseline: the query's BoW scored against every stored keyframe (the thesis's
        visual-similarity-matrix method, vectorised), then the filter; the k best."""
        with self._lock:
            slots = np.flatnonzero(self.alive.view)
            d = self._bow_by_slot(q_ids, q_counts, slots)
            robots, stamps = self.robots.view[slots], self.stamps.view[slots]
            idx = np.flatnonzero(flt.mask(robots, stamps))
            best = idx[np.argsort(d[idx], kind="stable")[:k]]
            return [
                Candidate(
                    int(self.ids.view[slots[i]]),
                    int(robots[i]),
                    float(stamps[i]),
                    float("nan"),
                    float(d[i]),
                )
                for i in best
            ]
