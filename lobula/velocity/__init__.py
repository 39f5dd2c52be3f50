"""Forward velocity from a camera and its IMU: the pipeline on a whole footage (:func:`estimate_velocity`)
and frame by frame (:class:`VelocityEstimator`).

Both run the same stages: dense optic flow (a front end, :mod:`lobula.front_ends`), derotated by the
gyro and pooled into the lobula-columnar receptive fields (:mod:`lobula.velocity.fields`), the
accelerometer's forward acceleration with gravity removed (:mod:`lobula.velocity.inertial`), and the
readout that fuses the two (:mod:`lobula.readout`).
"""
from .fields import FieldPooling, FieldRates, PooledPair, field_rates
from .inertial import forward_accel_at, gyro_bias_track, start_accel_prior
from .pipeline import estimate_velocity
from .streaming import VelocityEstimator, VelocityState

__all__ = ["estimate_velocity", "VelocityEstimator", "VelocityState", "field_rates", "FieldRates", "FieldPooling", "PooledPair",
           "forward_accel_at", "gyro_bias_track", "start_accel_prior"]
