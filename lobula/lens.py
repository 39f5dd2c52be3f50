"""Lens distortion: the Kannala–Brandt (OpenCV fisheye, "equidistant") and radial–tangential models, the
rays a distorted image's pixels see, and the maps that resample such an image onto a pinhole camera.

The velocity pipeline works in normalised pinhole coordinates (x, y) = (X/Z, Y/Z). A wide or fisheye
lens's frames are resampled onto a pinhole camera once per frame (:func:`undistortion_maps`, one map
made at opening), after which every angle the pipeline makes — flow to angular rates, the receptive
fields, the gyro's derotation, the epipole, depth — is exact for that pinhole camera.

Kannala–Brandt: a ray at angle θ from the optical axis lands at distorted radius
θ_d = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸) (normalised units) in the direction it points; pixel
u = fx·θ_d·cos φ + cx. Radial–tangential: OpenCV's (k1, k2, p1, p2[, k3]) on (x, y).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: the names a model goes by -> the one used here
MODEL_NAMES = {"kannala-brandt": "kannala-brandt", "kb4": "kannala-brandt", "equidistant": "kannala-brandt",
               "fisheye": "kannala-brandt", "radtan": "radtan", "radial-tangential": "radtan", "plumb_bob": "radtan"}


@dataclass(frozen=True)
class LensDistortion:
    """A lens's distortion: ``model`` "kannala-brandt" (k1..k4) or "radtan" (k1, k2, p1, p2[, k3]),
    ``coeffs`` dimensionless (normalised image units)."""

    model: str
    coeffs: tuple

    def __post_init__(self):
        model = MODEL_NAMES.get(str(self.model).lower())
        if model is None:
            raise ValueError(f"unknown lens model {self.model!r}; choose one of {', '.join(sorted(MODEL_NAMES))}")
        c = tuple(float(x) for x in self.coeffs)
        need = (4,) if model == "kannala-brandt" else (4, 5)
        if len(c) not in need or not all(np.isfinite(c)):
            raise ValueError(f"lens model {model} takes {' or '.join(map(str, need))} finite coefficients, got {list(c)}")
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "coeffs", c)

    def to_dict(self) -> dict:
        """{"model": ..., "coeffs": [...]}, as a camera.json's "distortion" holds it."""
        return dict(model=self.model, coeffs=list(self.coeffs))

    @classmethod
    def parse(cls, text: str) -> "LensDistortion":
        """From ``text`` "MODEL:c1,c2,..." (the command line's form), e.g. "kannala-brandt:0.05,-0.01,0,0"."""
        model, _, rest = str(text).partition(":")
        try:
            coeffs = [float(x) for x in rest.split(",") if x.strip()]
        except ValueError:
            raise ValueError(f"lens {text!r}: coefficients must be numbers, as MODEL:c1,c2,...") from None
        return cls(model, tuple(coeffs))


