"""lobula.rolling_shutter: a rolling shutter's flow put back on the frames' times for the rotation."""
import functools
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from lobula.camera import PinholeCamera
from lobula.readers.core import FootageError, read_camera_json
from lobula.rolling_shutter import global_shutter_flow, pixel_delays

CAM = PinholeCamera(width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5, frame_rate_hz=30.0,
                    rolling_shutter_s=0.03)
W0, ALPHA = np.array([0.3, -0.5, 0.2]), np.array([-2.0, 3.0, 1.0])  # rad/s and rad/s²: a turn speeding up


@functools.lru_cache(maxsize=1)
def _turning():
    """The camera's orientation track, camera → world, turning at ω(t) = W0 + ALPHA·t (integrated in 0.1 ms steps)."""
    fine = np.linspace(0.0, 1.0, 10001)
    w = W0 + np.outer(fine, ALPHA)
    steps = Rotation.from_rotvec(0.5 * (w[1:] + w[:-1]) * np.diff(fine)[:, None]).as_matrix()
    q = np.empty((len(fine), 3, 3))
    q[0] = np.eye(3)
    for k, s in enumerate(steps):
        q[k + 1] = q[k] @ s
    return Slerp(fine, Rotation.from_matrix(q))


def attitude(t):
    """Camera → world rotations (k, 3, 3) at times t (k,) s."""
    return _turning()(np.atleast_1d(np.asarray(t, float))).as_matrix()


def _project(d):
    return d[0] / d[2], d[1] / d[2]


def _rolling_flow(x, y, t0, t1, delay_of):
    """The flow a rolling shutter sees of a scene at infinity: pixel p exposed at t0 + δ(p) sees the direction w;
    at t1 it is seen at the pixel p1 whose own exposure t1 + δ(p1) turns w onto its ray (found by iteration)."""
    q0 = attitude(t0 + delay_of(y).ravel()).reshape(*x.shape, 3, 3)
    w = np.einsum("...ij,j...->...i", q0, np.stack([x, y, np.ones_like(x)]))
    x1, y1 = x.copy(), y.copy()
    for _ in range(6):
        q1 = attitude(t1 + delay_of(y1).ravel()).reshape(*x.shape, 3, 3)
        d = np.einsum("...ji,...j->...i", q1, w)
        x1, y1 = d[..., 0] / d[..., 2], d[..., 1] / d[..., 2]
    return np.stack([(x1 - x) / (t1 - t0), (y1 - y) / (t1 - t0)])


def test_the_flow_of_a_turn_comes_back_to_a_global_shutters():
    """A scene at infinity, the camera turning faster and faster: the rolling shutter's flow, put back on the
    frames' times, is the flow a global shutter sees, to 2 % of what the rolling shutter changed (1 % at the
    median)."""
    x, y = CAM.normalised_grid()
    t0, t1 = 0.2, 0.4
    delays = pixel_delays(y, CAM, CAM.rolling_shutter_s)
    assert delays[0, 0] == 0.0 and delays[-1, 0] == pytest.approx(0.03 * 119 / 120)
    measured = _rolling_flow(x, y, t0, t1, lambda yy: 0.03 * np.clip(CAM.fy * yy + CAM.cy, 0, 119) / 120)
    q = attitude([t0, t1])
    X1, Y1 = _project(np.einsum("ij,j...->i...", q[1].T @ q[0], np.stack([x, y, np.ones_like(x)])))
    truth = np.stack([(X1 - x) / (t1 - t0), (Y1 - y) / (t1 - t0)])
    back = global_shutter_flow(x, y, measured, t0, t1, delays, attitude)
    inner = (slice(None), slice(5, -5), slice(5, -5))  # the remap's border
    left, before = np.abs(back - truth)[inner], np.abs(measured - truth)[inner]
    assert before.max() > 0.02  # the shutter moved the flow by more than the translation of a slow walk
    assert left.max() < 0.02 * before.max() and np.median(left) < 0.01 * np.median(before)


def test_a_global_shutter_is_left_as_it_is():
    x, y = CAM.normalised_grid()
    flow = np.random.default_rng(0).normal(0, 0.1, (2,) + x.shape)
    assert global_shutter_flow(x, y, flow, 0.2, 0.4, np.zeros_like(x), attitude) is flow


def test_a_lens_sets_the_delay_by_its_raw_row():
    """Through a lens resampled onto a pinhole, a pixel's delay is its raw sensor row's."""
    x, y = CAM.normalised_grid()
    map_x = np.zeros((120, 160), np.float32)
    map_y = np.tile(np.linspace(20, 100, 120, dtype=np.float32)[:, None], (1, 160))
    d = pixel_delays(y, CAM, 0.03, (map_x, map_y))
    np.testing.assert_allclose(d[:, 7], 0.03 * np.linspace(20, 100, 120) / 120, rtol=1e-5)


