"""lobula.readers.imu_rotation: the IMU's axes against the camera's, from the gyro and the image's rotation."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lobula.readers.core import FootageError
from lobula.readers.imu_rotation import ROTATION_SYSTEMATIC_DEG, fit_imu_rotation, wahba_rotation
from tests.flow_helpers import swaying_flow


def _rates(n=300, seed=0, axes=(1.0, 1.0, 1.0)):
    """Smooth angular velocities (n, 3) rad/s, about 0.3 rad/s RMS on each axis scaled by ``axes``."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 30.0
    w = np.stack([sum(rng.normal(0, 0.2) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6))
                      for f in rng.uniform(0.2, 2.0, 4)) for _ in range(3)], -1)
    return w * np.asarray(axes)


def _angle_between(r1, r2) -> float:
    return float(np.degrees(Rotation.from_matrix(r1 @ r2.T).magnitude()))


def test_wahba_finds_a_known_rotation_and_never_a_reflection():
    r = Rotation.from_rotvec([0.3, -1.1, 2.0]).as_matrix()
    b = _rates()
    assert np.allclose(wahba_rotation(b @ r.T, b), r, atol=1e-10)
    mirrored = b * np.array([1.0, 1.0, -1.0])          # best fitted by a reflection: the rotation is kept proper
    assert np.linalg.det(wahba_rotation(mirrored, b)) == pytest.approx(1.0)


def _statistical_std(est) -> float:
    return float(np.sqrt(est.angle_std_deg ** 2 - ROTATION_SYSTEMATIC_DEG ** 2))


@pytest.mark.parametrize("rotvec_deg", [(0, 0, 0), (0, 0, 90), (10, -20, 5), (180, 0, 0)])
def test_the_rotation_and_both_scales_are_found(rotvec_deg):
    """ω_img = D·R·ω_gyro + noise, the image's pan/tilt read 0.8× (a short focal length), roll 0.95× (the flow's
    under-reading): R within 0.3°, the scales within 1 %."""
    r = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    g = _rates(seed=1)
    d = np.array([0.8, 0.8, 0.95])
    a = (g @ r.T) * d + np.random.default_rng(2).normal(0, 0.01, g.shape)
    est = fit_imu_rotation(a, g)
    err = _angle_between(est.rotation, r)
    print(f"\n{rotvec_deg}: angle {est.angle_deg:.2f} ± {est.angle_std_deg:.2f}°, error {err:.3f}°, "
          f"scales {est.scales}")
    assert err < 0.3 and est.scales == pytest.approx((0.8, 0.95), rel=0.01) and est.correlation > 0.99
    assert est.angle_deg == pytest.approx(np.linalg.norm(rotvec_deg), abs=0.3)
    if np.linalg.norm(rotvec_deg) >= 90:
        assert est.correlation_as_given < est.correlation - 0.25


def test_the_stated_std_is_calibrated_over_noise_draws():
    """Over 60 noise draws the angle's error is inside twice its statistical std (the stated std less the
    systematic part) on ≥ 90 % of them, and its RMS is 0.7–1.4× the std's."""
    r = Rotation.from_rotvec([0.2, 0.4, -0.3]).as_matrix()
    g = _rates(seed=3)
    errs, stds = [], []
    for k in range(60):
        a = (g @ r.T) * np.array([0.9, 0.9, 1.0]) + np.random.default_rng(10 + k).normal(0, 0.04, g.shape)
        est = fit_imu_rotation(a, g)
        errs.append(_angle_between(est.rotation, r))
        stds.append(_statistical_std(est))
    errs, stds = np.array(errs), np.array(stds)
    ratio = np.sqrt(np.mean(errs ** 2)) / np.sqrt(np.mean(stds ** 2))
    print(f"\nRMS error {np.sqrt(np.mean(errs ** 2)):.3f}°, std {np.sqrt(np.mean(stds ** 2)):.3f}°, "
          f"inside 2σ {np.mean(errs < 2 * stds):.2f}")
    assert np.mean(errs < 2 * stds) >= 0.9 and 0.7 < ratio < 1.4


def test_turning_about_one_axis_cannot_tell_the_axes():
    g = _rates(axes=(0.0, 1.0, 0.0))
    with pytest.raises(FootageError, match="turns about one axis at most"):
        fit_imu_rotation(g, g, where="clip.mp4")


def test_a_swaying_walk_does_not_turn_the_axes_once_the_translation_is_fitted():
    """Exact flow of a camera that sways with its own pan and roll and bounces with its tilt, its IMU's axes 30°
    off: fitted to the image's least-squares rates the axes read more than 3° off the truth, to the flow with the
    translation alongside within 0.2°, with the scales (1.1 pan/tilt, 1.1 roll) recovered."""
    from lobula.readers.clock_offset import FlowSamples, rotation_rates
    from lobula.readers.imu_rotation import refine_with_translation

    x, y, flow, gyro_cam = swaying_flow(1.1, roll_sway=1.5)
    r_true = Rotation.from_rotvec(np.radians(30.0) * np.array([0.6, -0.64, 0.48])).as_matrix()
    gyro_imu = gyro_cam @ r_true                                          # ω_imu = Rᵀ ω_camera, row by row
    samples = FlowSamples(np.arange(len(flow)) / 30.0, x, y, flow)
    w_img = rotation_rates(samples)
    start = fit_imu_rotation(w_img, gyro_imu)
    assert _angle_between(start.rotation, r_true) > 3.0
    got = refine_with_translation(start, samples, w_img, gyro_imu)
    assert _angle_between(got.rotation, r_true) < 0.2
    assert got.scales == pytest.approx((1.1, 1.1), rel=2e-3)
