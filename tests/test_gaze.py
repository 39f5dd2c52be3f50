"""Haltere-driven gaze stabilisation: the neck reflex's analytic response, frames, and gaze-stabilised eye footage."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lobula.gaze import GazeConfig, head_angles, head_rotation, retinal_rotation
from tests.test_compound_eye import Corridor, flying_straight


def test_head_angles_follow_the_neck_reflex_analytically_and_causally():
    cfg = GazeConfig(gain=0.8, tau_return_s=0.5, limit_deg=20.0)
    t = np.arange(0.0, 3.0, 0.002)
    w = np.zeros((len(t), 3))
    w[:, 2] = 0.3                                      # a constant yaw turn, rad/s
    th = head_angles(t, w, cfg)
    # dθ/dt = −g·ω − θ/τ from θ(0) = 0: θ(t) = −g·ω·τ·(1 − e^{−t/τ}) (ω held from the previous sample).
    want = -0.8 * 0.3 * 0.5 * (1.0 - np.exp(-t / 0.5))
    assert np.allclose(th[:, 2], want, atol=1e-12)
    assert np.all(th[:, :2] == 0.0)
    # The neck's range stops the head.
    big = head_angles(t, 10.0 * w, cfg)
    assert np.isclose(np.abs(big[:, 2]).max(), math.radians(20.0)) and big[-1, 2] < 0
    # Causal: a later change of ω leaves the earlier head angles as they were.
    w2 = w.copy()
    w2[700:, 2] = -1.0
    assert np.array_equal(head_angles(t, w2, cfg)[:701], th[:701])
    with pytest.raises(ValueError, match="gain"):
        GazeConfig(gain=1.5)


def test_head_rotation_is_the_rotation_vector_and_retinal_rotation_is_what_the_head_leaves():
    rv = np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.3], [1e-14, 0.0, 0.0]])
    assert np.allclose(head_rotation(rv), Rotation.from_rotvec(rv).as_matrix(), atol=1e-12)
    # A constant yaw turn: the retina turns at ω·(1 − g·e^{−t/τ}) (the head first cancels g of it, then returns).
    cfg = GazeConfig(gain=0.8, tau_return_s=0.5)
    t = np.arange(0.0, 2.0, 0.002)
    w = np.tile([0.0, 0.0, 0.3], (len(t), 1))
    ret = retinal_rotation(t, w, head_angles(t, w, cfg))
    want = 0.3 * (1.0 - 0.8 * np.exp(-t / 0.5))
    assert np.allclose(ret[5:, 2], want[5:], atol=2e-3)
    assert np.abs(ret[:, :2]).max() < 1e-9
    # Without the head moving, the retina turns with the body.
    assert np.allclose(retinal_rotation(t, w, np.zeros_like(w)), w)


def test_gaze_stabilised_footage_sees_a_turn_cancelled_by_the_head(tmp_path):
    from stimuli.eye import open_eye_footage, render_eye, write_eye_footage

    omega = np.array([0.0, 0.4, 0.0])                 # the body yaws at 0.4 rad/s
    world = flying_straight(Corridor(v=0.5, wavelength=0.3, rotation_rate=omega))
    from lobula.compound_eye import CompoundEye, CompoundEyeConfig
    eye = CompoundEye(CompoundEyeConfig(dphi_deg=10.0, rings=1))
    times = np.arange(40) / 500.0
    imu_t = np.arange(0.0, 0.1, 0.001)
    still = np.tile([0.0, -9.81, 0.0], (len(imu_t), 1))   # gravity's specific force, camera y down
    imu = dict(time_s=imu_t, accel=still, gyro=np.tile(omega, (len(imu_t), 1)))
    # Unit gain and a neck that never returns: the head holds its orientation in the world.
    gaze = GazeConfig(gain=1.0, tau_return_s=1e6, limit_deg=90.0)
    fo = open_eye_footage(write_eye_footage(tmp_path / "gaze", world, eye, imu, times, {}, range_every=10,
                                            gaze=gaze))
    assert fo.head is not None and fo.head.shape == (40, 3) and fo.info["gaze"]["gain"] == 1.0
    assert np.allclose(fo.head[:, 1], -0.4 * times, atol=1e-5)
    still = Corridor(v=0.5, wavelength=0.3)           # the same world seen by an eye that does not turn
    _, want = next(render_eye(still, eye, times, chunk=40))
    _, body = next(render_eye(world, eye, times, chunk=40))
    got = np.asarray(fo.luminance)
    late = slice(20, 40)
    # The turning body's eye sees the turn; the stabilised head's eye sees the still world's image.
    assert np.abs(body[late] - want[late]).max() > 0.02
    assert np.abs(got[late] - want[late]).max() < 0.1 * np.abs(body[late] - want[late]).max()
    # The haltere prediction the circuit gets is the retina's own rotation (body's plus neck's): about zero.
    ret = retinal_rotation(fo.times, np.tile(omega, (len(times), 1)), fo.head)
    assert np.abs(ret[2:]).max() < 0.01 * 0.4


def test_scene_gaze_options_need_the_fly_eye(tmp_path, capsys):
    from experiments.cli import main

    assert main(["scene", str(tmp_path / "a"), "--gaze", "haltere", "--duration", "1"]) == 2
    assert "--eye fly" in capsys.readouterr().err
    assert main(["scene", str(tmp_path / "b"), "--eye", "fly", "--gaze-gain", "0.5", "--duration", "1"]) == 2
    assert "--gaze haltere" in capsys.readouterr().err
    assert main(["scene", str(tmp_path / "c"), "--eye", "fly", "--gaze-return", "5", "--duration", "1"]) == 2
    assert "--gaze-return applies to --gaze haltere" in capsys.readouterr().err
    assert main(["scene", str(tmp_path / "d"), "--gaze-return", "5", "--duration", "1"]) == 2
    assert "--eye fly" in capsys.readouterr().err
    assert not any((tmp_path / k).exists() for k in "abcd")


def test_scene_gaze_return_reaches_the_footage(tmp_path):
    """--gaze-gain 1 --gaze-return 5: the neck's configuration in eye.json, and a head that returns slowly
    holds more of the body's turn than the default 0.5 s return does."""
    from experiments.cli import main
    from stimuli.eye import open_eye_footage

    heads = {}
    for name, ret in (("slow", "5"), ("default", "0.5")):
        args = ["scene", str(tmp_path / name), "--eye", "fly", "--gaze", "haltere", "--gaze-gain", "1",
                "--gaze-return", ret, "--rotation", "4", "--duration", "1", "--rate-hz", "100", "--quiet"]
        assert main(args) == 0
        fo = open_eye_footage(tmp_path / name)
        assert fo.info["gaze"]["gain"] == 1.0 and fo.info["gaze"]["tau_return_s"] == float(ret)
        heads[name] = np.abs(fo.head).max()
    assert heads["slow"] > 1.2 * heads["default"] > 0, heads


