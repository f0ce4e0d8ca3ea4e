"""Kinematic needle models, registered by name in :data:`MODELS`."""

from needlecli.models import magnetic, so3, unicycle  # noqa: F401  (registers the models)
from needlecli.models.base import MODELS, Model, ModelParams, NotMeasurable, Params, StateSelection

__all__ = ["MODELS", "Model", "ModelParams", "NotMeasurable", "Params", "StateSelection"]
