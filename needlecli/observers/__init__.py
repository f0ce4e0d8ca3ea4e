"""State estimators, registered by type in :data:`OBSERVERS` (each imported on first use)."""

from needlecli.observers.base import (
    OBSERVERS,
    Channel,
    EstimationProblem,
    Observer,
    ObserverSettings,
    Posterior,
)

__all__ = ["OBSERVERS", "Channel", "EstimationProblem", "Observer", "ObserverSettings", "Posterior"]