def test_camera_json_reads_the_readout(tmp_path):
    base = dict(width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5, frame_rate_hz=30.0)
    p = tmp_path / "camera.json"
    p.write_text(json.dumps(dict(base, rolling_shutter_s=0.02)))
    assert read_camera_json(p).rolling_shutter_s == 0.02
    p.write_text(json.dumps(base))
    assert read_camera_json(p).rolling_shutter_s == 0.0 and "rolling_shutter_s" not in read_camera_json(p).to_dict()
    for bad in (-0.01, 0.05, "fast"):
        p.write_text(json.dumps(dict(base, rolling_shutter_s=bad)))
        with pytest.raises(FootageError, match="rolling_shutter_s"):
            read_camera_json(p)


@pytest.fixture(scope="module")
def rolling_run(tmp_path_factory):
    """A 160×120 run turning on three axes (3 s), its rows read out over 33 ms."""
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, make_track_run

    cfg = TrackRunConfig(start_s=3.0, duration_s=3.0, scale=0.25,
                         scene=SceneConfig(seed=2, rotation3_amp_deg=(5.0, 5.0, 5.0), rolling_shutter_s=0.033))
    return make_track_run(tmp_path_factory.mktemp("rolling") / "run", cfg, progress=False)


def _causal_rmse(run, **kwargs) -> float:
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage
    from lobula.readout import ReadoutConfig
    from lobula.velocity.pipeline import estimate_velocity

    ds = estimate_velocity(open_footage(run, **kwargs), VelocityConfig(readout=ReadoutConfig(filter="causal")),
                           progress=False)
    late = (ds.time.values - ds.time.values[0] >= 0.5) & ds.observable.values.astype(bool)
    return float(np.sqrt(np.mean((ds.v_hat - ds.v_true).values[late] ** 2)))


def test_a_rolling_shutter_run_reads_as_a_global_shutter_does(rolling_run):
    """The run's camera.json states its readout; read with it, the causal error is 0.012 m/s (a global shutter's
    render of the same run: 0.004), read as a global shutter (--rolling-shutter 0) 0.157."""
    from lobula.readers import open_footage

    assert open_footage(rolling_run).camera.rolling_shutter_s == pytest.approx(0.033)
    corrected, ignored = _causal_rmse(rolling_run), _causal_rmse(rolling_run, rolling_shutter=0.0)
    assert corrected < 0.015 and ignored > 5 * corrected, (corrected, ignored)


def test_the_option_sets_the_readout_or_says_why_not(rolling_run, capsys):
    from experiments.cli import main
    from lobula.readers import open_footage

    fo = open_footage(rolling_run, rolling_shutter=0.02)
    assert fo.camera.rolling_shutter_s == 0.02 and any(n.startswith("rolling shutter: 20.0 ms") for n in fo.notes)
    code = main(["velocity", str(rolling_run), "--out", str(rolling_run.parent / "o.nc"), "--rolling-shutter",
                 "0.05", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "--rolling-shutter 0.05" in err and "Traceback" not in err
    assert not (rolling_run.parent / "o.nc").exists()


@pytest.mark.slow
def test_depth_on_a_rolling_shutter_run(rolling_run):
    """The depth pass puts the rows back on the frames' times as the velocity run does: with the truth's speed,
    ratio depth's AbsRel 0.17 (a global shutter's render: 0.14) where read as a global shutter it is 0.39."""
    from experiments.depth_stream import DepthRunConfig, estimate_depth
    from lobula.readers import open_footage

    scores = {}
    for readout in (None, 0.0):
        ds = estimate_depth(open_footage(rolling_run, rolling_shutter=readout),
                            run=DepthRunConfig(method="ratio", every=10, velocity="truth"), progress=False)
        scores[readout] = float(ds.pooled_abs_rel.sel(ring="all"))
    assert scores[None] < 0.22 and scores[0.0] > 1.8 * scores[None], scores


def test_where_the_shutter_cannot_be_corrected_the_output_says_so(rolling_run):
    """Without a gyro, with derotation off, or through a front end that pools its own fields, the rows cannot be
    put back on the frames' times: the notes (and so the output's attrs) say which."""
    from dataclasses import replace

    from lobula.config import VelocityConfig
    from lobula.front_ends import get_front_end
    from lobula.readers import open_footage
    from lobula.readers.core import IMU
    from lobula.velocity.pipeline import _note_uncorrected_shutter

    cases = [(VelocityConfig(), "dis", None), (replace(VelocityConfig(), derotate=False), "dis", "derotation is off"),
             (VelocityConfig(), "emd", "the emd front end pools its own fields, not flow"),
             (VelocityConfig(), "dis", "no gyro")]
    for config, front, why in cases:
        fo = open_footage(rolling_run)
        if why == "no gyro":
            fo.imu = IMU(fo.imu.time_s, fo.imu.accel, None, "no gyro")
            why = "the footage has no gyro"
        _note_uncorrected_shutter(fo, config, get_front_end(front))
        said = [n for n in fo.notes if n.startswith("rolling shutter (33.0 ms) not corrected")]
        assert said == ([] if why is None else [f"rolling shutter (33.0 ms) not corrected: {why}"])
