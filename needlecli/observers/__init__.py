"""State estimators, registered by type in :data:`OBSERVERS`."""

from needlecli.observers import high_gain, kalman, open_loop, so3_invariant, ukf  # noqa: F401  (registers)
from needlecli.observers.base import (
    OBSERVERS,
    Channel,
    EstimationProblem,
    Observer,
    ObserverSettings,
    Posterior,
)

__all__ = ["OBSERVERS", "Channel", "EstimationProblem", "Observer", "ObserverSettings", "Posterior"]
