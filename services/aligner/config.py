"""Aligner settings, from FLEETMAP_ALIGNER_* environment variables or a .env file."""

from __future__ import annotations

from pydantic import SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from fleetmap.align import AlignParams

_P = AlignParams()


class Settings(BaseSettings):
    model_config = SettingsConfigDict(
        env_prefix="FLEETMAP_ALIGNER_", env_file=".env", extra="ignore"
    )

    # access control: none configured = open (logged at start-up)
    operator_token: SecretStr | None = None
    robot_tokens: dict[str, SecretStr] = {}  # JSON: {"robot_id": "token", ...}
    max_body_bytes: int = 128 * 1024 * 1024  # enforced while streaming, chunked or not
    # decoded colour + depth pixels of all requests being aligned at once (about 8 bytes
    # each while aligned): bounds memory whatever the concurrency; more waits, then 503
    max_pixels_in_flight: int = 32 * 1024 * 1024
    max_requests_in_flight: int = 2  # /align requests past their body; more wait, then 503
    max_views: int = 32  # per robot in one request
    max_pairs: int = 512
    max_image_pixels: int = 4096 * 4096
    cloud_cache: int = 8  # merged clouds kept for GET /clouds/{id}
    ransac_tol_m: float = _P.ransac_tol_m
    min_inliers: int = _P.min_inliers
    min_spread_m: float = _P.min_spread_m
    max_holdout_m: float = _P.max_holdout_m
    voxel_m: float = _P.voxel_m
    coarse_voxel_m: float = _P.coarse_voxel_m
    min_consistency: float = _P.min_consistency
    min_overlap: float = _P.min_overlap
    ambiguity: float = _P.ambiguity
    colour_icp: bool = _P.colour_icp

    def params(self) -> AlignParams:
        return AlignParams(
            ransac_tol_m=self.ransac_tol_m,
            min_inliers=self.min_inliers,
            min_spread_m=self.min_spread_m,
            max_holdout_m=self.max_holdout_m,
            voxel_m=self.voxel_m,
            coarse_voxel_m=self.coarse_voxel_m,
            min_consistency=self.min_consistency,
            min_overlap=self.min_overlap,
            ambiguity=self.ambiguity,
            colour_icp=self.colour_icp,
        )
