"""State estimators, registered by type in :data:`OBSERVERS`."""

from needlecli.observers.base import (
    OBSERVERS,
    Channel,
    EstimationProblem,
    Observer,
    ObserverSettings,
    Posterior,
)
from needlecli.observers import open_loop  # noqa: F401  (registers)

__all__ = ["OBSERVERS", "Channel", "EstimationProblem", "Observer", "ObserverSettings", "Posterior"]
