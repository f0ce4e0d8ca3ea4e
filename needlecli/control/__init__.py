"""Controllers that close a loop through a sensor while the truth is simulated (config section
``control:``), registered by type in :data:`CONTROLLERS`.

``opacity_bz``  seed 004 eq. (7): the field's out-of-plane component from the camera's opacity -- :mod:`.opacity_bz`

How the loop runs (sensor in the loop measured frame by frame, interleaved with the truth simulation) is
the experiment layer's :mod:`needlecli.experiments.closed_loop`; the contract is :class:`~needlecli.control.base.Controller`.
"""

from needlecli.control.base import CONTROLLERS, Controller, ControllerSettings

__all__ = ["CONTROLLERS", "Controller", "ControllerSettings"]
