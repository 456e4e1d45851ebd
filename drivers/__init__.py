"""The boundary to the world: everything that touches a wire or a device.

A driver converts the outside world's conventions (PX4's NED/FRD frames and boot time, device
timestamps and pixel formats) into the project's own at the boundary, so nothing in
:mod:`autonomy` or :mod:`companion` ever sees them. Drivers may import :mod:`autonomy`, never
:mod:`companion`.

Later issues fill ``mavlink/`` (pymavlink link and the PX4 autopilot interface), ``camera/``
(V4L2, RealSense, OAK, recorded replay) and ``sim/`` (the simulated vehicle, renderer and mock
PX4 that stand in for the hardware).
"""
