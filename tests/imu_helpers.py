"""Helpers the IMU tests share: the gyro integrated into attitudes, as a strapdown solution."""
import numpy as np
from scipy.spatial.transform import Rotation


def integrate_gyro(t, gyro, r0):
    """Attitudes (n, 3, 3) from r0 (3, 3) by the gyro (n, 3) rad/s at t (n,) s: trapezoidal increments with the
    second-order coning correction dt²/12·(ω_k × ω_k+1)."""
    dt = np.diff(t)
    r = [r0]
    for k in range(len(t) - 1):
        phi = 0.5 * (gyro[k] + gyro[k + 1]) * dt[k] + dt[k] ** 2 / 12 * np.cross(gyro[k], gyro[k + 1])
        r.append(r[-1] @ Rotation.from_rotvec(phi).as_matrix())
    return np.array(r)
