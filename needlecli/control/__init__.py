"""Controllers that close a loop through a sensor while the truth is simulated (config section
``control:``), registered by type in :data:`CONTROLLERS`.

``opacity_bz``  the magnetic needle EM paper's eq. (7): the field's out-of-plane component from the camera's opacity -- :mod:`.opacity_bz`

How the loop runs (sensor in the loop measured frame by frame, interleaved with the truth simulation) is
the experiment layer's :mod:`needlecli.experiments.simulation.closed_loop`; the contract is :class:`~needlecli.control.base.Controller`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from needlecli.registry import Registry, lazy_attributes

if TYPE_CHECKING:
    from needlecli.control.base import Controller

CONTROLLERS: Registry[type[Controller]] = Registry("controller type", group="needlecli.controllers", base="needlecli.control.base:Controller", builtins={
    "opacity_bz": "needlecli.control.opacity_bz",
})


#: the contract, imported on first use (this package's import is light)
__getattr__ = lazy_attributes(__name__, {"Controller": "needlecli.control.base", "ControllerSettings": "needlecli.control.base"})


__all__ = ["CONTROLLERS", "Controller", "ControllerSettings"]
