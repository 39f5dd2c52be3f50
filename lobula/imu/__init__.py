"""The inertial measurement unit: forward acceleration from the accelerometer and the camera's rotation
from the gyroscope (what the fly's halteres and their mechanosensors supply the fly).

An accelerometer reads specific force f = a − g (plus bias) in the camera frame.
Forward acceleration needs gravity removed, and the recording may start in motion,
so nothing assumes an initial rest. Instead: the gyroscope (its bias estimated where the
camera is still, :func:`gyro_bias`) tracks the camera's orientation, the
specific force is rotated into the first frame where gravity is a constant vector.
Offline that vector is the mean over a long centred window (the platform's mean
acceleration over a bounded track is ~0); online it is a reference set over the first
quarter second and updated slowly (:func:`online_gravity`), so its error is nearly a
constant offset (the start's acceleration) that the readout's offset state learns from
vision. The attitude that removes gravity integrates the gyro less its bias: the still-camera
estimate, fused with the one the flow's heading fit learns (:func:`fused_gyro_bias`) where the
camera turns without stopping. What the bias's error leaves (gravity ramping through the
forward axis) is the readout's ramp state, not fitted here. Samples are then averaged over
each flow interval and interpolated to the flow's time stamps.

The gyro is integrated with the rate taken linear between samples (trapezoid plus coning,
:func:`rotation_increments`). For the image (derotation, heading, fields) a turning camera's
gyro bias and scale error are learned from the flow itself
(:class:`lobula.epipole.HeadingBiasEstimator`) and :class:`GyroAttitude` integrates with
them as they are learned.

Modules: :mod:`lobula.imu.gyro` (bias, attitude), :mod:`lobula.imu.gravity` (gravity removed, the
forward acceleration and its error bounds), :mod:`lobula.imu.resample` (samples at the frames' times).
"""
from .gravity import (ACCEL_CORRELATION_S, G, GRAVITY_INIT_S, GRAVITY_WINDOW_S, LEAK_WINDOW_S, attitude_leak,
                      forward_acceleration, forward_axis, gravity_direction, gravity_drift_std,
                      gravity_free_acceleration, gravity_time_constant, leak_walk, local_linear, online_gravity,
                      transport_rate)
from .gyro import (GYRO_BIAS_PRIOR, GYRO_BIAS_WALK, GYRO_NOISE_DENSITY, GYRO_SCALE_PRIOR, HEADING_BIAS_STD_SCALE,
                   HEADING_FIT_BIAS_PRIOR, MIN_RESIDUALS, RESIDUAL_GATE, RESIDUAL_RATE_PRIOR_STD, GyroAttitude,
                   fused_gyro_bias, gyro_bias, orientation_from_gyro, rotation_increments, vision_gyro_bias)
from .resample import resample_to, turn_rate

__all__ = ["ACCEL_CORRELATION_S", "G", "GRAVITY_INIT_S", "GRAVITY_WINDOW_S", "LEAK_WINDOW_S", "GYRO_BIAS_PRIOR",
           "GYRO_BIAS_WALK", "GYRO_NOISE_DENSITY", "GYRO_SCALE_PRIOR", "HEADING_BIAS_STD_SCALE",
           "HEADING_FIT_BIAS_PRIOR", "MIN_RESIDUALS", "RESIDUAL_GATE", "RESIDUAL_RATE_PRIOR_STD", "GyroAttitude",
           "attitude_leak", "forward_acceleration", "forward_axis", "fused_gyro_bias", "gravity_direction",
           "gravity_free_acceleration", "gravity_drift_std", "gravity_time_constant", "gyro_bias", "leak_walk",
           "local_linear", "online_gravity",
           "orientation_from_gyro", "resample_to", "rotation_increments", "transport_rate", "turn_rate",
           "vision_gyro_bias"]
