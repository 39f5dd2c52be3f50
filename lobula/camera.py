"""Pinhole camera geometry: pixels <-> normalised image coordinates <-> visual angles.

Conventions (camera optical frame, as the RealSense and ROS use it): x right, y down,
z forward along the optical axis. A pixel (u, v) has normalised coordinates
``p = (x, y) = ((u - cx) / fx, (v - cy) / fy)``; the ray through it is ``(x, y, 1)``.
Under pure translation with forward velocity ``v`` a scene point at forward depth
``d`` moves as ``dp/dt = (v / d) * (p - e)`` with ``e`` the epipole (focus of
expansion), so flow in normalised coordinates per second (1/s, equal to rad/s of
visual angle at the principal point) is the natural unit of every flow front end.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

# Colour intrinsics of the Intel RealSense D435i at 640x480 (../shared/data camera.json).
D435I = dict(width=640, height=480, fx=615.8287353515625, fy=615.9053344726562,
             cx=320.0995178222656, cy=245.37171936035156, frame_rate_hz=30.0)


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of a pinhole camera.

    width, height: image size (pixels); fx, fy: focal lengths (pixels);
    cx, cy: principal point (pixels); frame_rate_hz: frames per second; rolling_shutter_s: the time from the
    first row's exposure to the last's (s; 0, the default: a global shutter; :mod:`lobula.rolling_shutter`).
    """

    width: int = D435I["width"]
    height: int = D435I["height"]
    fx: float = D435I["fx"]
    fy: float = D435I["fy"]
    cx: float = D435I["cx"]
    cy: float = D435I["cy"]
    frame_rate_hz: float = D435I["frame_rate_hz"]
    rolling_shutter_s: float = 0.0

    def __post_init__(self):
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera size and focal lengths must be positive, got {self}")
        if self.frame_rate_hz <= 0:
            raise ValueError(f"frame_rate_hz must be positive, got {self.frame_rate_hz}")
        if not 0.0 <= self.rolling_shutter_s <= 1.0 / self.frame_rate_hz:
            raise ValueError(f"rolling_shutter_s must lie between 0 and the frame interval "
                             f"{1.0 / self.frame_rate_hz:.4f} s, got {self.rolling_shutter_s}")

    @classmethod
    def from_json(cls, path: str | Path) -> "PinholeCamera":
        """Read the ``camera.json`` at ``path`` ({"width","height","fx","fy","cx","cy" in px, "frame_rate_hz"}),
        or in the folder ``path`` (a footage folder's)."""
        path = Path(path)
        if path.is_dir():
            path = path / "camera.json"
        try:
            d = json.loads(path.read_text())
            return cls(**{k: d[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "frame_rate_hz")},
                       rolling_shutter_s=float(d.get("rolling_shutter_s", 0.0)))
        except FileNotFoundError:
            raise FileNotFoundError(f"{path}: no camera.json; write one with width, height, fx, fy, cx, cy, frame_rate_hz") from None
        except (KeyError, TypeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"{path}: not a valid camera.json ({exc}); it needs width, height, fx, fy, cx, cy, frame_rate_hz") from None

    def to_dict(self) -> dict:
        """The fields as a dict (px, Hz, s), as a camera.json holds them (rolling_shutter_s only where not 0)."""
        d = asdict(self)
        if not d["rolling_shutter_s"]:
            del d["rolling_shutter_s"]
        return d

    def scaled(self, scale: float) -> "PinholeCamera":
        """The same camera with the image resampled by ``scale`` (0.5 halves each side).

        Pixel centres map as u' = (u + 0.5) * scale - 0.5, which keeps the field of view.
        """
        w, h = int(round(self.width * scale)), int(round(self.height * scale))
        sx, sy = w / self.width, h / self.height
        return replace(self, width=w, height=h, fx=self.fx * sx, fy=self.fy * sy,
                       cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5)

    @property
    def frame_interval_s(self) -> float:
        """Time between frames (s)."""
        return 1.0 / self.frame_rate_hz

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Full horizontal and vertical field of view (degrees)."""
        return (math.degrees(math.atan((self.width - 1 - self.cx) / self.fx) + math.atan(self.cx / self.fx)),
                math.degrees(math.atan((self.height - 1 - self.cy) / self.fy) + math.atan(self.cy / self.fy)))

    def normalised_grid(self, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
        """Normalised coordinates (x, y) of every pixel centre, each of shape (height, width) and ``dtype``."""
        u = (np.arange(self.width, dtype=dtype) - self.cx) / self.fx
        v = (np.arange(self.height, dtype=dtype) - self.cy) / self.fy
        return np.meshgrid(u, v)

    def pixel_to_normalised(self, u, v):
        """Normalised coordinates (x, y) of pixels (u, v) (px, any one shape; the result has that shape)."""
        return (np.asarray(u) - self.cx) / self.fx, (np.asarray(v) - self.cy) / self.fy

    def normalised_to_pixel(self, x, y):
        """Pixels (u, v) (px) of normalised coordinates (x, y) (any one shape; the result has that shape)."""
        return np.asarray(x) * self.fx + self.cx, np.asarray(y) * self.fy + self.cy

    def rotation_homography(self, r: np.ndarray) -> np.ndarray:
        """Pixel homography (3, 3) of a pure rotation: K·r·K⁻¹.

        r (3, 3) takes a ray seen from one orientation to the same ray seen from another
        (v' = r·v); the result takes a pixel (u, v, 1) of the first to the second's.
        """
        k = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        return k @ np.asarray(r, float) @ np.linalg.inv(k)

    def flow_px_to_normalised(self, du_px, dv_px, dt_s: float):
        """Pixel displacement (``du_px``, ``dv_px``: px, any one shape) over ``dt_s`` seconds -> normalised
        flow (u, v) (1/s, that shape)."""
        return np.asarray(du_px) / (self.fx * dt_s), np.asarray(dv_px) / (self.fy * dt_s)


def normalised_to_angles(x, y):
    """Azimuth and elevation (radians) of normalised coordinates x, y (any one shape; the result has that
    shape): atan(x), atan(y / sqrt(1 + x^2)).

    Elevation is positive downward (y down), as in the camera frame.
    """
    x, y = np.asarray(x), np.asarray(y)
    return np.arctan(x), np.arctan2(y, np.sqrt(1.0 + x * x))


def angles_to_normalised(azimuth, elevation):
    """Inverse of :func:`normalised_to_angles`: ``azimuth``, ``elevation`` (radians, any one shape) in,
    normalised coordinates (x, y) of that shape out."""
    az, el = np.asarray(azimuth), np.asarray(elevation)
    x = np.tan(az)
    return x, np.tan(el) * np.sqrt(1.0 + x * x)


def ray_directions(x, y):
    """Unit ray directions (..., 3) in the camera frame for normalised coordinates x, y (...)."""
    d = np.stack([np.asarray(x), np.asarray(y), np.ones_like(np.asarray(x))], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
