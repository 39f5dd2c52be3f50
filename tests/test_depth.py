"""Depth from flow (lobula.depth) against known answers.

Flow is built analytically from a synthetic forward-depth map: a back wall, three
fronto-parallel panels and a slanted floor, camera moving forward at v = 0.5 m/s with
the epipole off-centre (on the wall), so every method has an exact answer to meet.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lobula.camera import PinholeCamera
from lobula.depth import (DepthConfig, angle_from_epipole, depth_metrics,
                          depth_parallax, depth_ratio, depth_tv, derotate_flow,
                          radial_rate, tv_objective)

V = 0.5                    # forward speed, m/s
EPI = (0.08, -0.05)        # epipole, normalised coordinates (inside the wall region)
WALL_M, FLOOR_DROP_M = 3.0, 0.35
# Panels: normalised extents at travel 0 (x0, x1, y0, y1) and forward depth (m).
PANELS = [(-0.45, -0.15, -0.30, 0.15, 0.9), (0.22, 0.42, -0.30, 0.05, 1.6),
          (-0.12, 0.02, 0.10, 0.30, 2.2)]


def make_camera(width: int, height: int) -> PinholeCamera:
    """A ~58° wide camera with slightly unequal focal lengths and an off-centre principal point."""
    f = 0.9 * width
    return PinholeCamera(width=width, height=height, fx=f, fy=1.01 * f, cx=(width - 1) / 2 + 0.3,
                         cy=(height - 1) / 2 - 0.2, frame_rate_hz=30.0)


def scene_depth(cam: PinholeCamera, travel_m: float = 0.0) -> np.ndarray:
    """Exact forward depth (m, (H, W)) after the camera travelled ``travel_m`` along (ex, ey, 1)."""
    x, y = cam.normalised_grid()
    s = travel_m
    d = np.full(x.shape, WALL_M - s)
    floor = y > 0
    d[floor] = np.minimum(d[floor], (FLOOR_DROP_M - EPI[1] * s) / y[floor])
    for x0, x1, y0, y1, dd in PANELS:
        dn = dd - s
        X, Y = EPI[0] * s + x * dn, EPI[1] * s + y * dn   # where the ray meets the panel plane
        inside = (X >= x0 * dd) & (X < x1 * dd) & (Y >= y0 * dd) & (Y < y1 * dd)
        d[inside] = np.minimum(d[inside], dn)
    return d


def translational_flow(cam: PinholeCamera, depth: np.ndarray, v: float = V, epi=EPI) -> np.ndarray:
    """Exact instantaneous flow (2, H, W), 1/s: (v/d)(p − e)."""
    x, y = cam.normalised_grid()
    return np.stack([(v / depth) * (x - epi[0]), (v / depth) * (y - epi[1])])


def noisy(flow: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    return flow + np.random.default_rng(seed).normal(0.0, sigma, flow.shape)


def rel_err(a, b) -> np.ndarray:
    return np.abs(np.asarray(a) - np.asarray(b)) / np.abs(np.asarray(b))


# ----------------------------------------------------------------------------- ratio
def test_ratio_is_exact_away_from_the_epipole():
    cam = make_camera(80, 60)
    d = scene_depth(cam)
    res = depth_ratio(translational_flow(cam, d), cam, V, EPI, min_radius_deg=2.0)
    assert isinstance(res.depth, np.ndarray) and res.method == "ratio"
    ang = angle_from_epipole(cam, EPI)
    # Every pixel outside the radius is valid and exact to float64 precision...
    assert res.valid[ang > 2.0].all()
    assert rel_err(res.depth[res.valid], d[res.valid]).max() < 1e-12
    # ...and every pixel inside it is marked invalid with NaN, not filled.
    assert (ang <= 2.0).any()
    assert not res.valid[ang <= 2.0].any() and np.isnan(res.depth[ang <= 2.0]).all()
    assert np.allclose(res.rate[res.valid], V / d[res.valid], rtol=1e-12)


def test_ratio_marks_wrong_sign_nonfinite_and_zero_speed_invalid():
    cam = make_camera(40, 30)
    d = scene_depth(cam)
    flow = translational_flow(cam, d)
    # Receding (v < 0) makes the flow contract: still exact, with v/r > 0.
    back = depth_ratio(translational_flow(cam, d, v=-V), cam, -V, EPI)
    assert back.valid.sum() > 0.9 * back.valid.size
    assert rel_err(back.depth[back.valid], d[back.valid]).max() < 1e-12
    # Expanding flow but v < 0 claimed: every r has the wrong sign -> nothing valid.
    wrong = depth_ratio(flow, cam, -V, EPI)
    assert not wrong.valid.any() and np.isnan(wrong.depth).all()
    # v = 0: depth is unobservable, not 0 or inf.
    assert not depth_ratio(flow, cam, 0.0, EPI).valid.any()
    # Missing flow stays missing.
    holes = flow.copy()
    holes[:, 5:8, 20:25] = np.nan
    res = depth_ratio(holes, cam, V, EPI)
    assert not res.valid[5:8, 20:25].any()
    # Tiny |r| (beyond max_depth_m) is invalid rather than a huge depth.
    far = depth_ratio(flow * 1e-3, cam, V, EPI, config=DepthConfig(max_depth_m=100.0))
    assert not far.valid.any()


def test_torch_in_torch_out_and_shape_errors():
    cam = make_camera(40, 30)
    f = torch.tensor(translational_flow(cam, scene_depth(cam)), dtype=torch.float32)
    res = depth_ratio(f, cam, V, EPI)
    assert isinstance(res.depth, torch.Tensor) and res.depth.dtype == torch.float32
    assert isinstance(radial_rate(f, cam, EPI), torch.Tensor)
    with pytest.raises(ValueError, match="camera is 30x40"):
        depth_ratio(f[:, :-1], cam, V, EPI)
    with pytest.raises(ValueError, match=r"\(2, H, W\)"):
        depth_ratio(f[0], cam, V, EPI)
    with pytest.raises(ValueError, match="epipole"):
        depth_ratio(f, cam, V, (0.1, float("nan")))


# ----------------------------------------------------------------------------- TV
def _cvxpy_tv(flow: np.ndarray, cam: PinholeCamera, gamma: float):
    """The same problem written independently in cvxpy: Σ|ṗ − z(p−e)|² + γ Σ|∇z| (∇ in normalised units)."""
    cp = pytest.importorskip("cvxpy", reason="cvxpy (test extra) is needed to check the TV solver against a reference")
    H, W = cam.height, cam.width
    x, y = cam.normalised_grid()
    qx, qy = x - EPI[0], y - EPI[1]
    ok = np.isfinite(flow).all(0).astype(float)
    fl = np.nan_to_num(flow)
    z = cp.Variable((H, W))
    gx = cp.hstack([cam.fx * (z[:, 1:] - z[:, :-1]), np.zeros((H, 1))])
    gy = cp.vstack([cam.fy * (z[1:, :] - z[:-1, :]), np.zeros((1, W))])
    tv = cp.sum(cp.norm(cp.vstack([cp.vec(gx, order="C"), cp.vec(gy, order="C")]), 2, axis=0))
    data = (cp.sum_squares(cp.multiply(ok, cp.multiply(z, qx) - fl[0]))
            + cp.sum_squares(cp.multiply(ok, cp.multiply(z, qy) - fl[1])))
    prob = cp.Problem(cp.Minimize(data + gamma * tv))
    prob.solve(solver=cp.CLARABEL if "CLARABEL" in cp.installed_solvers() else None)
    return z.value, prob.value


@pytest.mark.parametrize("gamma", [1e-4, 1e-3])
def test_tv_reaches_the_cvxpy_optimum(gamma):
    cam = make_camera(32, 24)
    flow = noisy(translational_flow(cam, scene_depth(cam)), 0.02, seed=3)
    flow[:, 2, 3] = np.nan                       # a missing pixel: no data term there
    z_ref, obj_ref = _cvxpy_tv(flow, cam, gamma)
    # Our objective function agrees with cvxpy's at cvxpy's solution (same problem)...
    assert tv_objective(z_ref, flow, cam, EPI, gamma) == pytest.approx(obj_ref, rel=1e-6)
    res = depth_tv(torch.tensor(flow, dtype=torch.float32), cam, V, EPI, gamma=gamma,
                   tol=1e-4, iters=5000)
    assert res.converged
    # ...and the fast solver reaches the same optimum.
    assert abs(res.objective - obj_ref) / obj_ref < 0.01
    z = res.rate.double().numpy()
    assert np.sqrt(np.mean((z - z_ref) ** 2)) / np.sqrt(np.mean(z_ref ** 2)) < 0.01
    # The solution is not trivial (TV has not flattened it to a constant).
    assert z_ref.std() > 0.1 * np.abs(z_ref).mean()


def test_tv_beats_ratio_near_the_epipole_and_is_no_worse_away():
    cam = make_camera(128, 96)
    d = scene_depth(cam)
    flow = noisy(translational_flow(cam, d), 0.02, seed=7)
    ratio = depth_ratio(flow, cam, V, EPI)
    tv = depth_tv(torch.tensor(flow, dtype=torch.float32), cam, V, EPI)
    m_r = depth_metrics(ratio.depth, d, ratio.valid, EPI, cam)
    m_t = depth_metrics(tv.depth, d, tv.valid, EPI, cam)
    inner = "0-5"
    assert m_t[inner]["abs_rel"] < 0.5 * m_r[inner]["abs_rel"]
    assert m_t[inner]["valid_fraction"] > m_r[inner]["valid_fraction"]
    assert m_t[inner]["valid_fraction"] == 1.0
    for ring in ("10-20", "20-90", "all"):
        assert m_t[ring]["abs_rel"] <= m_r[ring]["abs_rel"] + 0.01
        assert m_t[ring]["valid_fraction"] >= m_r[ring]["valid_fraction"] - 1e-9
    assert m_t["all"]["abs_rel"] < 0.06


def test_tv_with_exact_flow_and_tiny_gamma_recovers_depth():
    cam = make_camera(64, 48)
    d = scene_depth(cam)
    # (With γ → 0 the few pixels at the epipole are held only by TV and settle slowly,
    # so this caps the iterations instead of asking for convergence.)
    res = depth_tv(translational_flow(cam, d), cam, V, EPI, gamma=1e-7, tol=1e-5, iters=200)
    assert isinstance(res.depth, np.ndarray) and res.valid.all()
    m = depth_metrics(res.depth, d, res.valid, EPI, cam)
    assert m["20-90"]["abs_rel"] < 1e-3 and m["all"]["abs_rel"] < 1e-3


def test_warm_start_needs_fewer_iterations():
    cam = make_camera(96, 72)
    dt = 1.0 / cam.frame_rate_hz
    f0 = torch.tensor(noisy(translational_flow(cam, scene_depth(cam)), 0.01, seed=1), dtype=torch.float32)
    f1 = torch.tensor(noisy(translational_flow(cam, scene_depth(cam, V * dt)), 0.01, seed=2),
                      dtype=torch.float32)
    cfg = DepthConfig(tv_tol=1e-3)
    first = depth_tv(f0, cam, V, EPI, config=cfg)
    cold = depth_tv(f1, cam, V, EPI, config=cfg)
    warm = depth_tv(f1, cam, V, EPI, init=first, config=cfg)
    assert warm.converged and cold.converged and warm.coarse_iterations == ()
    assert warm.iterations < cold.iterations + sum(cold.coarse_iterations)
    assert abs(warm.objective - cold.objective) / cold.objective < 2e-3
    # A bare z map also works as a warm start (no dual, default step).
    from_map = depth_tv(f1, cam, V, EPI, init=first.rate, config=cfg)
    assert from_map.converged


# ----------------------------------------------------------------------------- parallax
def _rotation(omega, dt):
    w = -np.asarray(omega, float) * dt
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th ** 2 * K @ K


def rotational_flow(cam: PinholeCamera, omega) -> np.ndarray:
    """Pinhole rotational flow (2, H, W), 1/s, for ω in rad/s (camera frame), written out here."""
    x, y = cam.normalised_grid()
    wx, wy, wz = omega
    return np.stack([wx * x * y - wy * (1 + x * x) + wz * y, wx * (1 + y * y) - wy * x * y - wz * x])


def test_rotational_flow_is_the_derivative_of_a_rotating_projection_and_derotates():
    cam = make_camera(40, 30)
    omega = np.array([0.3, -0.2, 0.5])
    x, y = cam.normalised_grid()
    h = 1e-6
    P = _rotation(omega, h) @ np.stack([x.ravel(), y.ravel(), np.ones(x.size)])
    num = np.stack([(P[0] / P[2]).reshape(x.shape) - x, (P[1] / P[2]).reshape(x.shape) - y]) / h
    assert np.allclose(rotational_flow(cam, omega), num, atol=1e-5)
    # derotate_flow removes exactly that field (instantaneous model)...
    assert np.allclose(derotate_flow(rotational_flow(cam, omega), cam, omega), 0.0, atol=1e-12)
    # ...and its finite-rotation form tends to it as dt -> 0.
    assert np.allclose(derotate_flow(num, cam, omega, dt=h), 0.0, atol=1e-4)


def test_parallax_derotates_with_the_gyro_and_recovers_depth():
    cam = make_camera(80, 60)
    d = scene_depth(cam)
    omega = np.array([0.2, -0.3, 0.1])      # rad/s, camera frame
    flow = translational_flow(cam, d) + rotational_flow(cam, omega)
    res = depth_parallax(flow, cam, V, EPI, gyro=omega)
    assert res.method == "parallax"
    assert res.valid[angle_from_epipole(cam, EPI) > 2.0].all()
    assert rel_err(res.depth[res.valid], d[res.valid]).max() < 1e-9
    # Without the gyro the rotation is read as depth: badly wrong.
    raw = depth_parallax(flow, cam, V, EPI, gyro=None)
    assert depth_metrics(raw.depth, d, raw.valid, EPI, cam)["all"]["abs_rel"] > 0.2


def test_parallax_finite_motion_is_exact_with_dt():
    """Flow as a finite displacement over dt (X' = R(X − t·dt)): depth at the later frame."""
    cam = make_camera(80, 60)
    d = scene_depth(cam)
    omega, dt = np.array([0.4, -0.6, 0.3]), 0.2          # large rotation over 0.2 s
    x, y = cam.normalised_grid()
    X = np.stack([x * d, y * d, d]).reshape(3, -1)
    t = V * np.array([EPI[0], EPI[1], 1.0])
    Xp = _rotation(omega, dt) @ (X - t[:, None] * dt)
    flow = np.stack([(Xp[0] / Xp[2]).reshape(x.shape) - x, (Xp[1] / Xp[2]).reshape(x.shape) - y]) / dt
    res = depth_parallax(flow, cam, V, EPI, gyro=omega, dt=dt)
    later = d - V * dt
    assert rel_err(res.depth[res.valid], later[res.valid]).max() < 1e-9
    assert res.valid.mean() > 0.95
    # The instantaneous derotation is only approximate for a finite rotation.
    approx = depth_parallax(flow, cam, V, EPI, gyro=omega)
    assert np.nanmax(rel_err(approx.depth[approx.valid], later[approx.valid])) > 1e-3
    # derotate_flow keeps the array kind.
    assert isinstance(derotate_flow(torch.tensor(flow), cam, omega, dt=dt), torch.Tensor)


# ----------------------------------------------------------------------------- metrics
def test_depth_metrics_known_values():
    cam = make_camera(40, 30)
    true = np.full((30, 40), 2.0)
    pred = np.full_like(true, np.nan)
    pred[:, :20] = 2.2                                   # +10 % on the left half
    m = depth_metrics(pred, true, np.isfinite(pred), EPI, cam, rings_deg=(0, 5, 90))
    assert set(m) == {"all", "0-5", "5-90"}
    a = m["all"]
    assert a["abs_rel"] == pytest.approx(0.1) and a["rmse_m"] == pytest.approx(0.2)
    assert a["delta_1_25"] == 1.0 and a["valid_fraction"] == pytest.approx(0.5)
    assert m["0-5"]["n_true"] + m["5-90"]["n_true"] == a["n_true"] == 1200
    # The epipole (x = +0.08) sits in the right half, where nothing is valid.
    assert m["0-5"]["valid_fraction"] < 0.5
    # No true depth, no valid prediction: NaN, not an error.
    empty = depth_metrics(pred, np.full_like(true, np.nan), None, EPI, cam)
    assert math.isnan(empty["all"]["abs_rel"]) and math.isnan(empty["all"]["valid_fraction"])
