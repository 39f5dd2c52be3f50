"""Haltere-driven gaze stabilisation: the head counter-rotates on the haltere's angular velocity.

A fly does not only subtract its own rotation from what its eyes see; it keeps much of the
rotation off the retina. The halteres sense the body's angular velocity and drive the neck
motor system, so the head turns against the body's turn (compensatory head roll driven by
the halteres: Hengstenberg 1988, J Comp Physiol A 163:151; Sandeman & Markl 1980, J Exp
Biol 85:43; gaze stabilisation in flies reviewed by Hardcastle & Krapp 2016, Curr Biol
26:R1077). Visual and haltere feedback combine there; this module models the haltere's
feed-forward part alone, so nothing visual is needed to stabilise the gaze.

Model (per axis of the body, i.e. camera, frame; small head angles): the head's rotation
vector θ relative to the body follows

    dθ/dt = −gain·ω_body − θ/τ_return,    |θ_i| ≤ limit,

ω_body the haltere's (gyroscope's) angular velocity: the neck cancels a fraction ``gain``
of the body's rotation and the neck's elasticity returns the head to the body axis with
time constant ``tau_return_s``, within the neck's range ``limit_deg``. The retina then
turns at about (1 − gain)·ω_body for turns faster than 1/τ_return. Causal: θ at sample k
uses ω up to sample k − 1 (the neck acts after the haltere).

Frames: the head-to-body rotation R(θ) maps directions fixed in the head (the ommatidial
axes) to the body (camera) frame, d_body = R·d_head. :func:`retinal_rotation` gives the head's
angular velocity in its own frame (what the eye's haltere subtraction must predict): the
body's plus the neck's, the latter from the head angles themselves (an efference copy of
the neck motor command).

Shapes: t (T,), ω (T, 3) rad/s, θ (T, 3) rad, R (T, 3, 3).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["GazeConfig", "head_angles", "head_rotation", "retinal_rotation", "fixation_reference"]


@dataclass
class GazeConfig:
    """Neck reflex parameters.

    gain: fraction of the body's angular velocity the neck cancels (0: no stabilisation).
    tau_return_s: time constant (s) with which the head relaxes back to the body axis.
    limit_deg: the neck's range per axis (deg); the head stops there.
    """

    gain: float = 0.8
    tau_return_s: float = 0.5
    limit_deg: float = 20.0

    def __post_init__(self):
        if not (0.0 <= self.gain <= 1.0):
            raise ValueError(f"gaze gain must lie in [0, 1], got {self.gain}")
        if not (self.tau_return_s > 0 and math.isfinite(self.tau_return_s)):
            raise ValueError(f"tau_return_s must be a positive number of seconds, got {self.tau_return_s}")
        if not (0.0 < self.limit_deg <= 90.0):
            raise ValueError(f"limit_deg must lie in (0, 90] degrees, got {self.limit_deg}")

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


def head_angles(t: np.ndarray, omega_body: np.ndarray, config: GazeConfig | None = None) -> np.ndarray:
    """Head rotation vector θ (T, 3) rad relative to the body, from the body's angular velocity ``omega_body``
    (T, 3) rad/s at times ``t`` (T,) s, the neck reflex of ``config`` (None: the default GazeConfig).

    Exact discretisation of dθ/dt = −gain·ω − θ/τ for ω held over each step (ω of the previous
    sample: causal), clipped to ±limit per axis. θ(t0) = 0 (the head starts on the body axis).
    A loop over samples (a 3-vector recursion).
    """
    cfg = config or GazeConfig()
    t = np.asarray(t, dtype=float)
    w = np.asarray(omega_body, dtype=float)
    if w.shape != (len(t), 3):
        raise ValueError(f"omega_body must be (time, 3) matching t, got {w.shape}")
    lim = math.radians(cfg.limit_deg)
    th = np.zeros((len(t), 3))
    x = np.zeros(3)
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        e = math.exp(-dt / cfg.tau_return_s)
        x = np.clip(x * e - cfg.gain * w[k - 1] * cfg.tau_return_s * (1.0 - e), -lim, lim)
        th[k] = x
    return th


def head_rotation(theta: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors θ = ``theta`` (..., 3) rad (Rodrigues): head-to-body,
    d_body = R·d_head."""
    th = np.asarray(theta, dtype=float)
    ang = np.linalg.norm(th, axis=-1)[..., None, None]
    k = np.where(ang[..., 0] > 1e-12, th / np.maximum(ang[..., 0], 1e-12), 0.0)
    K = np.zeros(th.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = k[..., 2], -k[..., 1], k[..., 0]
    return np.eye(3) + np.sin(ang) * K + (1.0 - np.cos(ang)) * (K @ K)


def retinal_rotation(t: np.ndarray, omega_body: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The head's angular velocity (T, 3) rad/s in the head's own frame: what turns the retina.

    R_kᵀ·(ω_body + ω_neck), ω_neck the neck's angular velocity in the body frame from the head
    angles (backward difference of R: causal, an efference copy), ω_body = ``omega_body`` (T, 3) rad/s at the
    samples ``t`` (T,) s, ``theta`` (T, 3) rad the head angles (:func:`head_angles`).
    """
    t = np.asarray(t, dtype=float)
    R = head_rotation(theta)
    W = R[1:] @ np.swapaxes(R[:-1], -1, -2)                     # R_k R_{k−1}ᵀ ≈ I + [ω dt]×
    dt = np.diff(t)[:, None]
    w_neck = np.zeros((len(t), 3))
    w_neck[1:] = 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], -1) / dt
    return np.einsum("tji,tj->ti", R, np.asarray(omega_body, dtype=float) + w_neck)


def fixation_reference(orientation: np.ndarray, limit_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A stabilised gaze for a camera: fixations held exactly, saccades where they would leave the frame.

    orientation (T, 3, 3): the camera's attitude at each frame (camera → a fixed frame, from the
    integrated gyro). Returns the gaze's attitude (T, 3, 3) in the same frame and ``saccade``
    (T,) bool. The gaze holds its attitude (a fixation: the image warped into it has no rotation
    left at all) until the camera has turned more than ``limit_deg`` away from it, then jumps to
    the camera's attitude at that frame (a saccade) — the optokinetic nystagmus's slow and fast
    phases, and the fly's own saccade-and-fixate flight (Schilstra & van Hateren 1999, J Exp Biol
    202:1481). Why not a reference that relaxes back to the camera, as the neck of
    :func:`head_angles` does: a residual turn of even 1–2°/s is as large as the translational
    image motion near the focus of expansion (on development rotation worlds a 3 s return doubles
    the EMD path's error against a held fixation). Frame k uses attitudes up to k only (causal).
    """
    from scipy.spatial.transform import Rotation

    q = np.asarray(orientation, dtype=float)
    if q.ndim != 3 or q.shape[1:] != (3, 3):
        raise ValueError(f"orientation must be (time, 3, 3), got {q.shape}")
    if not (0.0 < limit_deg <= 90.0):
        raise ValueError(f"limit_deg must lie in (0, 90] degrees, got {limit_deg}")
    lim = math.radians(limit_deg)
    ref = np.empty_like(q)
    saccade = np.zeros(len(q), bool)
    if not len(q):
        return ref, saccade
    held = q[0]
    for k in range(len(q)):  # a scalar decision per frame
        if np.linalg.norm(Rotation.from_matrix(held.T @ q[k]).as_rotvec()) > lim:
            held, saccade[k] = q[k], True
        ref[k] = held
    return ref, saccade
