"""Kinematic needle models, registered by name in :data:`MODELS` (each imported on first use)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from needlecli.registry import Registry, lazy_attributes

if TYPE_CHECKING:
    from needlecli.models.base import Model

MODELS: Registry[type[Model]] = Registry("model", group="needlecli.models", base="needlecli.models.base:Model", builtins={
    "unicycle": "needlecli.models.unicycle",
    "modified_unicycle": "needlecli.models.unicycle",
    "so3": "needlecli.models.so3",
    "mnm": "needlecli.models.magnetic",
    "binm": "needlecli.models.magnetic",
})

_LAZY = {  # the contract, imported on first use (this package's import is light: ``needle list``)
    "Model": "needlecli.models.base",
    "ModelParams": "needlecli.models.base",
    "NotMeasurable": "needlecli.models.base",
    "Params": "needlecli.models.base",
    "StateSelection": "needlecli.models.base",
}

__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = ["MODELS", "Model", "ModelParams", "NotMeasurable", "Params", "StateSelection"]
