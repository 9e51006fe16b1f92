"""Aligner request metadata and response bodies.

`POST /align` takes `multipart/form-data`: a `meta` field holding `AlignMeta` as JSON, and
for each pair i the files `a{i}_rgb`, `a{i}_depth`, `b{i}_rgb`, `b{i}_depth` (PNG or any
image OpenCV decodes; depth 16-bit single channel, metres = value / depth_scale).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, field_validator


class IntrinsicsIn(BaseModel):
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    depth_scale: float = Field(gt=0)
    width: int = Field(640, gt=0, le=16384)
    height: int = Field(480, gt=0, le=16384)


class ViewMeta(BaseModel):
    stamp: float = 0.0
    T_map_cam: list[list[float]] = Field(description="4x4 camera-to-map pose")
    intrinsics: IntrinsicsIn

    @field_validator("T_map_cam")
    @classmethod
    def _four_by_four(cls, v):
        if len(v) != 4 or any(len(r) != 4 for r in v):
            raise ValueError("T_map_cam must be 4x4")
        return v


class PairMeta(BaseModel):
    a: ViewMeta
    b: ViewMeta


class AlignMeta(BaseModel):
    pairs: list[PairMeta] = Field(min_length=1)
    method: Literal["default", "rigid", "similarity", "affine", "mlp", "icp"] = "default"
    cloud: bool = False
    colour: Literal["robot", "image"] = "robot"


class AlignAnswer(BaseModel):
    merged: bool
    reason: str
    method: str
    transform: list[list[float]] | None = None
    affine: list[list[float]] | None = None
    correspondences: int
    inliers: int
    holdout_residual_m: float | None = None
    icp_fitness: float = 0.0
    mlp_holdout_residual_m: float | None = None
    hypotheses: list[dict] = []
    seconds: float = 0.0
    cloud_id: str | None = None
    cloud_points: int | None = None


class Health(BaseModel):
    status: str
    clouds_cached: int
