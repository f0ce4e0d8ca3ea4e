"""needlecli: batch experiments with steerable-needle models, sensors and observers.

The package is laid out by role (see ``STYLE.md`` in the project's shared folder):

``numerics``     pure array functions (RK4, angle wrapping, SO(3), rotations)
``models``       kinematic needle models, one class each, registered by name
``sensors``      emulated hardware: clock, noise, pipeline, registered by kind
``observers``    state estimators, registered by type
``experiments``  config schema, input schedules and the batch runner
``io``           the results file (a public contract, see docs/reference/results-file.md)
``metrics``      error records computed from a results file
``reports``      paper-form tables and plots built from the metrics
``cli``          the ``needle`` command
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__"]
