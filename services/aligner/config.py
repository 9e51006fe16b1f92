"""Aligner settings, from FLEETMAP_ALIGNER_* environment variables or a .env file."""

from __future__ import annotations

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from fleetmap.align.types import AlignParams
from fleetmap.services.schemas import Token
from fleetmap.services.serving import HEADER_TIMEOUT_S
from fleetmap.services.settings import refuse_flat_names, secrets_dir


class Settings(BaseSettings):
    model_config = SettingsConfigDict(
        env_prefix="FLEETMAP_ALIGNER_",
        env_nested_delimiter="__",
        env_file=".env",
        secrets_dir=secrets_dir(),
        extra="ignore",
    )

    # access control: none configured = open (logged at start-up)
    operator_token: Token | None = None
    robot_tokens: dict[str, SecretStr] = {}  # JSON: {"robot_id": "token", ...}
    max_body_bytes: int = Field(128 * 1024 * 1024, ge=1)  # enforced while streaming
    # a request's headers within this many seconds, else the connection is closed (slowloris)
    header_timeout_s: float = HEADER_TIMEOUT_S
    # decoded colour + depth pixels of all requests being aligned at once (about 8 bytes
    # each while aligned): bounds memory whatever the concurrency; more waits, then 503
    max_pixels_in_flight: int = Field(32 * 1024 * 1024, ge=1)
    # /align requests past their body; more wait, then 503
    max_requests_in_flight: int = Field(2, ge=1)
    max_views: int = Field(32, ge=1)  # per robot in one request
    max_pairs: int = Field(512, ge=1)
    max_image_pixels: int = Field(4096 * 4096, ge=1)
    cloud_cache: int = Field(8, ge=1)  # merged clouds kept for GET /clouds/{id}
    # the alignment's parameters, nested: FLEETMAP_ALIGNER_ALIGN__MIN_INLIERS=20
    align: AlignParams = AlignParams()

    def __init__(self, **values):
        refuse_flat_names("FLEETMAP_ALIGNER_", AlignParams, "ALIGN")
        super().__init__(**values)
