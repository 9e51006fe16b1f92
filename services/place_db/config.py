"""Place database settings, from FLEETMAP_PLACE_DB_* environment variables or a .env file."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from fleetmap.fleet.merge_worker import LiveParams
from fleetmap.frame import MAX_FRAME_BYTES
from fleetmap.matching import MatchParams
from fleetmap.place import CascadeParams
from fleetmap.place.store import DB_FILE, PG_TIMEOUT_S, POSTGRES_SCHEMES
from fleetmap.services.schemas import Token
from fleetmap.services.serving import HEADER_TIMEOUT_S
from fleetmap.services.settings import refuse_flat_names, secrets_dir


def default_data_dir() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "fleetmap"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(
        env_prefix="FLEETMAP_PLACE_DB_",
        env_nested_delimiter="__",
        env_file=".env",
        secrets_dir=secrets_dir(),
        extra="ignore",
    )

    data_dir: Path = Field(default_factory=default_data_dir)
    # postgresql://USER[:PASS]@HOST:PORT/DB: replicas over one database; unset: SQLite in
    # data_dir (the embedded default)
    database: SecretStr | None = None
    pg_timeout_s: float = PG_TIMEOUT_S  # PostgreSQL: a pooled connection within this, else 503
    db_file: str = DB_FILE
    vocabulary: Path | None = None  # None: the shipped default
    # access control: none configured = open (logged at start-up)
    operator_token: Token | None = None
    robot_tokens: dict[str, SecretStr] = {}  # JSON: {"robot_id": "token", ...}
    max_body_bytes: int = MAX_FRAME_BYTES
    max_view_bytes: int = 16 * 1024 * 1024  # a keyframe's colour and depth images together
    # a request's headers within this many seconds, else the connection is closed (slowloris)
    header_timeout_s: float = HEADER_TIMEOUT_S
    # the cascade's parameters (thesis Algorithm 3), nested:
    # FLEETMAP_PLACE_DB_CASCADE__GIST_THRESHOLD=0.7, FLEETMAP_PLACE_DB_CASCADE__MATCH__RATIO=0.8
    cascade: CascadeParams = CascadeParams()
    # the live map: the aligner the merge worker sends robot pairs to (unset: no merge
    # worker; the map is still served from the store), its token, and when pairs are aligned
    aligner: str | None = None
    aligner_token: Token | None = None
    live: LiveParams = LiveParams()
    # coarse codebook upkeep
    auto_retrain: bool = True
    background_overlaps: bool = True
    # overlap detection waits for the first overlaps request, so that every keyframe stored
    # before it is compared with all the others: overlaps that do not follow the order the
    # keyframes arrived in (the batch merge's embedded database; not for a live fleet)
    defer_overlaps: bool = False
    # threads detecting overlaps: one for a live fleet (keyframes arrive one by one); the
    # batch merge's deferred detection uses one per core (`OverlapWorker`)
    overlap_threads: int = Field(1, ge=1, le=64)

    def __init__(self, **values):
        refuse_flat_names("FLEETMAP_PLACE_DB_", CascadeParams, "CASCADE")
        refuse_flat_names(
            "FLEETMAP_PLACE_DB_",
            MatchParams,
            "CASCADE__MATCH",
            renamed=[("min_inliers", "min_epipolar_inliers")],
        )
        super().__init__(**values)

    @property
    def store(self) -> str | Path:
        """What PlaceDB opens: the PostgreSQL URL when one is set, else the SQLite file."""
        return self.db_path if self.database is None else self.database.get_secret_value()

    @field_validator("database")
    @classmethod
    def _postgres_url(cls, v: SecretStr | None) -> SecretStr | None:
        if v is not None and not v.get_secret_value().startswith(POSTGRES_SCHEMES):
            raise ValueError("must be a postgresql://USER[:PASS]@HOST:PORT/DB URL")
        return v

    @field_validator("aligner")
    @classmethod
    def _aligner_url(cls, v: str | None) -> str | None:
        """An aligner that is not an http(s) URL was accepted at start and failed on every
        pair once robots streamed (an outside tester's review)."""
        if v is not None and not v.startswith(("http://", "https://")):
            raise ValueError("must be an http:// or https:// URL")
        return v

    @field_validator("data_dir")
    @classmethod
    def _a_folder(cls, v: Path) -> Path:
        if v.exists() and not v.is_dir():
            raise ValueError("is not a folder")
        return v

    @property
    def db_path(self) -> Path:
        return self.data_dir / self.db_file
