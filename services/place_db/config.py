"""Place database settings, from FLEETMAP_PLACE_DB_* environment variables or a .env file."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from shared.frame import MAX_FRAME_BYTES


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
    max_body_bytes: int = MAX_FRAME_BYTES
    # cascade (thesis Algorithm 3)
    m_clusters: int = 4
    gist_threshold: float = 0.75
    max_candidates: int = 300
    bow_threshold: float = 0.92
    max_verify: int = 12
    max_verify_per_robot: int = 4
    ratio: float = 0.9
    min_inliers: int = 10
    min_inlier_ratio: float = 0.3
    # coarse codebook upkeep
    auto_retrain: bool = True
    background_overlaps: bool = True

    @property
    def db_path(self) -> Path:
        return self.data_dir / self.db_file
