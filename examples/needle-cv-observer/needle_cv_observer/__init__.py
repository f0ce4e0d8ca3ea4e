"""Example needlecli plug-in: a constant-velocity Kalman filter on the tip position (:mod:`.observer`)."""

from needle_cv_observer.observer import ConstantVelocityKF, CVSettings

__all__ = ["CVSettings", "ConstantVelocityKF"]
