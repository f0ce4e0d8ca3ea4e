"""Emulated hardware. Sensor kinds in :data:`SENSORS`, measurement pipelines in :data:`PIPELINES`
(each imported on first use)."""

from needlecli.sensors.base import PIPELINES, SENSORS, MeasurementStream, Pipeline, Sensor, SensorSettings

__all__ = ["PIPELINES", "SENSORS", "MeasurementStream", "Pipeline", "Sensor", "SensorSettings"]
