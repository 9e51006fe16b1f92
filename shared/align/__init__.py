"""Alignment of two robots' maps from matched RGB-D pairs (thesis Chapter 3), with a
quality gate that refuses rather than guesses: `types` (parameters, results; no torch or
Open3D), `methods` (the registry: `METHODS[name](pairs, params)`), `hypotheses` (RANSAC,
ICP, the free-space test), `validation` (cross-validation, spread), `pipeline` (the gated
default), `second_look` (ASIFT where the first look was refused), `geometric_look` (FPFH
basins judged by free space and colour where both image looks were refused), `baselines`
(what the default is compared with), `outputs` (the merged cloud)."""

from fleetmap.align.baselines import fpfh_ransac_icp, select_model
from fleetmap.align.hypotheses import surface_rmse
from fleetmap.align.methods import METHODS, Method, method
from fleetmap.align.outputs import merged_cloud
from fleetmap.align.pipeline import align_views
from fleetmap.align.types import DEFAULT_ALIGN, AlignParams, AlignResult, Hypothesis
from fleetmap.align.validation import holdout_residual, spread_m

__all__ = [
    "DEFAULT_ALIGN",
    "METHODS",
    "AlignParams",
    "AlignResult",
    "Hypothesis",
    "Method",
    "align_views",
    "fpfh_ransac_icp",
    "holdout_residual",
    "merged_cloud",
    "method",
    "select_model",
    "spread_m",
    "surface_rmse",
]
