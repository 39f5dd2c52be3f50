"""The camera's trajectory from its estimated velocity and the gyro's attitude, for comparison with a
robotics trajectory (the TUM format that evo and the TUM RGB-D tools read)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def world_velocity(v_hat: np.ndarray, heading: np.ndarray, attitude: np.ndarray) -> np.ndarray:
    """The camera's 3-D velocity in the first frame's axes (m/s, (n, 3)).

    Parameters
    ----------
    v_hat : ndarray, (n,)
        m/s: forward velocity along the optical axis (NaN where not observable).
    heading : ndarray, (n, 2)
        The epipole (v_x/v_z, v_y/v_z), normalised (NaN read as 0: along the axis).
    attitude : ndarray, (n, 4)
        Quaternions (x, y, z, w) taking camera-frame vectors into the first frame's.

    Returns
    -------
    ndarray, (n, 3)
        m/s, NaN where v_hat is.
    """
    e = np.nan_to_num(np.asarray(heading, float))
    v_cam = np.asarray(v_hat, float)[:, None] * np.column_stack([e, np.ones(len(e))])
    return Rotation.from_quat(np.asarray(attitude, float)).apply(np.nan_to_num(v_cam)) + 0.0 * v_cam


def integrate_positions(t: np.ndarray, v_world: np.ndarray) -> np.ndarray:
    """Positions (m, (n, 3)) from the first observable estimate on, the trapezoid rule over t (n,) s.

    Where the velocity (n, 3) m/s is NaN after that, the last finite one is held (dead reckoning across
    the gap); before it the positions are NaN.
    """
    v = np.asarray(v_world, float)
    ok = np.all(np.isfinite(v), axis=1)
    out = np.full(v.shape, np.nan)
    if not ok.any():
        return out
    k0 = int(np.argmax(ok))
    idx = np.maximum.accumulate(np.where(ok, np.arange(len(v)), -1))[k0:]
    held = v[idx]
    steps = 0.5 * (held[1:] + held[:-1]) * np.diff(np.asarray(t, float)[k0:])[:, None]
    out[k0:] = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, 0)])
    return out


def tum_rows(t: np.ndarray, v_hat: np.ndarray, heading: np.ndarray, attitude: np.ndarray) -> np.ndarray:
    """TUM trajectory rows (m, 8): timestamp s, position x y z m, orientation qx qy qz qw, camera → first frame.

    One row per estimate from the first observable one on (:func:`integrate_positions`); t (n,) s,
    v_hat (n,) m/s, heading (n, 2), attitude (n, 4) as :func:`world_velocity` takes them. The scale is the
    estimate's own: an error in v̂ is an error in the path's length.
    """
    p = integrate_positions(t, world_velocity(v_hat, heading, attitude))
    keep = np.all(np.isfinite(p), axis=1)
    return np.column_stack([np.asarray(t, float), p, np.asarray(attitude, float)])[keep]
