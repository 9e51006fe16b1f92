"""Alignment of two robots' maps from matched RGB-D pairs (thesis Chapter 3), with a
quality gate that refuses rather than guesses: `types` (parameters, results, the registry
of methods; no torch or Open3D), `hypotheses` (RANSAC, ICP, the free-space test),
`validation` (cross-validation, spread), `pipeline` (the gated default), `baselines`
(and `run_method`, any of `METHODS`), `outputs` (the merged cloud)."""

from fleetmap.align.baselines import baseline, fpfh_ransac_icp, run_method, select_model
from fleetmap.align.hypotheses import surface_rmse
from fleetmap.align.outputs import align_request, merged_cloud
from fleetmap.align.pipeline import align_views
from fleetmap.align.types import DEFAULT_ALIGN, METHODS, AlignParams, AlignResult, Hypothesis
from fleetmap.align.validation import holdout_residual, spread

__all__ = [
    "DEFAULT_ALIGN",
    "METHODS",
    "AlignParams",
    "AlignResult",
    "Hypothesis",
    "align_request",
    "align_views",
    "baseline",
    "fpfh_ransac_icp",
    "holdout_residual",
    "merged_cloud",
    "run_method",
    "select_model",
    "spread",
    "surface_rmse",
]
