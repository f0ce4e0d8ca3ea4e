"""Emulated imaging hardware: frames rendered from the true needle and measured by image pipelines.

One module per device, registered in :data:`DEVICES` and chosen in a position sensor's ``image:``
section by ``device``:

``us2d``    2D transverse ultrasound following the tip, tip by RANSAC (the high-gain observer paper) -- :mod:`.ultrasound2d`
``us3d``    3D end-fire ultrasound volumes at a fixed pose, tip by segmentation (the multi-rate UKF paper) -- :mod:`.ultrasound3d`
``camera``  overhead camera, OpenCV threshold / contours / minAreaRect, opacity (the magnetic needle EM paper) -- :mod:`.camera`

Shared rendering helpers are in :mod:`.render`; the ``image`` pipeline that runs a device for a sensor
is :mod:`.pipeline`; measuring a pipeline's error on chosen poses is :mod:`.characterize`.
Image settings are in mm and pixels whatever the model's length unit.
"""

from typing import Annotated, Union

from pydantic import Field

from needlecli.sensors.imaging import pipeline  # noqa: F401  (registers the 'image' pipeline)
from needlecli.sensors.imaging.base import DEVICES, Device, ImageSettings
from needlecli.sensors.imaging.camera import CameraSettings, OverheadCamera, bz_command
from needlecli.sensors.imaging.ultrasound2d import TransverseUltrasound, TransverseUltrasoundSettings
from needlecli.sensors.imaging.ultrasound3d import EndFireUltrasound, EndFireUltrasoundSettings

#: the ``image:`` section of a sensor: one schema per device, chosen by ``device``
ImageSection = Annotated[
    Union[TransverseUltrasoundSettings, EndFireUltrasoundSettings, CameraSettings], Field(discriminator="device")
]

__all__ = [
    "DEVICES", "CameraSettings", "Device", "EndFireUltrasound", "EndFireUltrasoundSettings", "ImageSection",
    "ImageSettings", "OverheadCamera", "TransverseUltrasound", "TransverseUltrasoundSettings", "bz_command",
]
