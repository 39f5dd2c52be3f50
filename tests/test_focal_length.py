"""lobula.readers.focal_length, lobula.readers.lens_projection and `lobula calibrate-camera`: the focal length and
the projection from the gyro against the image."""
import json

import numpy as np
import pytest

from lobula.readers import open_footage
from lobula.readers.core import FootageError
from lobula.epipole import rotational_flow
from lobula.readers.focal_length import estimate_focal_length
from lobula.readers.gyro_scale import gyro_scale_with_translation
from lobula.readers.self_calibration import FOCAL_SYSTEMATIC_REL_STD
from tests.flow_helpers import swaying_flow


def _guess(run, tmp_path, factor, name="guess.json", imu_to_camera=None):
    d = json.loads((run / "camera.json").read_text())
    d["fx"], d["fy"] = d["fx"] * factor, d["fy"] * factor
    if imu_to_camera is not None:
        d["imu_to_camera"] = np.asarray(imu_to_camera).tolist()
    (tmp_path / name).write_text(json.dumps(d))
    return tmp_path / name


def _rotation_only_slope(x, y, flow, gyro):
    basis = np.stack([rotational_flow(e, x, y).reshape(-1) for e in np.eye(3)], -1)
    w = np.linalg.lstsq(basis, flow.reshape(len(flow), -1).T, rcond=None)[0].T
    return float((w[:, :2] * gyro[:, :2]).sum() / (gyro[:, :2] ** 2).sum())


@pytest.mark.parametrize("k", [0.85, 1.0, 1.2])
def test_the_gyro_scale_is_found_through_a_swaying_walk(k):
    """Exact flow of a camera that sways and bounces with its own pan and tilt: a fit of the rotation alone reads
    the scale more than 10 % off, the fit with the translation alongside within 0.2 %, roll's scale too."""
    x, y, flow, gyro = swaying_flow(k)
    assert abs(_rotation_only_slope(x, y, flow, gyro) / k - 1) > 0.1
    got, std, roll = gyro_scale_with_translation(x, y, flow, gyro)
    assert got == pytest.approx(k, rel=2e-3) and roll == pytest.approx(k, rel=2e-3) and std < 2e-3


def test_the_gyro_scale_std_covers_its_error_in_noisy_flow():
    """With flow noise of 0.05 1/s (about 1.5 px per frame at 320 px) over 10 seeds: unbiased (mean error within
    0.2 %; the same fit without the noise's own normal matrix reads 4 % long), the stated standard errors neither
    too small (RMS of error over σ under 1.6) nor vacuous (over 0.4)."""
    errs, stds = [], []
    for seed in range(10):
        x, y, flow, gyro = swaying_flow(1.1, n=120, m=400, noise=0.05, seed=seed)
        got, std, _ = gyro_scale_with_translation(x, y, flow, gyro)
        errs.append(got / 1.1 - 1)
        stds.append(std / 1.1)
    errs, stds = np.array(errs), np.array(stds)
    assert abs(errs.mean()) < 2e-3, errs
    assert 0.4 < np.sqrt(((errs / stds) ** 2).mean()) < 1.6, (errs, stds)


@pytest.mark.parametrize("factor", [0.78, pytest.param(1.25, marks=pytest.mark.slow)])
def test_the_focal_length_is_found_from_a_wrong_guess(fisheye_run, tmp_path, factor):
    """A 131° equidistant fisheye (fx 140 px at 320×240) turning on three axes: from a guess 22 % short or 25 %
    long, within 3 % of the truth, and within three of its stated standard errors with the systematic 4 %
    (a guess left as it was is 22-25 % off)."""
    true_fx = json.loads((fisheye_run / "camera.json").read_text())["fx"]
    est = estimate_focal_length(open_footage(fisheye_run, camera=_guess(fisheye_run, tmp_path, factor)))
    print(f"\nguess ×{factor}: fx {est.fx:.2f} px (true {true_fx}), slopes {est.steps}")
    assert est.fx == pytest.approx(true_fx, rel=0.03) and est.correlation > 0.9
    assert abs(est.fx / true_fx - 1) < 3 * np.hypot(est.slope_std, FOCAL_SYSTEMATIC_REL_STD)


def test_calibrate_camera_writes_a_camera_that_fixes_the_velocity(fisheye_run, tmp_path, capsys):
    """From a guess 22 % short whose IMU axes are 90° off about the optical axis, the camera.json it writes
    keeps the lens, turns the IMU back within 2.5° and has the focal length within 5 %; velocity read through it is
    right, where through the guess it is never answered (or ≥ 2× worse)."""
    from scipy.spatial.transform import Rotation

    from experiments.cli import main
    from lobula.config import VelocityConfig
    from lobula.velocity import estimate_velocity

    off = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    guess = _guess(fisheye_run, tmp_path, 0.78, imu_to_camera=off)
    out = tmp_path / "calibrated.json"
    assert main(["calibrate-camera", str(fisheye_run), "--camera", str(guess), "--out", str(out)]) == 0
    assert "IMU axes: turned by" in capsys.readouterr().out
    cam = json.loads(out.read_text())
    assert cam["distortion"]["model"] == "kannala-brandt" and cam["calibration"]["frame_pairs"] > 100
    assert np.degrees(Rotation.from_matrix(np.asarray(cam["imu_to_camera"])).magnitude()) < 2.5
    assert cam["fx"] == pytest.approx(json.loads((fisheye_run / "camera.json").read_text())["fx"], rel=0.05)

    def rmse(camera):
        ds = estimate_velocity(open_footage(fisheye_run, camera=camera), VelocityConfig(), progress=False)
        keep = (ds.time > ds.time[0] + 1.5).values & ds.observable.values
        if not keep.any():
            return float("nan")
        return float(np.sqrt(np.mean((ds.v_hat - ds.v_true).values[keep] ** 2)))

    wrong, fixed = rmse(guess), rmse(out)
    print(f"\nRMSE with the guess {wrong:.4f}, calibrated {fixed:.4f} m/s")
    assert fixed < 0.03 and (np.isnan(wrong) or wrong > 2 * fixed)


