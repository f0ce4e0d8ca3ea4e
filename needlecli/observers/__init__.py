"""State estimators, registered by type in :data:`OBSERVERS` (each imported on first use)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from needlecli.registry import Registry, lazy_attributes

if TYPE_CHECKING:
    from needlecli.observers.base import Observer

OBSERVERS: Registry[type[Observer]] = Registry("observer type", group="needlecli.observers", base="needlecli.observers.base:Observer", builtins={
    "open_loop": "needlecli.observers.open_loop",
    "ukf": "needlecli.observers.ukf",
    "high_gain": "needlecli.observers.high_gain",
    "so3_invariant": "needlecli.observers.so3_invariant",
    "ekf": "needlecli.observers.kalman",
    "eks": "needlecli.observers.kalman",
    "pf": "needlecli.observers.pf",
    "rbpf": "needlecli.observers.rbpf",
    "rts_fixed_lag": "needlecli.observers.kalman",
})

_LAZY = {  # the contract, imported on first use (this package's import is light: ``needle list``)
    "Channel": "needlecli.problem",
    "ComparisonContext": "needlecli.observers.defaults",
    "EstimationProblem": "needlecli.problem",
    "FitTakes": "needlecli.observers.base",
    "NotApplicable": "needlecli.observers.defaults",
    "Observer": "needlecli.observers.base",
    "ObserverSettings": "needlecli.observers.base",
    "Posterior": "needlecli.observers.base",
    "RunRecorder": "needlecli.observers.record",
}

__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = ["OBSERVERS", "Channel", "ComparisonContext", "EstimationProblem", "FitTakes", "NotApplicable", "Observer",
           "ObserverSettings", "Posterior", "RunRecorder"]
