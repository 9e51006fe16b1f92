"""The storage interface: `open_store` chooses the backend from where the data lives, and
each backend has every member of the `Store` protocol (no caller needs `getattr`)."""

from __future__ import annotations

import inspect

import pytest

from fleetmap.place.postgres import PostgresStore
from fleetmap.place.sqlite import SQLiteStore
from fleetmap.place.store import DB_FILE, SharedStore, Store, open_store


def _members(proto) -> set[str]:
    own = {n for n, v in vars(proto).items() if not n.startswith("_") and callable(v)}
    return own | set(proto.__annotations__)


def _methods(proto) -> set[str]:
    return {n for n in _members(proto) if inspect.isfunction(getattr(proto, n, None))}


@pytest.mark.parametrize("where", ["folder", "file"])
def test_open_store_opens_sqlite_in_a_folder_or_the_file_named(tmp_path, where):
    target = tmp_path if where == "folder" else tmp_path / "mine.sqlite"
    store = open_store(target, "vocab")
    try:
        assert isinstance(store, SQLiteStore) and not store.shared
        assert store.path == (tmp_path / DB_FILE if where == "folder" else target)
        assert store.where == str(store.path) and store.path.exists()
        with store.exclusive("live map") as held:
            assert held()
        missing = [n for n in _members(Store) if not hasattr(store, n)]
        assert missing == []
    finally:
        store.close()


def test_postgres_has_every_member_of_a_shared_store():
    assert PostgresStore.shared is True
    missing = [n for n in _methods(SharedStore) | _methods(Store) if not hasattr(PostgresStore, n)]
    assert missing == []
    params = inspect.signature(PostgresStore.index_rows).parameters
    assert list(params) == ["self", "batch", "after"]