def _yaw(angles_rad: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.outer(angles_rad, [0.0, 1.0, 0.0])).as_matrix()


def test_fixation_holds_the_gaze_and_saccades_at_the_limit_causally():
    from lobula.gaze import fixation_reference

    t = np.arange(0.0, 2.0, 1.0 / 30.0)
    # A wobble within the limit: one fixation, the gaze exactly the first frame's attitude.
    wob = _yaw(np.radians(5.0) * np.sin(2 * np.pi * 1.0 * t))
    ref, sac = fixation_reference(wob, 12.0)
    assert not sac.any() and np.allclose(ref, wob[0])
    # A steady 30°/s turn (1° per frame): a saccade onto the camera whenever it is more than 12.5° past the gaze.
    turn = _yaw(np.radians(30.0) * t)
    ref, sac = fixation_reference(turn, 12.5)
    k = np.flatnonzero(sac)
    assert list(k) == [13, 26, 39, 52] and np.allclose(ref[k], turn[k])
    gap = np.degrees(np.linalg.norm(Rotation.from_matrix(np.swapaxes(ref, 1, 2) @ turn).as_rotvec(), axis=1))
    assert gap.max() <= 12.5
    # Causal: a different future leaves the past gaze as it was.
    other = turn.copy()
    other[30:] = _yaw(np.radians(-20.0) * t[30:])
    assert np.array_equal(fixation_reference(other, 12.5)[0][:30], ref[:30])
    with pytest.raises(ValueError, match="limit_deg"):
        fixation_reference(turn, 0.0)
