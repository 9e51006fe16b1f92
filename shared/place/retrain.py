"""Upkeep of the coarse codebook: when the stored GISTs no longer fit it (thesis Fig.
2.12: uneven clusters), k-means it anew and swap the index in while queries and ingest go
on. On a shared store one replica retrains at a time (`Store.exclusive`) and the others
take the saved codebook (`Follower`)."""

from __future__ import annotations

import logging
import threading
import time

from fleetmap.errors import Conflict
from fleetmap.place.index import PlaceIndex
from fleetmap.place.store import Store
from fleetmap.place.types import RetrainPolicy

log = logging.getLogger(__name__)


class CodebookUpkeep:
    def __init__(self, policy: RetrainPolicy, index: PlaceIndex, store: Store, follower=None):
        self.policy, self.index, self.store, self.follower = policy, index, store, follower
        self._running = threading.Lock()

    def retrain(self, n_clusters: int | None = None) -> dict:
        """Retrain now; Conflict if a retraining is already running."""
        if not self._running.acquire(blocking=False):
            raise Conflict("A retraining is already running")
        try:
            t = time.perf_counter()
            k = n_clusters or self.policy.target_clusters(len(self.index))
            with self.store.exclusive("retraining"):
                sizes = self.index.retrain(k)
                self.store.save_codebook(self.index.codebook)
            if self.follower is not None:
                self.follower.codebook_saved()
            info = {
                "clusters": int(len(sizes)),
                "keyframes": int(sizes.sum()),
                "cluster_max": int(sizes.max()),
                "cluster_mean": float(sizes.mean()),
                "seconds": time.perf_counter() - t,
            }
            log.info("codebook retrained: %s", info)
            return info
        finally:
            self._running.release()

    def needed(self) -> bool:
        p, n = self.policy, len(self.index)
        if not p.enabled or n < p.min_keyframes:
            return False
        sizes = self.index.cluster_sizes()
        mean = max(float(sizes.mean()), 1e-9)
        return mean > p.max_mean_list or sizes.max() > p.max_imbalance * mean

    def maybe(self, added: int = 1) -> None:
        """Checked every 500 keyframes; retrains in the background when needed."""
        if len(self.index) % 500 >= added or self._running.locked():
            return
        if self.needed():
            threading.Thread(target=self._quietly, daemon=True).start()

    def _quietly(self) -> None:
        try:
            self.retrain()
        except Conflict:
            pass
        except Exception:
            log.exception("background codebook retraining failed")
