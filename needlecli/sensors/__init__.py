"""Emulated hardware. Sensor kinds in :data:`SENSORS`, measurement pipelines in :data:`PIPELINES`."""

from needlecli.sensors import statistical  # noqa: F401  (registers the sensors)
from needlecli.sensors.base import PIPELINES, SENSORS, MeasurementStream, Pipeline, Sensor, SensorSettings

__all__ = ["PIPELINES", "SENSORS", "MeasurementStream", "Pipeline", "Sensor", "SensorSettings"]
