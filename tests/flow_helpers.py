"""Helpers the gyro-against-image tests share: exact flow of a camera that turns while it walks."""
import numpy as np

from lobula.epipole import rotational_flow


def swaying_flow(k, n=200, m=600, noise=0.0, seed=0, roll_sway=0.0):
    """Flow (n, 2, m) 1/s of a camera turning at k·gyro while it walks forward at 1 m/s and sways sideways and
    bounces in step with its pan and tilt (a hand-held walk), and sideways with its roll by ``roll_sway`` m/s per
    rad/s, before points 1-10 m away; and the gyro (n, 3)."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-0.6, 0.6, m), rng.uniform(-0.45, 0.45, m)
    t = np.arange(n) / 30.0
    gyro = np.stack([0.3 * np.sin(2 * np.pi * 0.9 * t), 0.3 * np.sin(2 * np.pi * 1.3 * t + 1),
                     0.2 * np.sin(2 * np.pi * 0.6 * t + 2)], -1)
    # m/s: sway with pan (and roll), bounce with tilt
    vel = np.stack([0.8 * gyro[:, 1] + roll_sway * gyro[:, 2], -0.8 * gyro[:, 0], np.ones(n)], -1)
    depth = rng.uniform(1.0, 10.0, (n, m))
    rot = np.stack([rotational_flow(k * w, x, y) for w in gyro])
    trans = np.stack([x * vel[:, 2, None] - vel[:, 0, None], y * vel[:, 2, None] - vel[:, 1, None]], 1) / depth[:, None]
    return x, y, rot + trans + noise * rng.standard_normal((n, 2, m)), gyro