def read_lens(path: str | Path) -> LensDistortion | None:
    """The optional "distortion" object ({"model": ..., "coeffs": [...]}) of the camera.json at ``path``; None
    without one.
    A malformed one raises ValueError naming the file."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if not isinstance(d, dict) or "distortion" not in d or d["distortion"] in (None, "none"):
        return None
    dist = d["distortion"]
    try:
        return LensDistortion(dist["model"], tuple(dist["coeffs"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: its \"distortion\" must be {{\"model\": one of {', '.join(sorted(MODEL_NAMES))}, "
                         f"\"coeffs\": [numbers]}} ({exc})") from None


def distort(x: np.ndarray, y: np.ndarray, lens: LensDistortion) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalised coordinates (xd, yd) through ``lens`` of the rays (x, y, 1) (normalised pinhole
    coordinates, any one shape; the result has that shape)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if lens.model == "kannala-brandt":
        r = np.hypot(x, y)
        th = np.arctan(r)
        k1, k2, k3, k4 = lens.coeffs
        th2 = th * th
        th_d = th * (1 + th2 * (k1 + th2 * (k2 + th2 * (k3 + th2 * k4))))
        s = np.where(r > 0, th_d / np.where(r > 0, r, 1.0), 1.0)
        return x * s, y * s
    k1, k2, p1, p2 = lens.coeffs[:4]
    k3 = lens.coeffs[4] if len(lens.coeffs) > 4 else 0.0
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def kb_ray_angles(xd: np.ndarray, yd: np.ndarray, lens: LensDistortion, iterations: int = 20) -> np.ndarray:
    """θ (rad, like xd) of the rays that land at distorted normalised coordinates (xd, yd) of a
    Kannala–Brandt lens (``iterations`` steps of Newton's method on θ_d = θ(1 + k1θ² + …))."""
    th_d = np.hypot(np.asarray(xd, float), np.asarray(yd, float))
    k1, k2, k3, k4 = lens.coeffs
    th = th_d.copy()
    for _ in range(iterations):  # element-wise Newton steps on whole arrays
        th2 = th * th
        f = th * (1 + th2 * (k1 + th2 * (k2 + th2 * (k3 + th2 * k4)))) - th_d
        df = 1 + th2 * (3 * k1 + th2 * (5 * k2 + th2 * (7 * k3 + th2 * 9 * k4)))
        th = th - f / df
    return th


def pixel_rays(camera, lens: LensDistortion | None, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pinhole coordinates (x, y) = (X/Z, Y/Z) of the rays pixels (u, v) of ``camera`` (its K)
    see through ``lens`` (None: a pinhole). u, v: px, any one shape; x, y have that shape. Rays at 90° or
    more from the axis give NaN."""
    xd, yd = (np.asarray(u, float) - camera.cx) / camera.fx, (np.asarray(v, float) - camera.cy) / camera.fy
    if lens is None:
        return xd, yd
    if lens.model == "kannala-brandt":
        th = kb_ray_angles(xd, yd, lens)
        rd = np.hypot(xd, yd)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(rd > 0, np.tan(th) / np.where(rd > 0, rd, 1.0), 1.0)
        s = np.where(th < np.pi / 2 - 1e-6, s, np.nan)
        return xd * s, yd * s
    # Radial–tangential: the fixed-point iteration OpenCV's undistortPoints runs, to convergence.
    k1, k2, p1, p2 = lens.coeffs[:4]
    k3 = lens.coeffs[4] if len(lens.coeffs) > 4 else 0.0
    x, y = xd.copy(), yd.copy()
    for _ in range(100):  # element-wise on whole arrays
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
        y = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
    return x, y


def undistortion_maps(camera, lens: LensDistortion, target: str = "same-k"):
    """Maps (map_x, map_y) (H, W) float32 px for cv2.remap that resample a distorted image of ``camera``'s size and
    K onto a pinhole camera, and that pinhole camera.

    target: "same-k" (the same K: the centre keeps its resolution, a wide lens's periphery is cropped) or
    "optimal" (a focal length chosen so the whole width's horizontal field of view fits, up to 150°).
    """
    from dataclasses import replace

    w, h = camera.width, camera.height
    if target == "same-k":
        out = camera
    elif target == "optimal":
        # The horizontal field of view the raw image's left and right edges see, capped at 150° (tan grows
        # without bound towards 90°, and the pinhole's periphery would hold no pixels worth having).
        xs, _ = pixel_rays(camera, lens, np.array([-0.5, w - 0.5]), np.array([camera.cy, camera.cy]))
        half = np.minimum(np.abs(np.arctan(xs)), np.radians(75.0))
        half = np.where(np.isfinite(half), half, np.radians(75.0))
        f = float(0.5 * w / np.tan(np.max(half)))
        out = replace(camera, fx=f, fy=f * camera.fy / camera.fx)
    else:
        raise ValueError(f"unknown undistortion target {target!r}; choose same-k or optimal")
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    x, y = (u - out.cx) / out.fx, (v - out.cy) / out.fy
    xd, yd = distort(x, y, lens)
    map_x = (camera.fx * xd + camera.cx).astype(np.float32)
    map_y = (camera.fy * yd + camera.cy).astype(np.float32)
    return (map_x, map_y), out


def undistort(image: np.ndarray, maps) -> np.ndarray:
    """``image`` (H, W) resampled through :func:`undistortion_maps`' ``maps`` (bilinear, edges replicated);
    (H, W), its dtype and units."""
    import cv2

    return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
