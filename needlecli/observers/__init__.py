"""State estimators, registered by type in :data:`OBSERVERS` (each imported on first use)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from needlecli.registry import Registry

if TYPE_CHECKING:
    from needlecli.observers.base import Observer

OBSERVERS: Registry[type[Observer]] = Registry("observer type", group="needlecli.observers", builtins={
    "open_loop": "needlecli.observers.open_loop",
    "ukf": "needlecli.observers.ukf",
    "high_gain": "needlecli.observers.high_gain",
    "so3_invariant": "needlecli.observers.so3_invariant",
    "ekf": "needlecli.observers.kalman",
    "eks": "needlecli.observers.kalman",
})

_LAZY = {  # the contract, imported on first use (this package's import is light: ``needle list``)
    "Channel": "needlecli.problem",
    "EstimationProblem": "needlecli.problem",
    "Observer": "needlecli.observers.base",
    "ObserverSettings": "needlecli.observers.base",
    "Posterior": "needlecli.observers.base",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["OBSERVERS", "Channel", "EstimationProblem", "Observer", "ObserverSettings", "Posterior"]
