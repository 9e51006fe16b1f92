"""Fits that must agree: around every cycle of merged robot pairs the pairwise transforms
compose to the identity, up to the sensor's noise. A fit that closes a cycle and disagrees
with the chain of fits it closes means one of them is wrong; inlier counts cannot say
which (a robot posting copies of another's images gets thousands), so no robot placed
through that cycle is placed until the fits agree (the robot where the cycle starts keeps
its place: it does not depend on the cycle).

Tolerances follow from RGB-D depth noise: a structured-light or time-of-flight camera's
depth error grows to about 5 cm at the 6 m the clouds are cut at (Khoshelham & Elberink
2012: sigma_z = 1.4e-3 z^2 m); a cycle of honest fits lies well within five times that,
0.25 m, and within 5 degrees; the wrong fits seen (issue 26: 5 m and 90 degrees) are far
outside both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetmap.geometry import invert, transform_error


@dataclass(frozen=True)
class CycleParams:
    max_translation_m: float = 0.25
    max_rotation_deg: float = 5.0


def disagreeing(
    placed: dict[str, np.ndarray],
    chain: dict[str, list[str]],
    edges: dict[tuple[str, str], dict],
    params: CycleParams = CycleParams(),
) -> dict[str, str]:
    """{robot: reason} of robots whose placement rests on a cycle whose fits disagree.

    placed, chain: `fleetmap.fleet.placement.spanning_placement`'s T_ref_r and the robots
    each placement went through; edges[(a, b)]: {"T_a_b": 4x4, ...}."""
    tree = {frozenset(c[-2:]) for c in chain.values() if len(c) >= 2}
    out: dict[str, str] = {}
    for (a, b), e in edges.items():
        if a not in placed or b not in placed or frozenset((a, b)) in tree:
            continue
        dt, dr = transform_error(invert(placed[a]) @ placed[b], e["T_a_b"])
        if dt <= params.max_translation_m and dr <= params.max_rotation_deg:
            continue
        root = _common_root(chain[a], chain[b])
        cycle = chain[a][chain[a].index(root) :] + chain[b][chain[b].index(root) + 1 :][::-1]
        why = (
            f"its fits disagree around the cycle {'-'.join(cycle)}-{cycle[0]} by {dt:.2f} m "
            f"and {dr:.1f} deg: not placed until they agree"
        )
        for r in cycle[1:]:
            out.setdefault(r, why)
    for r, c in chain.items():  # placed through a robot whose fits disagree
        through = next((x for x in c if x in out), None)
        if through is not None and r not in out:
            out[r] = f"placed through {through}, whose fits disagree"
    return out


def _common_root(x: list[str], y: list[str]) -> str:
    root = x[0]
    for p, q in zip(x, y, strict=False):
        if p != q:
            break
        root = p
    return root
