"""lobula.readers.image_orientation: the IMU turned into a stabilised image's frame by CORI and IORI."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lobula.readers.core import IMU
from lobula.readers.image_orientation import (body_rates, gyro_agreement, image_frame_imu,
                                              quaternion_rotations)

FPS, IMU_HZ, SECONDS = 30.0, 200.0, 4.0


def _smooth(t, seed, amp):
    """(n, 3) rotation vectors (rad): a few sines per axis, amplitude ``amp``."""
    rng = np.random.default_rng(seed)
    return np.stack([sum(amp * rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6))
                         for f in rng.uniform(0.2, 2.0, 3)) for _ in range(3)], -1)


def _wxyz(rot: Rotation) -> np.ndarray:
    q = rot.as_quat()
    return np.c_[q[:, 3:], q[:, :3]]


def _camera(seed=0):
    """A body turning as a hand-held camera does and a stabilisation S (image → body) that undoes most of it,
    exact: the body's gyro at IMU_HZ, its specific force, and CORI = B⁻¹, IORI = S⁻¹ at the frames."""
    t_imu = np.arange(0.0, SECONDS, 1.0 / IMU_HZ)
    t_fr = np.arange(0.0, SECONDS - 0.05, 1.0 / FPS)
    body = lambda t: Rotation.from_rotvec(_smooth(t, seed, 0.15))  # noqa: E731  camera → world
    smooth_image = lambda t: Rotation.from_rotvec(0.2 * _smooth(t, seed, 0.15))  # noqa: E731  image → world
    # the gyro: body rates from the exact orientation, finely differenced
    h = 1e-5
    gyro = (body(t_imu).inv() * body(t_imu + h)).as_rotvec() / h
    accel = np.c_[np.sin(t_imu), -9.81 + 0.3 * np.cos(3 * t_imu), 0.5 * np.ones_like(t_imu)]
    s = body(t_fr).inv() * smooth_image(t_fr)  # image → body
    return (IMU(t_imu, accel, gyro, "synthetic"), t_fr, _wxyz(body(t_fr).inv()), _wxyz(s.inv()), body, smooth_image,
            t_imu)


def test_body_rates_of_a_constant_turn():
    t = np.arange(10) / 30.0
    rot = Rotation.from_rotvec(np.outer(t, [0.1, -0.2, 0.3]))
    mid, w = body_rates(t, rot)
    assert np.allclose(mid, t[:-1] + 1 / 60.0) and np.allclose(w, [0.1, -0.2, 0.3], atol=1e-12)


def test_quaternions_are_read_w_first():
    q = np.array([[np.cos(0.25), np.sin(0.25), 0.0, 0.0]]) * 3.0  # 0.5 rad about x, any norm
    assert np.allclose(quaternion_rotations(q).as_rotvec(), [[0.5, 0.0, 0.0]])


def test_the_image_frame_imu_turns_as_the_image_does():
    """The gyro it gives integrates over each frame interval to the image's own turn there (to the slerp's
    discretisation), where the body's gyro turns by up to several times more; the accelerometer is the body's
    specific force in the image's axes (to the slerp between frames: 0.01 m/s² of 10, where leaving it out errs by
    up to 1.4)."""
    imu, t_fr, cori, iori, body, image, t_imu = _camera()
    res = image_frame_imu(imu, t_fr, cori, iori)
    assert res.gyro_agreement > 0.99
    inside = (t_imu >= t_fr[0]) & (t_imu < t_fr[-1])
    for a, b in zip(t_fr[5:-5:7], t_fr[6:-4:7]):
        m = (t_imu >= a) & (t_imu < b)
        turned = res.imu.gyro[m].sum(0) / IMU_HZ
        want = (image(np.array([a])).inv() * image(np.array([b]))).as_rotvec()[0]
        body_turn = (body(np.array([a])).inv() * body(np.array([b]))).as_rotvec()[0]
        assert np.linalg.norm(turned - want) < 0.05 * np.linalg.norm(body_turn) + 1e-4
    s = body(t_imu[inside]).inv() * image(t_imu[inside])  # image → body, exact
    np.testing.assert_allclose(res.imu.accel[inside], s.inv().apply(imu.accel[inside]), atol=0.02)
    assert res.max_deg == pytest.approx(np.degrees(np.max(quaternion_rotations(iori).magnitude())))


def test_orientations_in_another_convention_are_not_used():
    """CORI written as camera → world (B, not B⁻¹) turns the other way from the gyro: refused, not misread."""
    imu, t_fr, cori, iori, *_ = _camera(seed=1)
    flipped = _wxyz(quaternion_rotations(cori).inv())
    assert gyro_agreement(t_fr, cori, imu)[0] > 0.99
    assert gyro_agreement(t_fr, flipped, imu)[0] < -2.5
    with pytest.raises(ValueError, match="CORI's rates do not follow the gyro's"):
        image_frame_imu(imu, t_fr, flipped, iori)
    with pytest.raises(ValueError, match="no gyro"):
        image_frame_imu(IMU(imu.time_s, imu.accel, None, "no gyro"), t_fr, cori, iori)


