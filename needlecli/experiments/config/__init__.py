"""What an experiment is: the typed config, its schema, loading and checking it before any work.

The front door is light (nothing is imported until used): :func:`load_config`, :func:`config_problems`
and the config's static type :class:`ExperimentConfig`.
"""

from __future__ import annotations

from needlecli.registry import lazy_attributes

_LAZY = {
    "ExperimentConfig": "needlecli.experiments.config.types",
    "load_config": "needlecli.experiments.config.load",
    "config_problems": "needlecli.experiments.config.load",
}

__getattr__ = lazy_attributes(__name__, _LAZY)

__all__ = ["ExperimentConfig", "config_problems", "load_config"]
