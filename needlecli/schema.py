"""Shared pieces of the typed config schema (pydantic, unknown keys rejected everywhere)."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class Strict(BaseModel):
    """Base of every config section: unknown keys are errors, values are frozen after validation."""

    model_config = ConfigDict(extra="forbid", frozen=True)


NonNeg = Annotated[float, Field(ge=0.0)]
Positive = Annotated[float, Field(gt=0.0)]
Probability = Annotated[float, Field(ge=0.0, lt=1.0)]


class DistanceGrowth(Strict):
    """Noise growing with distance from a transducer: ``sigma = (1 + a d / d_max) sigma_c`` (seed 003)."""

    transducer: tuple[float, float, float] = Field(description="transducer position, model length unit")
    a: NonNeg = 1.0
    d_max: Positive = Field(80.0, description="normalising distance, model length unit")

    def factor(self, position: np.ndarray, axes: list[int] | None = None) -> np.ndarray:
        """``1 + a d / d_max`` for positions ``(..., 3)`` (or ``(..., len(axes))`` of those axes)."""
        tr = np.asarray(self.transducer) if axes is None else np.asarray(self.transducer)[axes]
        d = np.linalg.norm(np.asarray(position) - tr, axis=-1)
        return 1.0 + self.a * d / self.d_max
