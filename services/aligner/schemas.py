"""Aligner request metadata and response bodies.

`POST /align` takes `multipart/form-data`: a `meta` field holding `AlignMeta` as JSON, and
image files (PNG or any image OpenCV decodes; depth 16-bit single channel, metres =
value / depth_scale), in one of two layouts:

- indexed (what the client sends): `views_a` and `views_b` list each robot's views once,
  `pairs` lists index pairs `[i, j]` (view i of A matched with view j of B), and the files
  are `a{i}_rgb`, `a{i}_depth` for view i of A, `b{j}_rgb`, `b{j}_depth` for view j of B.
  A view in many pairs is sent and processed once.
- inline: no `views_a`/`views_b`; `pairs` holds `{"a": view, "b": view}` objects and the
  files `a{i}_*`, `b{i}_*` belong to pair i.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, model_validator

from fleetmap.align.methods import METHODS
from fleetmap.camera import DEPTH_SCALE_RANGE
from fleetmap.services.aligner.config import Settings
from fleetmap.services.schemas import ConfigView, Matrix4

#: `GET /config`: the settings in force, tokens left out.
CONFIG = ConfigView(Settings, "AlignerConfig")


class IntrinsicsIn(BaseModel):
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    depth_scale: float = Field(ge=DEPTH_SCALE_RANGE[0], le=DEPTH_SCALE_RANGE[1])
    width: int = Field(640, gt=0, le=16384)
    height: int = Field(480, gt=0, le=16384)


class ViewMeta(BaseModel):
    stamp: float = Field(0.0, allow_inf_nan=False)
    T_map_cam: Matrix4 = Field(description="4x4 camera-to-map pose")
    intrinsics: IntrinsicsIn


class PairMeta(BaseModel):
    a: ViewMeta
    b: ViewMeta


class AlignMeta(BaseModel):
    pairs: list[PairMeta] | list[tuple[int, int]] = Field(min_length=1)
    views_a: list[ViewMeta] = []
    views_b: list[ViewMeta] = []
    method: Literal[tuple(METHODS)] = "default"  # type: ignore[valid-type]  (the registry)
    cloud: bool = False
    colour: Literal["robot", "image"] = "robot"

    @model_validator(mode="after")
    def _layout(self):
        indexed = bool(self.views_a or self.views_b)
        if indexed:
            if not (self.views_a and self.views_b):
                raise ValueError("give both views_a and views_b, or neither")
            for k, pr in enumerate(self.pairs):
                if not isinstance(pr, tuple):
                    raise ValueError("with views_a/views_b, pairs are index pairs [i, j]")
                i, j = pr
                if not (0 <= i < len(self.views_a) and 0 <= j < len(self.views_b)):
                    raise ValueError(
                        f"pair {k} = [{i}, {j}] outside views_a ({len(self.views_a)}) "
                        f"or views_b ({len(self.views_b)})"
                    )
        elif not isinstance(self.pairs[0], PairMeta):
            raise ValueError("index pairs need views_a and views_b")
        return self


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
