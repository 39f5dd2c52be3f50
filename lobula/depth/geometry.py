"""What every depth estimator shares: the pixels' offsets and angles from the epipole, the inverse
time to contact z turned into depth, and the checks and numpy/torch plumbing that let one code
path serve both kinds of array.
"""
from __future__ import annotations

import math

import numpy as np

from .._optional import is_tensor, torch
from lobula.camera import PinholeCamera


def _to_tensor(a, device=None, dtype=None) -> torch.Tensor:
    if is_tensor(a):
        return a.to(device=device if device is not None else a.device,
                    dtype=dtype if dtype is not None else a.dtype)
    t = torch.as_tensor(np.asarray(a))
    if dtype is None and not t.is_floating_point():
        dtype = torch.get_default_dtype()
    return t.to(device=device, dtype=dtype if dtype is not None else t.dtype)


def _like_input(t, as_numpy: bool):
    return t.detach().cpu().numpy() if as_numpy and is_tensor(t) else t


def _as_array(a):
    """A tensor stays one, anything else becomes a numpy array; integers become floating point
    (float32, torch's default, for numpy)."""
    if is_tensor(a):
        return a if a.is_floating_point() else a.to(torch.get_default_dtype())
    a = np.asarray(a)
    return a if np.issubdtype(a.dtype, np.floating) else a.astype(np.float32)


def _xp(a):
    """The array library of ``a``: torch for a tensor, else numpy (their functions used here share names)."""
    return torch if is_tensor(a) else np


def _quiet(a):
    """For a computation on ``a`` that divides by 0 or meets NaN on purpose: no autograd for a tensor,
    no floating-point warnings for numpy (0/0 → NaN, x/0 → inf, as torch gives them)."""
    return torch.no_grad() if is_tensor(a) else np.errstate(divide="ignore", invalid="ignore")


def _clamp(a, lo=None, hi=None):
    """``a`` limited to [lo, hi] (None: unbounded), either kind."""
    return a.clamp(lo, hi) if is_tensor(a) else np.clip(a, lo, hi)


def _median_low(a):
    """Median of a 1-D array; of an even count the lower middle value (torch's rule, for both kinds)."""
    if is_tensor(a):
        return a.median()
    k = (a.size - 1) // 2
    return np.partition(a, k)[k]


def _check_flow(flow, camera: PinholeCamera) -> tuple[object, bool]:
    """Flow as a floating array of shape (2, H, W) matching the camera (a tensor stays a tensor, any
    other input becomes numpy, see :func:`_as_array`); plus 'was not a tensor'."""
    as_numpy = not is_tensor(flow)
    f = _as_array(flow)
    if f.ndim != 3 or f.shape[0] != 2:
        raise ValueError(f"flow must have shape (2, H, W) (x and y components, 1/s), got {tuple(f.shape)}")
    if (f.shape[1], f.shape[2]) != (camera.height, camera.width):
        raise ValueError(f"flow is {f.shape[1]}x{f.shape[2]} (HxW) but the camera is "
                         f"{camera.height}x{camera.width}; rescale the camera with camera.scaled()")
    return f, as_numpy


def _epipole(epipole) -> tuple[float, float]:
    e = np.asarray(epipole.detach().cpu() if is_tensor(epipole) else epipole, dtype=float).ravel()
    if e.shape != (2,) or not np.all(np.isfinite(e)):
        raise ValueError(f"epipole must be two finite normalised coordinates (ex, ey), got {epipole!r}")
    return float(e[0]), float(e[1])


def _grid(camera: PinholeCamera, like) -> tuple[object, object]:
    """The camera's normalised pixel coordinates x, y (H, W), of the kind, dtype (and device) of ``like``."""
    x, y = camera.normalised_grid(np.float64)
    if not is_tensor(like):
        return x.astype(like.dtype, copy=False), y.astype(like.dtype, copy=False)
    return (torch.as_tensor(x).to(device=like.device, dtype=like.dtype),
            torch.as_tensor(y).to(device=like.device, dtype=like.dtype))


def _offsets(camera: PinholeCamera, epipole, like):
    """q = p − e, shape (2, H, W), normalised units, of the kind of ``like``."""
    ex, ey = _epipole(epipole)
    x, y = _grid(camera, like)
    return _xp(like).stack([x - ex, y - ey])


def angle_from_epipole(camera: PinholeCamera, epipole) -> np.ndarray:
    """Angle (degrees) between the ray (x, y, 1) of each pixel of ``camera`` and the epipole's ray, (H, W);
    epipole (ex, ey) normalised."""
    ex, ey = _epipole(epipole)
    x, y = camera.normalised_grid(np.float64)
    # atan2(|a×b|, a·b) stays accurate for small angles, unlike acos of the dot product.
    a = np.stack([x, y, np.ones_like(x)], axis=-1)
    b = np.array([ex, ey, 1.0])
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(cross, a @ b))


def _speed(v) -> float:
    """Forward speed as a Python float (m/s); accepts a 0-d tensor."""
    return float(v.item() if is_tensor(v) else v)


def rate_to_depth(rate, v: float, max_depth_m: float, extra_valid=None) -> tuple[object, object]:
    """d = v / z with validity: z finite, of the sign of v (approach: expansion), d ≤ max_depth_m.

    rate: (H, W) z in 1/s; v: forward speed (m/s); max_depth_m: m; extra_valid: (H, W) bool, ANDed
    into the mask (None: none). Returns depth ((H, W), m, NaN where invalid) and the (H, W) bool mask.
    v = 0 or non-finite makes every pixel invalid: depth is then
    unobservable from flow, and saying so beats returning 0 or inf. Tensors or numpy arrays.
    """
    xp = _xp(rate)
    if not math.isfinite(v) or v == 0.0:
        valid = xp.zeros_like(rate, dtype=bool)
    else:
        with _quiet(rate):
            d = v / rate
            valid = xp.isfinite(rate) & (rate * math.copysign(1.0, v) > 0) & xp.isfinite(d) & (d <= max_depth_m)
    if extra_valid is not None:
        valid = valid & extra_valid
    depth = xp.full_like(rate, float("nan"))
    if valid.any():
        depth[valid] = v / rate[valid]
    return depth, valid
