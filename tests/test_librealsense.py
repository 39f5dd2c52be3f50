"""RealSense recordings written at test time by librealsense itself (pyrealsense2 software_device + recorder).

A synthetic track run with exact truth (frames, accelerometer 250 Hz, gyroscope 400 Hz) is
recorded by the installed librealsense: ≥ 2.58 writes rosbag2 ``.db3``, ≤ 2.57 ROS1 ``.bag``.
The other format is written too when ``LOBULA_PYREALSENSE2_OTHER`` names a folder holding a
pyrealsense2 of the other kind (``pip install --target DIR pyrealsense2==2.56.5.9235``); a
format no available librealsense writes is skipped with the reason. pyrealsense2 is the
optional ``realsense`` extra; on Debian it needs ``apt-get install libusb-1.0-0`` to import.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# ImportError too: pyrealsense2 installed without libusb fails to load its library, which is as absent.
rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 (pip install '.[realsense]'; Debian: apt-get install "
                                                 "libusb-1.0-0) is needed to write genuine RealSense recordings",
                         exc_type=ImportError)

from tests import realsense_writer  # noqa: E402

from experiments.velocity import score  # noqa: E402
from lobula.velocity import estimate_velocity
from lobula.config import VelocityConfig  # noqa: E402
from lobula.readers import open_footage  # noqa: E402
from lobula.readers.core import IMU  # noqa: E402
from stimuli.imu import IMUConfig, synthesize_imu  # noqa: E402
from stimuli.track import TrackRunConfig, build_track, make_track_run  # noqa: E402

HERE = Path(__file__).resolve().parent
OTHER = os.environ.get("LOBULA_PYREALSENSE2_OTHER")
# 320×240, the resolution `lobula scene` and `lobula suite` render at. (At 160×120 the fields' κ
# errs by about ±10 % and zero-phase v̂ carries a constant −0.013 m/s: 0.012–0.013 RMSE.)
CFG = TrackRunConfig(profile=None, start_s=5.0, duration_s=3.0, scale=0.5)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("rs")
    folder = make_track_run(d / "run", CFG, progress=False)
    scene, _ = build_track(CFG)
    g = synthesize_imu(scene, CFG.duration_s, IMUConfig(rate_hz=400.0, seed=7))
    np.savez(d / "gyro.npz", t=g["time_s"], gyro=g["gyro"])
    return folder, d / "gyro.npz", g


_RECORDED: dict[str, Path] = {}


def _record(run, suffix, tmp_path) -> Path:
    """The run recorded by librealsense in this format (once per test session)."""
    if suffix in _RECORDED:
        return _RECORDED[suffix]
    folder, gyro_npz, g = run
    out = folder.parent / f"rec{suffix}"
    if realsense_writer.writes(suffix):
        realsense_writer.record(folder, out, g["time_s"], g["gyro"])
    elif OTHER:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([OTHER, str(HERE.parent)]))
        subprocess.run([sys.executable, str(HERE / "realsense_writer.py"), str(folder), str(out), str(gyro_npz)],
                       check=True, env=env, timeout=120)
    else:
        v = ".".join(map(str, realsense_writer.librealsense_version()))
        pytest.skip(f"librealsense {v} writes {'.db3' if suffix == '.bag' else '.bag'}, not {suffix}; set "
                    f"LOBULA_PYREALSENSE2_OTHER to a pyrealsense2 {'<' if suffix == '.bag' else '>='} 2.58 folder")
    assert out.exists()
    _RECORDED[suffix] = out
    return out


@pytest.mark.parametrize("suffix", [".db3", ".bag"])
def test_librealsense_recording_reads_back_exactly(run, tmp_path, suffix):
    rec = _record(run, suffix, tmp_path)
    folder, _, g = run
    ref, fo = open_footage(folder), open_footage(rec)
    assert fo.kind == ("realsense-db3" if suffix == ".db3" else "realsense-bag")
    assert fo.camera.width == ref.camera.width and abs(fo.camera.fx - ref.camera.fx) < 1e-3
    assert len(fo) == len(ref)
    # device time stamps (ms, as librealsense keeps them): sub-microsecond agreement
    np.testing.assert_allclose(fo.times, ref.times, atol=2e-6)
    np.testing.assert_allclose(fo.imu.time_s, ref.imu.time_s, atol=2e-6)
    np.testing.assert_allclose(fo.imu.accel, ref.imu.accel, atol=1e-5)          # float32 on the way
    gyro_at = np.stack([np.interp(fo.imu.time_s, g["time_s"], g["gyro"][:, j]) for j in range(3)], -1)
    np.testing.assert_allclose(fo.imu.gyro, gyro_at, atol=1e-5)   # 400 Hz onto the 250 Hz accelerometer
    for (i, t, img), (_, _, want) in zip(fo.frames(0, 5), ref.frames(0, 5)):
        np.testing.assert_array_equal(img, np.round(want))


@pytest.mark.parametrize("suffix", [".db3", ".bag"])
@pytest.mark.parametrize("filt, bound, coverage", [
    ("zero-phase", 0.01, None),
    ("causal", 0.05, 0.85),
])
def test_velocity_on_a_librealsense_recording(run, tmp_path, suffix, filt, bound, coverage):
    """The must-show: zero-phase RMSE ≤ 0.01 m/s; causal ≤ 0.05 m/s with truth inside ±2σ for ≥ 85% of frames."""
    rec = _record(run, suffix, tmp_path)
    folder = run[0]
    fo = open_footage(rec)
    fo.truth = open_footage(folder).truth     # a recording has no truth: the scene's, on the same clock
    cfg = VelocityConfig()
    cfg.readout.filter = filt
    ds = estimate_velocity(fo, cfg, progress=False)
    sc = score(ds, 0.75)
    print(f"\n{suffix} {filt}: {sc}")
    assert sc["observable_fraction"] > 0.5
    assert sc["rmse_m_s"] <= bound, sc
    if coverage:
        keep = (ds.time >= ds.time[0] + 0.75).values & ds.observable.values
        inside = np.abs(ds.v_hat - ds.v_true).values[keep] <= 2 * ds.v_std.values[keep]
        assert inside.mean() >= coverage


@pytest.mark.parametrize("suffix", [".db3", ".bag"])
def test_velocity_on_a_recording_equals_velocity_on_its_source(run, tmp_path, suffix):
    """What the reader must guarantee whatever the estimator: the recording gives the source folder's v̂."""
    rec = _record(run, suffix, tmp_path)
    src = open_footage(run[0])
    g = run[2]   # the source with the recording's 400 Hz gyroscope on its accelerometer's times
    src.imu = IMU(src.imu.time_s, src.imu.accel, np.stack(
        [np.interp(src.imu.time_s, g["time_s"], g["gyro"][:, j]) for j in range(3)], -1), "source")
    a = estimate_velocity(src, VelocityConfig(), progress=False)
    b = estimate_velocity(open_footage(rec), VelocityConfig(), progress=False)
    np.testing.assert_allclose(b.time.values, a.time.values, atol=2e-6)
    ok = np.isfinite(a.v_hat.values)
    assert ok.sum() > 30
    np.testing.assert_allclose(b.v_hat.values[ok], a.v_hat.values[ok], atol=2e-3)
