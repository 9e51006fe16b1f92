"""Place recognition for a fleet (thesis Chapter 2): the retrieval cascade over an
in-memory index (`types`, `index`, `cascade`), durable storage behind one interface
(`store`; SQLite in `sqlite`, `sqlite_files`), the overlap worker (`worker`), links from
registered map alignments (`links`), and `PlaceDB`, which composes them (`db`)."""

from fleetmap.place.db import PlaceDB
from fleetmap.place.sqlite_files import check_database_file
from fleetmap.place.types import (
    DEFAULT_CASCADE,
    Candidate,
    CascadeParams,
    CascadeResult,
    Filter,
    Overlap,
    RetrainPolicy,
)

__all__ = [
    "DEFAULT_CASCADE",
    "Candidate",
    "CascadeParams",
    "CascadeResult",
    "Filter",
    "Overlap",
    "PlaceDB",
    "RetrainPolicy",
    "check_database_file",
]
