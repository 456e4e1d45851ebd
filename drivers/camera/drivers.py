"""The camera driver ``[camera] driver`` names, each with its own config table.

======================  =====================================  ==========================
``driver``              module                                 table
======================  =====================================  ==========================
``v4l2``                :mod:`drivers.camera.v4l2` (OpenCV)    ``[v4l2]``
``realsense``           :mod:`drivers.camera.realsense`        ``[realsense]`` (extra
                        (pyrealsense2)                         ``companion[realsense]``)
``oak``                 :mod:`drivers.camera.oak` (depthai)    ``[oak]`` (extra
                                                               ``companion[oak]``)
======================  =====================================  ==========================

The vendor modules import their SDK only when a camera is opened or listed, so a missing
extra is a one-line error naming it, never an ImportError at start-up.
"""

from __future__ import annotations

from drivers.clock import Clock


def open_camera(config, clock: Clock):
    """The (not yet started) driver of ``config.camera.driver``; use it as ``async with``."""
    camera = config.camera
    if camera.driver == "realsense":
        from drivers.camera.realsense import RealSenseCamera
        return RealSenseCamera(camera, config.realsense, clock)
    if camera.driver == "oak":
        from drivers.camera.oak import OakCamera
        return OakCamera(camera, config.oak, clock)
    from drivers.camera.v4l2 import V4l2Camera
    return V4l2Camera(camera, config.v4l2, clock)