def test_footage_without_rotation_is_refused_in_one_line(tmp_path):
    from stimuli.track import TrackRunConfig, make_track_run

    run = make_track_run(tmp_path / "still", TrackRunConfig(start_s=3.0, duration_s=2.0, scale=0.25), progress=False)
    with pytest.raises(FootageError, match="too little pan and tilt"):
        estimate_focal_length(open_footage(run))


@pytest.mark.slow  # calibrate-camera's test measures the same focal length in make test
def test_self_calibration_keeps_what_the_gyro_measures(fisheye_run, tmp_path):
    """A camera opened with a lens guess 22 % short (as a GoPro file without intrinsics is): self_calibrate
    measures the focal length, remakes the lens's map at it, and says where it came from; the clock offset it
    estimates is ~0 (the synthetic IMU shares the frames' clock)."""
    from lobula.readers.self_calibration import self_calibrate

    true_fx = json.loads((fisheye_run / "camera.json").read_text())["fx"]
    fo = open_footage(fisheye_run, camera=_guess(fisheye_run, tmp_path, 0.78))
    fo.lens_guess = dict(model="kannala-brandt", coeffs=[0.0, 0.0, 0.0, 0.0], source="a test's short guess",
                         rel_std=0.15)
    cal = self_calibrate(fo)
    assert cal["focal_length_px"] == pytest.approx(true_fx, rel=0.05), cal
    assert "measured against the gyro" in cal["focal_length_source"] and cal["focal_length_rel_std"] < 0.05
    assert fo.distortion["raw_camera"]["fx"] == pytest.approx(cal["focal_length_px"], rel=1e-4)  # stored to 0.01 px
    # the map is the measured lens's: the pinhole it resamples onto keeps the measured focal length (same-k)
    assert fo.camera.fx == pytest.approx(cal["focal_length_px"], rel=1e-4)
    assert abs(cal["clock_offset_s"]) < 0.01 and "estimated" in cal["clock_offset_source"]


def _projection_guess(run, tmp_path, model, factor):
    d = {k: v for k, v in json.loads((run / "camera.json").read_text()).items() if k != "distortion"}
    d["fx"], d["fy"] = d["fx"] * factor, d["fy"] * factor
    if model != "pinhole":
        d["distortion"] = dict(model=model, coeffs=[0, 0, 0, 0])
    (tmp_path / f"{model}.json").write_text(json.dumps(d))
    return tmp_path / f"{model}.json"


def test_the_radial_ratio_is_one_through_the_right_projection(fisheye_run, tmp_path):
    """The 131° equidistant fisheye turning, its focal length guessed 20 % short: through its own projection the
    image's edge turns with its centre (ratio 0.97), read as a pinhole at well under half the speed (0.37)."""
    from lobula.readers.lens_projection import radial_rotation_ratio

    for factor in (0.8,):
        own = radial_rotation_ratio(open_footage(fisheye_run, camera=_projection_guess(
            fisheye_run, tmp_path, "kannala-brandt", factor)))
        flat = radial_rotation_ratio(open_footage(fisheye_run, camera=_projection_guess(
            fisheye_run, tmp_path, "pinhole", factor)))
        print(f"\nfocal ×{factor}: {own.ratio:.3f} ± {own.log_std:.3f} as a fisheye, {flat.ratio:.3f} as a pinhole, "
              f"corner {own.half_diagonal_deg:.0f}°")
        assert abs(np.log(own.ratio)) < 2 * own.log_std + 0.02 and flat.ratio < 0.65


@pytest.mark.slow  # the switch itself runs in make test (tests/test_camera_telemetry.py, an action camera's pinhole)
def test_a_fisheye_taken_for_a_pinhole_is_found_out(fisheye_run, tmp_path):
    """Self-calibration from a pinhole guess 15 % short: the projection is measured as equidistant, and the focal
    length found through it within 5 %."""
    from lobula.readers.self_calibration import self_calibrate

    fo = open_footage(fisheye_run, camera=_projection_guess(fisheye_run, tmp_path, "pinhole", 0.85))
    fo.lens_guess = dict(model="pinhole", coeffs=[], source="a test's pinhole guess", rel_std=0.25)
    cal = self_calibrate(fo)
    print("\n" + cal["projection_source"])
    assert cal["lens"].startswith("equidistant") and cal["projection_source"].startswith("measured"), cal
    assert fo.distortion["model"] == "kannala-brandt" and fo.lens_maps is not None
    assert cal["focal_length_px"] == pytest.approx(json.loads((fisheye_run / "camera.json").read_text())["fx"],
                                                   rel=0.05)
