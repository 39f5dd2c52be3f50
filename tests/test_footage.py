"""Footage readers, the .flo reader on the real FlowNet2 pair, the real D435i frames, and bad input."""
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest
import xarray as xr

from experiments.cli import main
from experiments.velocity import score
from lobula.velocity import estimate_velocity
from lobula.camera import PinholeCamera
from lobula.config import VelocityConfig
from lobula.receptive_field import pool_fields, tile_fields
from lobula.readers import open_footage
from lobula.readers.core import FootageError
from lobula.readers.flo import FloUnits, flo_to_normalised, read_flo
from stimuli.scene import SceneConfig
from stimuli.track import TrackRunConfig, make_track_run


# ------------------------------------------------------------------ real data
def test_flo_reader_passes_the_warp_check(d435i):
    """Warping 528 back onto 522 with the FlowNet2 flow halves the photometric error (README: 14.8 → 7.5)."""
    pair = d435i / "flownet2_pair"
    flow = read_flo(pair / "flownet2_522_to_528.flo")
    assert flow.shape == (2, 448, 640)
    cam = PinholeCamera.from_json(d435i / "camera.json")
    g = [cv2.resize(cv2.imread(str(pair / f"{k}.png"), cv2.IMREAD_GRAYSCALE), (640, 448)).astype(np.float32)
         for k in (522, 528)]
    u, v = np.meshgrid(np.arange(640, dtype=np.float32), np.arange(448, dtype=np.float32))
    mu = (u + flow[0] * 0.2 * cam.fx).astype(np.float32)
    mv = (v + flow[1] * 0.2 * cam.fx).astype(np.float32)
    warped = cv2.remap(g[1], mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    before, after = np.abs(g[1] - g[0]).mean(), np.abs(warped - g[0]).mean()
    # Measured here on grey levels: 13.9 -> 7.6 (the README's 14.8 -> 7.5 is on its own grey conversion).
    assert 13.0 < before < 16.0 and 6.5 < after < 8.5 and after < 0.6 * before, (before, after)


def test_flownet2_pair_shows_backward_motion(d435i):
    """Camera backing away at ~0.2 m/s from panels ~0.5–3 m away: r = v/d between about −0.4 and −0.07 1/s."""
    cam = PinholeCamera.from_json(d435i / "camera.json")
    flow = flo_to_normalised(read_flo(d435i / "flownet2_pair" / "flownet2_522_to_528.flo"), cam, FloUnits())
    r, _ = pool_fields(flow, tile_fields(cam))
    med = np.nanmedian(r)
    assert -0.4 < med < -0.07, med
    assert np.mean(r < 0) > 0.8


def test_flo_units_in_pixels_convert_the_same_way(d435i):
    cam = PinholeCamera.from_json(d435i / "camera.json")
    raw = read_flo(d435i / "flownet2_pair" / "flownet2_522_to_528.flo")
    a = flo_to_normalised(raw, cam, FloUnits("rad/s", 0.2, 640, 448))
    b = flo_to_normalised(raw * 0.2 * cam.fx, cam, FloUnits("px", 0.2, 640, 448))
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_d435i_sample_layout_is_read_as_it_is(d435i):
    fo = open_footage(d435i)
    assert fo.kind == "d435i-sample" and len(fo) == 36 and fo.imu is None
    # raw_frame = sample + 3: frame 0705 is sample 702.
    np.testing.assert_allclose(fo.times[0], fo.truth["time_s"][702])
    assert np.allclose(np.diff(fo.times), 1 / 30, atol=2e-3)
    assert "derived from the ground-truth" in fo.notes[0]


def test_real_frames_velocity_tracks_the_truth(d435i, tmp_path):
    """Real D435i frames 0705–0740 (1.2 s, accelerating 0.2 → 0.6 m/s), DIS, acceleration from truth.

    Measured: RMSE 0.093 m/s over the clip (zero-phase), 0.093 (causal). The bound has margin.
    """
    ds = estimate_velocity(open_footage(d435i), VelocityConfig(), progress=False)
    sc = score(ds, skip_s=0.0)
    assert sc["observable_fraction"] > 0.7
    assert sc["rmse_m_s"] < 0.2, sc
    # It tracks: the estimate rises with the truth over the clip.
    v = ds.v_hat.values
    ok = np.isfinite(v)
    assert np.corrcoef(v[ok], ds.v_true.values[ok])[0, 1] > 0.8
    assert "ground truth" in ds.attrs["acceleration_source"]


# ------------------------------------------------------------------ bad input
@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """2 s of a small (160×120) synthetic run in motion."""
    cfg = TrackRunConfig(profile=None, start_s=6.0, duration_s=2.0, scale=0.25, scene=SceneConfig(seed=2))
    return make_track_run(tmp_path_factory.mktemp("small") / "run", cfg, progress=False)


@pytest.fixture
def broken(small_run, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(small_run, dst)
    return dst


def run_cli(folder, out, capsys, *extra):
    code = main(["velocity", str(folder), "--out", str(out), "--quiet", *extra])
    err = capsys.readouterr().err.strip()
    return code, err


def test_small_run_works(small_run, tmp_path, capsys):
    code = main(["velocity", str(small_run), "--out", str(tmp_path / "ok.nc"), "--quiet"])
    assert code == 0
    ds = xr.open_dataset(tmp_path / "ok.nc")
    assert {"v_hat", "observable", "accel", "r", "r2", "r_dot", "v_field", "v_true"} <= set(ds)
    assert set(ds.r.dims) == {"time", "field"}
    assert {"azimuth_deg", "elevation_deg", "size_deg"} <= set(ds.coords)
    cfg = VelocityConfig.from_json(ds.attrs["config"])
    assert cfg.front_end == "dis" and ds.attrs["lobula_version"]
    assert ds.attrs["filter"] == "zero-phase" and "output_latency_s" not in ds.attrs  # offline: the whole record


def test_accel_scale_error_option_widens_the_band_by_its_share(small_run, tmp_path, capsys):
    """--accel-scale-error adds FRACTION·|v̂| to v_std in quadrature and moves nothing else; refused where no
    posterior std is stated (--paper) and out of range."""
    out = {}
    for frac in ("0", "0.1"):
        # a walking pace's prior and no coupling test: a 2 s clip is answered (see the --coupling test)
        assert run_cli(small_run, tmp_path / f"s{frac}.nc", capsys, "--accel-scale-error", frac,
                       "--speed-prior", "1", "--coupling", "0")[0] == 0
        with xr.open_dataset(tmp_path / f"s{frac}.nc") as ds:
            out[frac] = ds.load()
            assert VelocityConfig.from_json(ds.attrs["config"]).readout.accel_scale_error == float(frac)
    a, b = out["0"], out["0.1"]
    both = a.observable.values & b.observable.values
    assert both.sum() > 10
    np.testing.assert_allclose(b.v_hat.values[both], a.v_hat.values[both])
    np.testing.assert_allclose(b.v_std.values[both] ** 2,
                               a.v_std.values[both] ** 2 + (0.1 * a.v_hat.values[both]) ** 2, rtol=1e-6)
    code, err = run_cli(small_run, tmp_path / "p.nc", capsys, "--paper", "--accel-scale-error", "0.02")
    assert code == 2 and "--paper" in err and not (tmp_path / "p.nc").exists()
    code, err = run_cli(small_run, tmp_path / "n.nc", capsys, "--accel-scale-error", "-1")
    assert code == 2 and "accel_scale_error" in err and not (tmp_path / "n.nc").exists()


def test_lag_option_smooths_with_look_ahead_online_and_is_refused_offline(small_run, tmp_path, capsys):
    """--lag reaches the causal readout (stored in the configuration and the filter attribute) and changes
    its estimate; with the default zero-phase filter, or negative, it is refused and nothing is written.
    The output says when each v̂ is known: its pair's second frame, half the 6-frame gap (0.1 s at 30
    frames/s) after the pair's middle it is stamped with, plus the lag; and how late its vision
    measurements are (11 frames, the online low-pass cut at 1.5σ plus half the material stagger)."""
    out = {}
    for lag in ("0", "0.5"):
        assert run_cli(small_run, tmp_path / f"l{lag}.nc", capsys, "--filter", "causal", "--lag", lag,
                       "--speed-prior", "1", "--coupling", "0")[0] == 0
        with xr.open_dataset(tmp_path / f"l{lag}.nc") as ds:
            out[lag] = ds.load()
            assert VelocityConfig.from_json(ds.attrs["config"]).readout.lag_s == float(lag)
            assert ds.attrs["output_latency_s"] == pytest.approx(0.1 + float(lag), abs=1e-3)
            assert ds.attrs["measurement_delay_s"] == pytest.approx(11 / 30, abs=1e-3)
    assert out["0"].attrs["filter"] == "causal (each v_hat known 0.1 s after its time)"
    assert "fixed lag 0.5 s (each v_hat known 0.6 s after its time)" in out["0.5"].attrs["filter"]
    # the paper's causal readout stamps a pair at its first frame: known a whole gap later, no bridge to declare
    assert run_cli(small_run, tmp_path / "paper.nc", capsys, "--paper", "--filter", "causal")[0] == 0
    with xr.open_dataset(tmp_path / "paper.nc") as ds:
        assert ds.attrs["output_latency_s"] == pytest.approx(0.2, abs=1e-3) and "measurement_delay_s" not in ds.attrs
    both = out["0"].observable.values & out["0.5"].observable.values
    assert both.sum() > 5 and not np.allclose(out["0"].v_std.values[both], out["0.5"].v_std.values[both])
    for extra, said in ((("--lag", "1"), "give --filter causal"), (("--filter", "causal", "--lag", "-1"), "--lag")):
        code, err = run_cli(small_run, tmp_path / "bad.nc", capsys, *extra)
        assert code == 2 and said in err and not (tmp_path / "bad.nc").exists()


@pytest.mark.parametrize("damage, needle", [
    ("no_imu", "imu.csv"),
    ("missing_frame", "frames.csv"),
    ("corrupt_png", "000007.png"),
    ("nan_imu", "imu.csv"),
    ("time_backwards", "frames.csv"),
    ("imu_elsewhere", "imu.csv"),
])
def test_bad_input_gives_one_line_error_and_no_output(broken, tmp_path, capsys, damage, needle):
    if damage == "no_imu":
        (broken / "imu.csv").unlink()
    elif damage == "missing_frame":
        (broken / "frames" / "000010.png").unlink()
    elif damage == "corrupt_png":
        (broken / "frames" / "000007.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)
    elif damage == "nan_imu":
        lines = (broken / "imu.csv").read_text().splitlines()
        lines[40] = ",".join(["0.16"] + ["nan"] * 6)
        (broken / "imu.csv").write_text("\n".join(lines) + "\n")
    elif damage == "time_backwards":
        lines = (broken / "frames.csv").read_text().splitlines()
        lines[5], lines[6] = lines[6], lines[5]
        (broken / "frames.csv").write_text("\n".join(lines) + "\n")
    elif damage == "imu_elsewhere":
        lines = (broken / "imu.csv").read_text().splitlines()
        shifted = [lines[0]] + [",".join([f"{float(l.split(',')[0]) + 100:.6f}"] + l.split(",")[1:]) for l in lines[1:]]
        (broken / "imu.csv").write_text("\n".join(shifted) + "\n")
    out = tmp_path / "out.nc"
    code, err = run_cli(broken, out, capsys)
    assert code == 2
    assert len(err.splitlines()) == 1 and needle in err, err
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.nc")]


def test_missing_imu_can_fall_back_to_truth_when_asked(broken, tmp_path, capsys):
    (broken / "imu.csv").unlink()
    code, _ = run_cli(broken, tmp_path / "o.nc", capsys, "--accel-from-truth")
    assert code == 0
    assert "truth" in xr.open_dataset(tmp_path / "o.nc").accel.attrs["source"]


def test_zero_acceleration_is_all_unobservable(tmp_path, capsys):
    """Constant velocity: flow alone cannot tell speed from distance, so nothing may be claimed."""
    cfg = TrackRunConfig(constant_velocity_m_s=0.3, duration_s=3.0, scale=0.25, scene=SceneConfig(seed=1))
    run = make_track_run(tmp_path / "const", cfg, progress=False)
    out = tmp_path / "gravity-only.nc"
    code, _ = run_cli(run, out, capsys)
    assert code == 0
    ds = xr.open_dataset(out)
    assert not ds.observable.any()
    assert np.isnan(ds.v_hat).all() and not np.isinf(ds.v_field).any()
    # an accelerometer reading no gravity at all is a dead sensor, not a steady motion: refused by the reader
    lines = (run / "imu.csv").read_text().splitlines()
    rows = [lines[0]] + [",".join([l.split(",")[0]] + ["0"] * 6) for l in lines[1:]]
    (run / "imu.csv").write_text("\n".join(rows) + "\n")
    code, err = run_cli(run, tmp_path / "all-zero.nc", capsys)
    assert code == 2 and "reads no gravity" in err and not (tmp_path / "all-zero.nc").exists()


def test_existing_scene_folder_is_not_overwritten(small_run, capsys):
    code = main(["scene", str(small_run), "--duration", "0.2", "--quiet"])
    assert code == 2 and "exists" in capsys.readouterr().err


def test_coupling_option_sets_the_test_vision_must_pass(small_run, tmp_path, capsys):
    """--coupling sets ReadoutConfig.coupling_z (written to the file's config): a 2 s clip holds about 4 effective
    samples, too few for the default z of 3 beyond its first 1.5 s, so only its start is answered; with 0 the
    posterior decides alone. Refused with --paper (no such test) and below 0."""
    obs = {}
    for z in ("3", "0"):
        assert run_cli(small_run, tmp_path / f"c{z}.nc", capsys, "--coupling", z, "--speed-prior", "1")[0] == 0
        with xr.open_dataset(tmp_path / f"c{z}.nc") as ds:
            assert VelocityConfig.from_json(ds.attrs["config"]).readout.coupling_z == float(z)
            obs[z] = ds.observable.values.astype(bool)
            late = ds.time.values > ds.time.values[0] + 1.6
    assert not obs["3"][late].any() and obs["0"][late].mean() > 0.5, {k: v.mean() for k, v in obs.items()}
    code, err = run_cli(small_run, tmp_path / "cp.nc", capsys, "--paper", "--coupling", "0")
    assert code == 2 and "--paper" in err and not (tmp_path / "cp.nc").exists()
    code, err = run_cli(small_run, tmp_path / "cn.nc", capsys, "--coupling", "-1")
    assert code == 2 and "--coupling" in err and not (tmp_path / "cn.nc").exists()


def test_speed_prior_option_sets_the_readouts_prior(small_run, tmp_path, capsys):
    """--speed-prior sets ReadoutConfig.v_prior_m_s (written to the file's config); the narrower prior answers
    sooner on a short clip; refused with --paper (whose median readout has no prior)."""
    obs = {}
    for prior in ("1", "15"):
        assert run_cli(small_run, tmp_path / f"p{prior}.nc", capsys, "--speed-prior", prior, "--coupling", "0")[0] == 0
        with xr.open_dataset(tmp_path / f"p{prior}.nc") as ds:
            assert VelocityConfig.from_json(ds.attrs["config"]).readout.v_prior_m_s == float(prior)
            obs[prior] = float(ds.observable.mean())
    assert obs["1"] > obs["15"], obs
    code, err = run_cli(small_run, tmp_path / "pp.nc", capsys, "--paper", "--speed-prior", "1")
    assert code == 2 and "--paper" in err and not (tmp_path / "pp.nc").exists()
