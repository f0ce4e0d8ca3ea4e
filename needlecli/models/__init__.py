"""Kinematic needle models, registered by name in :data:`MODELS` (each imported on first use)."""

from needlecli.models.base import MODELS, Model, ModelParams, NotMeasurable, Params, StateSelection

__all__ = ["MODELS", "Model", "ModelParams", "NotMeasurable", "Params", "StateSelection"]