@pytest.mark.parametrize("bad", ["nan", "zero"])
def test_damaged_quaternions_are_refused_with_the_reason(bad):
    imu, t_fr, cori, iori, *_ = _camera(seed=3)
    broken = cori.copy()
    broken[5] = np.nan if bad == "nan" else 0.0
    with pytest.raises(ValueError, match="1 of their quaternions are not unit quaternions"):
        image_frame_imu(imu, t_fr, broken, iori)


def test_a_camera_too_still_to_check_keeps_its_imu():
    """Below MIN_CHECK_RATE the agreement says nothing: the orientations are not used."""
    imu, t_fr, cori, iori, *_ = _camera(seed=2)
    still = IMU(imu.time_s, imu.accel, imu.gyro * 1e-3, "still")
    slow = _wxyz(Rotation.from_rotvec(1e-3 * quaternion_rotations(cori).as_rotvec()))
    assert gyro_agreement(t_fr, slow, still)[1] < 0.02
    with pytest.raises(ValueError, match="turns too little to check them"):
        image_frame_imu(still, t_fr, slow, iori)


@pytest.fixture(scope="module")
def stabilised_run(tmp_path_factory):
    """A 160×120 run turning on three axes (3 s) taken as the stabilised image V, and a body B = V·S⁻¹ that shakes
    against it (S, image → body: ±8° of slow levelling, ±2° at 2-4 Hz and ±1.5° at 5-8 Hz per axis): the footage,
    the body's IMU (its gyro from B, its specific force S·a) and the CORI = B⁻¹, IORI = S⁻¹ a GoPro would write."""
    from scipy.spatial.transform import Slerp

    from lobula.readers import open_footage
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, make_track_run

    cfg = TrackRunConfig(start_s=3.0, duration_s=3.0, scale=0.25,
                         scene=SceneConfig(seed=2, rotation3_amp_deg=(5.0, 5.0, 5.0)))
    run = make_track_run(tmp_path_factory.mktemp("stabilised") / "run", cfg, progress=False)
    fo = open_footage(run)
    t, imu = fo.imu.time_s, fo.imu
    steps = Rotation.from_rotvec(0.5 * (imu.gyro[1:] + imu.gyro[:-1]) * np.diff(t)[:, None])
    image = [Rotation.identity()]
    for step in steps:
        image.append(image[-1] * step)
    image = Rotation.concatenate(image)
    rng = np.random.default_rng(0)
    freq = np.c_[rng.uniform(0.1, 0.3, 3), rng.uniform(2, 4, 3), rng.uniform(5, 8, 3)]
    amp, phase = np.radians([8.0, 2.0, 1.5]), rng.uniform(0, 2 * np.pi, (3, 3))
    shake = lambda tt: Rotation.from_rotvec(np.stack([  # noqa: E731
        sum(amp[i] * np.sin(2 * np.pi * freq[j, i] * tt + phase[j, i]) for i in range(3)) for j in range(3)], -1))
    s = shake(t)
    body = image * s.inv()
    d = (body[:-1].inv() * body[1:]).as_rotvec() / np.diff(t)[:, None]
    gyro = np.r_[d[:1], 0.5 * (d[1:] + d[:-1]), d[-1:]]
    body_imu = IMU(t, s.apply(imu.accel), gyro, "the body's")
    frames = Slerp(t, body)(fo.times)
    return run, body_imu, fo.times, _wxyz(frames.inv()), _wxyz(shake(fo.times).inv())


def _scored(run, imu):
    """(RMSE where observable after 0.5 s m/s, observable fraction, ±2σ fraction there) of the zero-phase run on
    ``run`` with ``imu`` in place of its own."""
    from lobula.readers import open_footage
    from lobula.velocity.pipeline import estimate_velocity

    fo = open_footage(run)
    fo.imu = imu
    ds = estimate_velocity(fo, progress=False)
    late = ds.time.values - ds.time.values[0] >= 0.5
    e, obs = (ds.v_hat - ds.v_true).values[late], ds.observable.values[late].astype(bool)
    if not obs.any():
        return np.nan, 0.0, np.nan
    return (float(np.sqrt(np.mean(e[obs] ** 2))), float(obs.mean()),
            float(np.mean(np.abs(e[obs]) <= 2 * ds.v_std.values[late][obs])))


def test_velocity_through_a_stabilised_image(stabilised_run):
    """Read with the body's IMU, the stabilised run is never observable offline (and online 0.12 m/s off on the few
    frames it answers); with the IMU turned into the image's frame by CORI and IORI it reads as with the image's own
    IMU (0.0021 m/s against 0.0009, observable 97 %)."""
    run, body_imu, times, cori, iori = stabilised_run
    res = image_frame_imu(body_imu, times, cori, iori)
    assert res.gyro_agreement > 0.99 and res.max_deg > 10
    rmse, observable, covered = _scored(run, res.imu)
    assert rmse < 0.005 and observable > 0.9 and covered > 0.95
    rmse, observable, covered = _scored(run, body_imu)
    assert observable < 0.1 or rmse > 0.05
