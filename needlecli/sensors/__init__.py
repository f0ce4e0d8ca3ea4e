"""Emulated hardware. Sensor kinds in :data:`SENSORS`, measurement pipelines in :data:`PIPELINES`
(each imported on first use)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from needlecli.registry import Registry, lazy_attributes

if TYPE_CHECKING:
    from needlecli.sensors.base import Pipeline, Sensor

SENSORS: Registry[type[Sensor]] = Registry("sensor type", group="needlecli.sensors", base="needlecli.sensors.base:Sensor", builtins={
    **{name: "needlecli.sensors.statistical" for name in ("position", "encoder", "elastography", "tangent", "bfield")},
    "image_plane": "needlecli.sensors.plane",
    "transverse": "needlecli.sensors.transverse",
    "insertion": "needlecli.sensors.insertion",
})
PIPELINES: Registry[type[Pipeline]] = Registry("measurement pipeline", group="needlecli.pipelines", base="needlecli.sensors.base:Pipeline", builtins={
    "gaussian": "needlecli.sensors.base",
    "image": "needlecli.sensors.imaging.pipeline",
})

_LAZY = {  # the contract, imported on first use (this package's import is light: ``needle list``)
    "MeasurementStream": "needlecli.sensors.base",
    "Pipeline": "needlecli.sensors.base",
    "Sensor": "needlecli.sensors.base",
    "SensorSettings": "needlecli.sensors.base",
}

__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = ["SENSORS", "PIPELINES", "MeasurementStream", "Pipeline", "Sensor", "SensorSettings"]
