"""Schema types both services' requests and answers use."""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator


def _four_by_four(v: list[list[float]]) -> list[list[float]]:
    if len(v) != 4 or any(len(r) != 4 for r in v):
        raise ValueError("must be 4x4")
    return v


Matrix4 = Annotated[list[list[float]], AfterValidator(_four_by_four)]
"""A 4x4 matrix in a JSON body, rows of numbers (pose or rigid transform)."""
