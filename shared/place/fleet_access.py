"""What the fleet level (`fleetmap.fleet`: the merge worker and what `GET /map` serves)
reads and keeps in the place database, as `PlaceDB` methods: each robot's keyframes and
stored views, which life of a robot this is, and the fleet's own rows (the pair states,
the placement, the worker's last word: `fleetmap.fleet.state`) under the store's lock.
The fleet never reaches into the store itself."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager

from fleetmap.place.store import Store


class FleetAccess:
    """`PlaceDB`'s face to the fleet level (a mixin: `PlaceDB` sets `store`)."""

    store: Store

    def robot_code(self, name: str) -> int | None:
        """The robot's store code (its order of arrival); None for an unknown robot."""
        return self.store.robot_code(name)

    def robot_count(self) -> int:
        return self.store.robot_count()

    def keyframe_ids(self, robot: str) -> list[int]:
        """The robot's keyframe ids in time order; [] for an unknown robot."""
        code = self.store.robot_code(robot)
        return [] if code is None else self.store.robot_keyframe_ids(code)

    def view_ids(self, robot: str) -> list[int]:
        """The robot's keyframes stored with an RGB-D view, in time order; [] for an
        unknown robot."""
        code = self.store.robot_code(robot)
        return [] if code is None else self.store.view_ids(code)

    def incarnation(self, robot: str) -> int | None:
        """Which life of `robot` this is: its first keyframe id (ids are never reused, so a
        robot deleted and posted again has another); None for an unknown robot."""
        ids = self.keyframe_ids(robot)
        return min(ids) if ids else None

    def exclusive(self, what: str) -> AbstractContextManager[Callable[[], bool]]:
        """Held by one process at a time (`Store.exclusive`): on SQLite always, on
        PostgreSQL one replica; yields `held()`, False once the hold was lost."""
        return self.store.exclusive(what)

    def live_get(self, key: str) -> str | None:
        """A fleet row ("pairs", "map", "worker"): JSON text, None before it was written."""
        return self.store.live_get(key)

    def live_put(self, key: str, value: str) -> None:
        self.store.live_put(key, value)

    def live_cas(self, key: str, old: str | None, new: str) -> bool:
        """Write `new` only if the row still holds `old` (compare-and-set)."""
        return self.store.live_cas(key, old, new)

    def overlap_graph(self) -> list[dict]:
        """Every robot pair with verified overlaps: count, best and total inliers."""
        merged: dict[tuple[str, str], list[int]] = {}
        for ra, rb, n, best, total in self.store.overlap_counts():
            names = self.store.robot_name(ra), self.store.robot_name(rb)
            if None in names:
                continue  # deleted meanwhile
            acc = merged.setdefault(tuple(sorted(names)), [0, 0, 0])
            acc[0], acc[1], acc[2] = acc[0] + n, max(acc[1], best), acc[2] + total
        return [
            {"robot_a": a, "robot_b": b, "pairs": n, "best_inliers": best, "total_inliers": total}
            for (a, b), (n, best, total) in sorted(merged.items())
        ]
