"""The inverted file over visual words: for each word, the keyframe slots whose bag of words
holds it and the word's Bhattacharyya weight there (the square root of its frequency).

Beside the GIST clusters it nominates the keyframes that share the query's most informative
words (highest tf-idf), so a revisit whose GIST falls outside the probed clusters (seen from
another direction, another light) still reaches the BoW stage. As DBoW2's inverted file, a
query reads only the postings of its own words; here only of its few most informative ones,
so the cost is bounded by those words' document frequencies, not by the database's size.

Layout: an unsorted tail of recent postings in grow-only buffers (as the forward CSR of
`PlaceIndex`), and word-sorted segments (CSR over words: `ptr`, `slots`, `weights`) of sizes
growing by at least two, as a log-structured merge: the full tail becomes a segment, and a
segment as large as half its elder is merged into it. So a posting is moved O(log N) times
over its life, a query reads a bounded tail plus O(log N) slices per word, and nothing
stalls ingest for a pass over the whole file. Removal compacts every part.
"""

from __future__ import annotations

import numpy as np

# a query scans the whole tail (a lookup per posting, ~0.1 ms per 65k); past this many
# postings (~300 keyframes) it is sorted into a segment
_MAX_TAIL = 1 << 16


class Grow:
    """Append-only numpy buffer with amortised doubling."""

    def __init__(self, dtype, width: int | None = None):
        shape = (1024,) if width is None else (1024, width)
        self.buf = np.zeros(shape, dtype=dtype)
        self.n = 0

    def extend(self, values: np.ndarray) -> None:
        need = self.n + len(values)
        if need > len(self.buf):
            new = np.zeros((max(need, 2 * len(self.buf)),) + self.buf.shape[1:], self.buf.dtype)
            new[: self.n] = self.buf[: self.n]
            self.buf = new
        self.buf[self.n : need] = values
        self.n = need

    def reset(self, values: np.ndarray) -> None:
        self.n = 0
        self.extend(values)

    @property
    def view(self) -> np.ndarray:
        return self.buf[: self.n]


class _Segment:
    """Postings sorted by word (then slot): CSR over words."""

    def __init__(self, ptr: np.ndarray, slots: np.ndarray, weights: np.ndarray):
        self.ptr, self.slots, self.weights = ptr, slots, weights

    @classmethod
    def sort(cls, words: np.ndarray, slots: np.ndarray, weights: np.ndarray, n_words: int):
        order = np.argsort(words, kind="stable")  # slot order kept within a word
        counts = np.bincount(words.astype(np.int64), minlength=n_words)
        return cls(np.concatenate([[0], np.cumsum(counts)]), slots[order], weights[order])

    def __len__(self) -> int:
        return len(self.slots)

    def words(self) -> np.ndarray:
        """The word of each posting, shape (len(self),)."""
        return np.repeat(np.arange(len(self.ptr) - 1), np.diff(self.ptr))

    def merge(self, younger: _Segment) -> _Segment:
        """One segment of both, younger's slots after ours within each word: one scatter."""
        n_old, n_new = len(self), len(self) + len(younger)
        # our entry i of word w moves past younger's entries of smaller words; younger's
        # entry j (of word w) lands after every one of ours of words up to w
        at_old = np.arange(n_old) + younger.ptr[self.words()]
        at_new = np.arange(len(younger)) + self.ptr[younger.words() + 1]
        slots, weights = np.empty(n_new, np.int32), np.empty(n_new, np.float16)
        slots[at_old], weights[at_old] = self.slots, self.weights
        slots[at_new], weights[at_new] = younger.slots, younger.weights
        return _Segment(self.ptr + younger.ptr, slots, weights)

    def compact(self, alive: np.ndarray) -> _Segment:
        keep = alive[self.slots]
        counts = np.bincount(self.words()[keep], minlength=len(self.ptr) - 1)
        return _Segment(
            np.concatenate([[0], np.cumsum(counts)]), self.slots[keep], self.weights[keep]
        )


