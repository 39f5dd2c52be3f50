"""Camera, receptive-field pooling, epipole and derotation against exact answers."""
import numpy as np
import pytest

from lobula.camera import PinholeCamera, angles_to_normalised, normalised_to_angles
from lobula.epipole import EpipoleEstimator, derotate, rotational_flow
from lobula.receptive_field import FieldConfig, gap_correction, pool_fields, tile_fields
from stimuli.scene import SceneConfig, TrackScene
from stimuli.trajectory import trajectory_from_function

CAM = PinholeCamera().scaled(0.5)


def test_scaled_camera_keeps_field_of_view():
    full, half = PinholeCamera(), PinholeCamera().scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    np.testing.assert_allclose(full.fov_deg, half.fov_deg, atol=0.1)


def test_angles_roundtrip():
    x, y = np.meshgrid(np.linspace(-0.5, 0.5, 7), np.linspace(-0.4, 0.4, 5))
    xr, yr = angles_to_normalised(*normalised_to_angles(x, y))
    np.testing.assert_allclose(xr, x, atol=1e-12)
    np.testing.assert_allclose(yr, y, atol=1e-12)


def test_fields_tile_the_view_without_overlap():
    f = tile_fields(CAM, FieldConfig(size_deg=5.0))
    w = f.weights.toarray()
    assert f.n_fields >= 60
    assert w.sum(0).max() <= 1.0  # a tiling: no pixel in two box fields
    assert (w.sum(1) > 0).all()
    hx, hy = CAM.fov_deg
    assert np.abs(f.centres_deg[:, 0]).max() + 2.5 <= hx / 2 + 1e-6
    assert np.abs(f.centres_deg[:, 1]).max() + 2.5 <= hy / 2 + 1e-6


@pytest.mark.parametrize("pooling", ["least-squares", "pixel-mean"])
def test_pooling_is_exact_for_pure_expansion(pooling):
    f = tile_fields(CAM)
    e = (0.05, -0.03)
    r_true = 0.37
    flow = r_true * np.stack([f.x - e[0], f.y - e[1]])
    r, r2 = pool_fields(flow, f, e, pooling=pooling)
    np.testing.assert_allclose(r, r_true, rtol=1e-5)
    np.testing.assert_allclose(r2, r_true ** 2, rtol=1e-5)


def test_pooled_r2_exceeds_r_squared_when_a_field_spans_two_depths():
    f = tile_fields(CAM)
    split = np.tan(np.radians(1.3))  # a depth edge that cuts through a column of fields
    rmap = np.where(f.x > split, 0.2, 0.6)
    flow = rmap * np.stack([f.x, f.y])
    r, r2 = pool_fields(flow, f, (0.0, 0.0))
    straddle = (f.weights @ (f.x.ravel() > split)) / f.weights.sum(1).A1
    mixed = (straddle > 0.2) & (straddle < 0.8)
    assert mixed.any()
    assert np.all(r2[mixed] > r[mixed] ** 2 + 1e-3)


def test_gap_correction_gives_the_mean_rate():
    d0, v, dt = 2.0, 0.5, 0.2
    d1 = d0 - v * dt
    r_pair = (d0 / d1 - 1) / dt
    r, r2 = gap_correction(np.array([r_pair]), np.array([r_pair ** 2]), dt)
    mean_r = np.log(d0 / d1) / dt  # ∫ v/d dt / Δt for constant v
    np.testing.assert_allclose(r, mean_r, rtol=1e-12)
    np.testing.assert_allclose(r2, mean_r ** 2, rtol=1e-12)


def test_epipole_estimator_recovers_a_known_epipole_from_noisy_flow():
    f = tile_fields(CAM)
    rng = np.random.default_rng(1)
    e = np.array([np.tan(np.radians(7.0)), np.tan(np.radians(-2.0))])
    depth = rng.uniform(1.0, 4.0, f.x.shape)
    est = EpipoleEstimator(f.x, f.y)
    for _ in range(5):
        flow = (0.4 / depth) * np.stack([f.x - e[0], f.y - e[1]])
        flow = flow + rng.normal(0, 0.01, flow.shape)
        flow[:, :20, :20] = 3.0  # an outlier patch (e.g. a moving object)
        got = est.update(flow)
    err_deg = np.degrees(np.abs(np.arctan(got) - np.arctan(e)))
    assert err_deg.max() < 0.2


def test_rotational_flow_matches_the_renderer_for_a_rotating_camera():
    traj = trajectory_from_function(lambda t: np.zeros_like(t), 2.0)
    scene = TrackScene(CAM, traj, SceneConfig(rotation_amp_deg=3.0, rotation_hz=0.5, noise_grey=0))
    from stimuli.imu import angular_velocity
    t0, dt = 0.4, 1e-3
    flow = scene.flow(t0, t0 + dt) / dt
    omega = angular_velocity(scene.rotation, np.array([t0 + dt / 2]))[0]
    x, y = CAM.normalised_grid()
    pred = rotational_flow(omega, x, y)
    assert np.abs(flow - pred).max() < 1e-3 * np.abs(pred).max() + 1e-6
    assert np.abs(derotate(flow, omega, x, y)).max() < 1e-3 * np.abs(flow).max()
