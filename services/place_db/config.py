"""Place database settings, from FLEETMAP_PLACE_DB_* environment variables or a .env file."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from fleetmap.frame import MAX_FRAME_BYTES
from fleetmap.place import DEFAULT_CASCADE as _C

_M = _C.match


def default_data_dir() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "fleetmap"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(
        env_prefix="FLEETMAP_PLACE_DB_", env_file=".env", extra="ignore"
    )

    data_dir: Path = Field(default_factory=default_data_dir)
    db_file: str = "place_db.sqlite"
    vocabulary: Path | None = None  # None: the shipped default
    # access control: none configured = open (logged at start-up)
    operator_token: SecretStr | None = None
    robot_tokens: dict[str, SecretStr] = {}  # JSON: {"robot_id": "token", ...}
    max_body_bytes: int = MAX_FRAME_BYTES
    # cascade (thesis Algorithm 3); defaults from fleetmap.place.types / fleetmap.matching
    m_clusters: int = _C.m_clusters
    gist_threshold: float = _C.gist_threshold
    max_candidates: int = _C.max_candidates
    bow_threshold: float = _C.bow_threshold
    max_verify: int = _C.max_verify
    max_verify_per_robot: int = _C.max_verify_per_robot
    ratio: float = _M.ratio
    min_inliers: int = _M.min_inliers
    min_inlier_ratio: float = _M.min_inlier_ratio
    min_inliers_3d_check: int = _M.min_inliers_3d_check
    min_rigid_inliers: int = _M.min_rigid_inliers
    # coarse codebook upkeep
    auto_retrain: bool = True
    background_overlaps: bool = True

    @property
    def db_path(self) -> Path:
        return self.data_dir / self.db_file