class Postings:
    """Word -> (keyframe slot, sqrt of the word's frequency in that keyframe) postings.

    Slots are `PlaceIndex` buffer positions; not thread-safe on its own (the index's lock
    guards it)."""

    def __init__(self, n_words: int):
        self.n_words = n_words
        self._wtype = np.uint16 if n_words <= 1 << 16 else np.uint32
        self.segments: list[_Segment] = []  # oldest (largest) first
        self.tail_words = Grow(self._wtype)
        self.tail_slots = Grow(np.int32)
        self.tail_weights = Grow(np.float16)
        self.df = np.zeros(n_words, np.int64)  # live keyframes holding each word
        self.n_docs = 0

    def __len__(self) -> int:
        """Postings held (live keyframes' only: removal compacts)."""
        return sum(map(len, self.segments)) + self.tail_slots.n

    def add(self, first_slot: int, lengths: np.ndarray, words: np.ndarray, counts: np.ndarray):
        """Postings of len(lengths) consecutive slots from `first_slot`; `words` and `counts`
        are their sparse bags of words concatenated (each word once per keyframe)."""
        lengths = np.asarray(lengths, np.int64)
        owner = np.repeat(np.arange(len(lengths)), lengths)
        counts = np.asarray(counts, np.float64)
        total = np.bincount(owner, weights=counts, minlength=len(lengths))
        weights = np.sqrt(counts / np.maximum(total[owner], 1e-12))
        words = np.asarray(words, np.int64)
        self.tail_words.extend(words.astype(self._wtype))
        self.tail_slots.extend((first_slot + owner).astype(np.int32))
        self.tail_weights.extend(weights.astype(np.float16))
        self.df += np.bincount(words, minlength=self.n_words)
        self.n_docs += len(lengths)
        if self.tail_slots.n > _MAX_TAIL:
            self._flush()

    def _flush(self) -> None:
        """The tail becomes the youngest segment; then merge while a segment is as large as
        half its elder (segment sizes at least double from young to old)."""
        tail = (g.view.copy() for g in (self.tail_words, self.tail_slots, self.tail_weights))
        self.segments.append(_Segment.sort(*tail, self.n_words))
        for g in (self.tail_words, self.tail_slots, self.tail_weights):
            g.n = 0
        segs = self.segments
        while len(segs) > 1 and 2 * len(segs[-1]) >= len(segs[-2]):
            young = segs.pop()
            segs[-1] = segs[-1].merge(young)

    def remove(self, alive: np.ndarray) -> None:
        """Drop the postings of every slot that `alive` (bool, by slot) no longer holds."""
        self.segments = [s.compact(alive) for s in self.segments]
        keep_t = alive[self.tail_slots.view]
        for g in (self.tail_words, self.tail_slots, self.tail_weights):
            g.reset(g.view[keep_t].copy())
        self.df = np.bincount(self.tail_words.view.astype(np.int64), minlength=self.n_words)
        for s in self.segments:
            self.df += np.diff(s.ptr)
        self.n_docs = int(np.count_nonzero(alive))

    def informative(self, q_ids: np.ndarray, q_counts: np.ndarray, k: int) -> np.ndarray:
        """The query's k words of highest tf-idf (tf = count / total, idf = log(N / df)),
        highest first; words no stored keyframe holds are left out."""
        q_ids = np.asarray(q_ids, np.int64)
        df = self.df[q_ids]
        held = df > 0
        q_ids, df = q_ids[held], df[held]
        tfidf = np.asarray(q_counts, np.float64)[held] * np.log(max(self.n_docs, 1) / df)
        return q_ids[np.argsort(-tfidf, kind="stable")[:k]]

    def score(
        self, q_ids: np.ndarray, q_counts: np.ndarray, words: np.ndarray, n_slots: int
    ) -> np.ndarray:
        """Partial Bhattacharyya coefficient of the query with every slot over `words` only:
        sum of sqrt(q_w d_w), shape (n_slots,), 0 where a slot holds none of them."""
        q = np.zeros(self.n_words, np.float64)
        q[np.asarray(q_ids, np.int64)] = np.sqrt(q_counts / max(float(np.sum(q_counts)), 1e-12))
        words = np.asarray(words, np.int64)
        slots, weights, lengths = [], [], []
        for s in self.segments:  # contiguous slices: no index arrays over the postings
            for w in words:
                a, b = s.ptr[w], s.ptr[w + 1]
                slots.append(s.slots[a:b])
                weights.append(s.weights[a:b])
            lengths.append(s.ptr[words + 1] - s.ptr[words])
        chosen = np.zeros(self.n_words, bool)
        chosen[words] = True
        hit = np.flatnonzero(chosen[self.tail_words.view])  # one lookup per tail posting
        slots.append(self.tail_slots.view[hit])
        weights.append(self.tail_weights.view[hit])
        qw = np.concatenate(
            [np.repeat(q[words], n) for n in lengths] + [q[self.tail_words.view[hit]]]
        )
        terms = qw * np.concatenate(weights)
        return np.bincount(np.concatenate(slots), terms, minlength=n_slots)
