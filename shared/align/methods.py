"""Every way to align two robots' maps, by name: the gated default and the baselines beside
it. `METHODS[name](pairs, params)` returns an `AlignResult`; the CLI's `--method` choices,
the aligner's request schema and the dispatch all read this one registry. Light to import:
each method imports its machinery (Open3D, torch) when it runs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from fleetmap.align.types import DEFAULT_ALIGN, AlignParams, AlignResult
from fleetmap.errors import BadInput


@dataclass(frozen=True)
class Method:
    """One way to align: what it is, and the callable (pairs, params) -> AlignResult."""

    description: str
    run: Callable[[list, AlignParams], AlignResult]

    def __call__(self, pairs, p: AlignParams = DEFAULT_ALIGN) -> AlignResult:
        return self.run(pairs, p)


def _default(pairs, p: AlignParams) -> AlignResult:
    from fleetmap.align.pipeline import align_views

    return align_views(pairs, p)


def _baseline(name: str) -> Callable[[list, AlignParams], AlignResult]:
    def run(pairs, p: AlignParams) -> AlignResult:
        from fleetmap.align import baselines

        return baselines.BASELINES[name](pairs, p)

    return run


METHODS: dict[str, Method] = {
    "default": Method(
        "gated: RANSAC hypotheses, free-space judged ICP, held-out residual, MLP", _default
    ),
    "rigid": Method(
        "rigid fit in RANSAC on the visual correspondences (no gate)", _baseline("rigid")
    ),
    "similarity": Method(
        "similarity fit in RANSAC on the visual correspondences (no gate)", _baseline("similarity")
    ),
    "affine": Method(
        "affine fit in RANSAC on the visual correspondences (no gate)", _baseline("affine")
    ),
    "mlp": Method("the thesis MLP on the visual correspondences (no gate)", _baseline("mlp")),
    "icp": Method(
        "point-to-plane ICP from identity on the depth clouds (no gate)", _baseline("icp")
    ),
    "fpfh": Method(
        "FPFH + RANSAC + ICP on the depth clouds, the map_merge_3d recipe (no gate)",
        _baseline("fpfh"),
    ),
}


def method(name: str) -> Method:
    """The method called `name`; BadInput naming the choices for any other name."""
    if name not in METHODS:
        raise BadInput(f"Unknown method {name!r}; expected one of {', '.join(METHODS)}")
    return METHODS[name]
