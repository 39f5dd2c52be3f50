"""The LC fields on the two eyes: mirror-symmetric Gaussian receptive fields, with their weights over
each eye's ommatidial pairs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..compound_eye import CompoundEye
from .config import EyeFieldConfig


@dataclass
class EyeFields:
    """LC fields: ``centres_deg`` (F, 2) deg (az, el), ``eye`` (F,) (0 right, 1 left), unit centre
    ``directions`` (F, 3), ``theta`` (F,) rad from ẑ, the (F, P) pair ``weights`` (dimensionless, peak 1),
    ``mirror`` (F,): the index of each field's mirror field, and ``size_deg``, the fields' FWHM (degrees)."""

    centres_deg: np.ndarray
    eye: np.ndarray
    directions: np.ndarray
    theta: np.ndarray
    weights: np.ndarray
    mirror: np.ndarray
    size_deg: float

    @property
    def n_fields(self) -> int:
        """Number of fields, F."""
        return len(self.eye)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (radians) between unit vectors, broadcast over leading dims."""
    return np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0))


def eye_fields(eye: CompoundEye, config: EyeFieldConfig) -> EyeFields:
    """Tile both eyes of ``eye`` with mirror-symmetric Gaussian fields as ``config`` says; weights over the
    eye's own pairs."""
    from ..compound_eye import eye_directions

    sp = config.spacing
    a0, a1 = config.azimuth_deg
    e0, e1 = config.elevation_deg
    naz = max(1, int(math.floor((a1 - a0) / sp + 1e-9)) + 1)
    nel = max(1, int(math.floor((e1 - e0) / sp + 1e-9)) + 1)
    az = a0 + 0.5 * ((a1 - a0) - (naz - 1) * sp) + sp * np.arange(naz)
    el = e0 + 0.5 * ((e1 - e0) - (nel - 1) * sp) + sp * np.arange(nel)
    AZ, EL = (x.ravel() for x in np.meshgrid(az, el, indexing="xy"))
    present = [k for k in (0, 1) if (eye.eye == k).any()]
    cen = np.concatenate([np.stack([AZ if k == 0 else -AZ, EL], -1) for k in present])
    f_eye = np.concatenate([np.full(len(AZ), k) for k in present])
    nf = len(AZ)
    mirror = (np.concatenate([np.arange(nf) + nf, np.arange(nf)]) if len(present) == 2
              else np.arange(nf))
    dirs = eye_directions(np.radians(cen[:, 0]), np.radians(cen[:, 1]))
    ang = _angle(dirs[:, None, :], eye.pair_midpoint[None, :, :])               # (F, P)
    fwhm = math.radians(config.size_deg)
    w = np.exp(-4.0 * math.log(2.0) * (ang / fwhm) ** 2)
    w *= (ang <= 1.5 * fwhm) & (f_eye[:, None] == eye.eye[eye.pairs_a][None, :])
    theta = _angle(dirs, np.array([0.0, 0.0, 1.0]))
    return EyeFields(cen, f_eye, dirs, theta, w, mirror, float(config.size_deg))
