"""A rolling shutter's rows, each exposed at its own time: the flow put back on the frames' times for rotation.

A CMOS sensor with a rolling shutter reads its rows one after another: row ``v`` of a frame stamped t is exposed
at t + δ(v), δ(v) = readout · v / height, the readout being the time from the first row to the last (8–30 ms on
action cameras and phones). A pixel's flow over a pair (t0, t1) then spans (t0 + δ, t1 + δ), and the camera's
rotation over that span is not the rotation over (t0, t1) that the derotation takes from the gyro: the two differ
by the change of the angular velocity across the pair times δ, which on a camera turning by ±5° at 0.3–1.5 Hz is
a fifth of a walk's translational flow. Read at 320×240 with a 16 ms readout, such a run's offline error grows
twelvefold (0.0032 → 0.037 m/s); at 33 ms it is never observable.

:func:`global_shutter_flow` turns each pixel's two rays into the camera's orientation at the frames' own times,
C0 = Q(t0)ᵀ·Q(t0 + δ) and C1 = Q(t1)ᵀ·Q(t1 + δ) from the gyro's attitude Q, so that what follows (the heading,
the derotation, the fields) sees the rotation a global shutter would have. What is left is the translation's
own δ, a timing error of at most the readout on a signal the readout low-passes at 1 Hz. Where a lens is
resampled onto a pinhole, δ is the raw sensor row's (:func:`pixel_delays`).
"""
from __future__ import annotations

import numpy as np

__all__ = ["pixel_delays", "global_shutter_flow", "DELAY_LEVELS"]

#: the delays are taken in this many equal steps over the readout: ¼ ms at a 32 ms readout, where the turn's
#: change over a pair (rad/s) moves the flow by that times ¼ ms over the pair's gap (a turn speeding up by 0.8 rad/s
#: over 0.2 s: 0.001 1/s, against 0.0035 in steps of 1 ms)
DELAY_LEVELS = 128


def pixel_delays(y: np.ndarray, camera, readout_s: float, lens_maps=None) -> np.ndarray:
    """δ (H, W) s: when each pixel of the flow's grid was exposed after its frame's time stamp.

    Parameters
    ----------
    y : ndarray, (H, W)
        The grid's normalised y coordinates (the camera's rows through fy, cy).
    camera : lobula.camera.PinholeCamera
        The pinhole the frames are read as.
    readout_s : float
        s: the first row's exposure to the last's (0: a global shutter).
    lens_maps : tuple of ndarray, optional
        (map_x, map_y) (camera.height, camera.width) px: where each pinhole pixel lies on the raw sensor
        (:func:`lobula.lens.undistortion_maps`); the raw row then sets δ.

    Returns
    -------
    ndarray, (H, W)
    """
    y = np.asarray(y, float)
    if lens_maps is None:
        rows = camera.fy * y + camera.cy
    else:
        import cv2

        map_y = np.asarray(lens_maps[1], np.float32)
        rows = cv2.resize(map_y, (y.shape[1], y.shape[0]), interpolation=cv2.INTER_LINEAR).astype(float)
    return readout_s * np.clip(rows, 0.0, camera.height - 1.0) / camera.height


def global_shutter_flow(x: np.ndarray, y: np.ndarray, flow: np.ndarray, t0: float, t1: float, delays: np.ndarray,
                        attitude, levels: int = DELAY_LEVELS) -> np.ndarray:
    """The flow (2, H, W) 1/s a global shutter at t0 and t1 would have seen, as far as the rotation goes.

    Each pixel's ray is turned from its own exposure time into the camera's orientation at t0, and the ray it
    flows to from that pixel's exposure time at t1 (the row it reaches, :func:`pixel_delays`' δ there) into the
    orientation at t1; the flow between them is then laid back on the grid the pixels had at t0 (a pixel read
    late during a turn sits where the turn moved it).

    Parameters
    ----------
    x, y : ndarray, (H, W)
        The grid's normalised coordinates (the pixels at t0), evenly spaced.
    flow : ndarray, (2, H, W)
        1/s: the measured flow over the pair.
    t0, t1 : float
        s: the pair's frame times.
    delays : ndarray, (H, W)
        s: each pixel's exposure after its frame's time stamp (:func:`pixel_delays`).
    attitude : callable
        t (k,) s -> camera → reference rotations (k, 3, 3) (the gyro's attitude).
    levels : int
        The delays are rounded to this many equal steps over their range (one rotation pair per step).

    Returns
    -------
    ndarray, (2, H, W)
    """
    import cv2

    dmax = float(np.max(delays))
    if dmax <= 0.0:
        return flow
    step = dmax / max(levels - 1, 1)
    tb = np.arange(levels) * step
    q = attitude(np.concatenate([[t0, t1], t0 + tb, t1 + tb]))
    c0 = np.einsum("ji,bjk->bik", q[0], q[2:2 + levels])  # Q(t0)ᵀ·Q(t0 + δ)
    c1 = np.einsum("ji,bjk->bik", q[1], q[2 + levels:])  # Q(t1)ᵀ·Q(t1 + δ)
    dt = t1 - t0
    gx, gy = float(x[0, 1] - x[0, 0]), float(y[1, 0] - y[0, 0])  # the grid's spacing, normalised
    x, y = x.astype(np.float32), y.astype(np.float32)  # float32 throughout: a few µrad, far below the flow's noise
    x1, y1 = x + np.float32(dt) * flow[0], y + np.float32(dt) * flow[1]
    cols = np.nan_to_num((x1 - x[0, 0]) / np.float32(gx)).astype(np.float32)  # a pixel without flow stays without
    rows = np.nan_to_num((y1 - y[0, 0]) / np.float32(gy)).astype(np.float32)
    d1 = cv2.remap(delays.astype(np.float32), cols, rows, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    x1, y1 = x1.astype(np.float32), y1.astype(np.float32)
    X0, Y0 = _turned(c0, np.rint(delays / step).astype(np.intp), x, y)
    X1, Y1 = _turned(c1, np.clip(np.rint(d1 / step), 0, levels - 1).astype(np.intp), x1, y1)
    moved = np.stack([(X1 - X0) / np.float32(dt), (Y1 - Y0) / np.float32(dt)])
    # back onto the grid: the value at pixel p is the one found at p's own place at t0, p + (X0 − x, Y0 − y)
    j = np.arange(x.shape[1], dtype=np.float32)[None, :] - (X0 - x) / np.float32(gx)
    i = np.arange(x.shape[0], dtype=np.float32)[:, None] - (Y0 - y) / np.float32(gy)
    out = np.stack([cv2.remap(m, j, i, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for m in moved])
    return out.astype(flow.dtype, copy=False)


def _turned(r: np.ndarray, idx: np.ndarray, x: np.ndarray, y: np.ndarray):
    """(x', y'): the rays (x, y, 1) (any shape S) turned by the rotations r[idx] (r (levels, 3, 3), idx of shape S),
    in normalised coordinates: :func:`lobula.epipole.turn` with a rotation per ray, its entries gathered one by one
    (5.8 ms a 320×240 pair; gathering whole matrices and turning through ``turn``, 9.0 ms)."""
    m = [r[:, i, j].astype(np.float32)[idx] for i in range(3) for j in range(3)]
    qz = m[6] * x + m[7] * y + m[8]
    return (m[0] * x + m[1] * y + m[2]) / qz, (m[3] * x + m[4] * y + m[5]) / qz
