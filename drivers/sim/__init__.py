"""The simulated vehicle: worlds, renderer, quadrotor dynamics, IMU model and a mock PX4.

It stands in for the hardware (DESIGN.md): the mock PX4 is reached over real MAVLink and
the camera is a driver like any other, so nothing above drivers/ knows the difference.
Ground truth from here feeds evaluation and the mock PX4's stand-in estimator only.
"""
