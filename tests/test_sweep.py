"""`lobula sweep`: parameter grids with Dask, results in Zarr, resumable after an interruption."""
import argparse
import json

import numpy as np
import pytest
import xarray as xr

from experiments.sweep import (COUNTER_ENV, SweepError, SweepInterrupted, SweepSpec, add_parser, estimate_sweep_s,
                               parse_param, run_sweep, sweep_paths)
from lobula.config import VelocityConfig
from stimuli.track import TrackRunConfig

TINY = dict(profile=None, start_s=5.0, duration_s=3.0, scale=0.25)


def _cli(argv):
    p = argparse.ArgumentParser(prog="lobula")
    add_parser(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(argv)
    return args.func(args)


def _counted(path):
    return path.read_text().split() if path.exists() else []


def test_parameter_paths_types_and_errors():
    vel, run = VelocityConfig(), TrackRunConfig()
    p = parse_param("emd.emd.tau_s=0.005,0.01,0.035", vel, run)
    assert p.targets == ("velocity.emd.emd.tau_s",) and p.values == [0.005, 0.01, 0.035]
    assert parse_param("flow.gap=3,6", vel, run).values == [3, 6]
    assert parse_param("scene.noise_grey=0,2", vel, run).values == [0.0, 2.0]  # float field: ints become floats
    assert parse_param("derotate=true,false", vel, run).values == [True, False]
    assert parse_param("seed=0,1", vel, run).targets == ("run.scene.seed", "run.imu.seed")
    assert parse_param("readout.cutoff_hz=log:0.5:2:3", vel, run).values == pytest.approx([0.5, 1.0, 2.0])
    assert parse_param("fields.spacing_deg=none,5", vel, run).values == [None, 5]
    assert parse_param("scene.texture_wavelengths_m=[[0.03,0.4],[0.01,0.2]]", vel, run).values == [(0.03, 0.4), (0.01, 0.2)]
    with pytest.raises(SweepError, match="size_deg"):
        parse_param("fields.size=3,5", vel, run)  # unknown, with a suggestion
    with pytest.raises(SweepError, match="group"):
        parse_param("emd.lattice=1,2", vel, run)
    with pytest.raises(SweepError, match="flo"):
        parse_param("front_end=dis,flo", vel, run)
    with pytest.raises(SweepError, match="integer"):
        parse_param("flow.gap=2.5", vel, run)
    with pytest.raises(SweepError, match="twice"):
        parse_param("flow.gap=3,3", vel, run)
    with pytest.raises(SweepError, match="epipole"):  # validation by the dataclass itself (replace re-runs it)
        SweepSpec.from_strings(["epipole=estimate,nowhere"]).points()

    spec = SweepSpec.from_strings(["front_end=dis,emd", "emd.lattice.dphi_deg=0.75,1.5", "scale=0.25,0.5"])
    pts = spec.points()
    assert spec.shape == (2, 2, 2) and len(pts) == 8
    assert spec.velocity.emd.lattice.dphi_deg == 0.75  # the frozen base is never mutated
    assert {p.velocity.emd.lattice.dphi_deg for p in pts} == {0.75, 1.5}
    # Δφ does not matter to a DIS point: those share one computation; renders depend only on the run.
    assert len({p.key for p in pts}) == 6
    assert len({p.run_key for p in pts}) == 2


@pytest.fixture
def counter(tmp_path, monkeypatch):
    path = tmp_path / "computed.txt"
    monkeypatch.setenv(COUNTER_ENV, str(path))
    return path


@pytest.mark.slow
def test_sweep_grid_resume_after_lost_record_and_same_numbers(tmp_path, counter):
    """2 scenes × 2 field sizes on tiny runs (threads): dims, coords, metrics; a deleted record is the
    only point recomputed, and it comes back with the same numbers; one point matches a direct run."""
    spec = SweepSpec.from_strings(["scene.seed=0,1", "fields.size_deg=5,10"], run=TrackRunConfig(**TINY), skip_s=1.0)
    out = tmp_path / "grid.zarr"
    run_sweep(spec, out, scheduler="threads", workers=2, progress=False)
    ds = xr.open_zarr(out).load()
    assert list(ds.rmse_m_s.dims) == ["scene.seed", "fields.size_deg"]
    assert list(ds["scene.seed"].values) == [0, 1] and list(ds["fields.size_deg"].values) == [5.0, 10.0]
    for k in ("rmse_m_s", "median_abs_error_m_s", "observable_fraction", "r_rel_error", "render_s", "point_wall_s"):
        assert np.all(np.isfinite(ds[k].values)), k
    assert np.all(ds.rmse_m_s.values < 0.3) and bool(ds.done.all())
    assert ds.v_hat.dims == ("scene.seed", "fields.size_deg", "time") and ds.sizes["time"] == 90
    assert json.loads(ds.attrs["sweep"])["dims"] == ["scene.seed", "fields.size_deg"]
    assert VelocityConfig.from_json(ds.attrs["base_velocity_config"]).fields.size_deg == 5.0
    assert ds.attrs["lobula_version"] and ds.attrs["points_computed"] == 4
    assert sorted(_counted(counter)) == sorted(ds.point_key.values.ravel())
    _, points, renders = sweep_paths(out)
    assert len(list(points.glob("*.json"))) == 4 and not renders.exists()  # renders removed when done

    lost = ds.point_key.values[1, 0]
    (points / f"{lost}.json").unlink()
    counter.unlink()
    run_sweep(spec, out, scheduler="threads", workers=2, progress=False)
    again = xr.open_zarr(out).load()
    assert _counted(counter) == [lost] and again.attrs["points_computed"] == 1 and again.attrs["points_reused"] == 3
    for k in ("rmse_m_s", "median_abs_error_m_s", "lock_on_s", "r_rmse_1_s", "v_hat"):
        np.testing.assert_array_equal(again[k].values, ds[k].values)  # same seed, same numbers

    # The recomputed point against a direct render + estimate_velocity + score.
    from experiments.velocity import score
    from lobula.velocity import estimate_velocity
    from lobula.readers import open_footage
    from stimuli.track import make_track_run
    pt = next(p for p in spec.points() if p.key == lost)
    fo = open_footage(make_track_run(tmp_path / "direct", pt.run, progress=False))
    direct = score(estimate_velocity(fo, pt.velocity, progress=False), 1.0)
    assert direct["rmse_m_s"] == float(again.rmse_m_s.values[1, 0])


def test_killed_sweep_restarts_without_recomputing_finished_points(tmp_path, counter, capsys):
    """Local dask processes; the sweep stops after 2 of 4 points, then the same command (CLI, threads
    this time) resumes, reusing the render and recomputing only the unrecorded points.

    320×240 DIS runs of 1.6 s also give per-frame costs for the 100-point estimate printed at the end."""
    run = TrackRunConfig(profile=None, start_s=5.0, duration_s=1.6, scale=0.5)
    # a walking-pace speed prior (m/s): 1.6 s is too short for the default's, which allows for cars and drones
    params = ["readout.cutoff_hz=1,2", "readout.v_prior_m_s=0.5,1"]
    spec = SweepSpec.from_strings(params, run=run, skip_s=0.5)
    out = tmp_path / "killed.zarr"
    with pytest.raises(SweepInterrupted):
        run_sweep(spec, out, scheduler="processes", workers=2, progress=False, stop_after=2, keep_renders=True)
    _, points, renders = sweep_paths(out)
    recorded = {p.stem for p in points.glob("*.json")}
    assert len(recorded) >= 2 and not out.exists()  # nothing half-written under the final name
    counter.unlink()
    rc = _cli(["sweep", *sum((["--param", p] for p in params), []), "--builtin-profile", "--start", "5",
               "--base-duration", "1.6", "--scale", "0.5", "--skip", "0.5", "--out", str(out),
               "--scheduler", "threads", "--workers", "2", "--quiet"])
    assert rc == 0
    ds = xr.open_zarr(out).load()
    all_keys = set(ds.point_key.values.ravel())
    assert set(_counted(counter)) == all_keys - recorded and len(_counted(counter)) == len(all_keys - recorded)
    assert ds.attrs["points_reused"] == len(recorded) and bool(ds.done.all())
    assert list(ds.rmse_m_s.dims) == ["readout.cutoff_hz", "readout.v_prior_m_s"]
    assert np.all(np.isfinite(ds.rmse_m_s.values))
    assert not renders.exists()

    # Per-frame costs at 320×240 → a 100-point sweep of the 30 s replay (900 frames) with DIS, 2 workers.
    frames = ds.sizes["time"]
    render_s = float(np.nanmax(ds.render_s.values)) / frames * 900
    point_s = float(np.nanmean(ds.point_wall_s.values)) / frames * 900
    with capsys.disabled():
        print(f"\n(on this machine now) 320×240 per frame: render {1000 * render_s / 900:.0f} ms, DIS point {1000 * point_s / 900:.0f} ms; "
              f"30 s replay: render {render_s:.0f} s, point {point_s:.0f} s. 100-point sweep on 2 workers: "
              f"{estimate_sweep_s(100, 1, point_s, render_s) / 60:.0f} min sharing one render, "
              f"{estimate_sweep_s(100, 10, point_s, render_s) / 60:.0f} min with 10 scenes, "
              f"{estimate_sweep_s(100, 100, point_s, render_s) / 60:.0f} min with 100 scenes")


def test_cli_dry_run_and_list_params(tmp_path, capsys):
    assert _cli(["sweep", "--list-params"]) == 0
    listed = capsys.readouterr().out
    assert "emd.emd.tau_s" in listed and "scene.seed" in listed and "imu.accel_noise_density" in listed
    assert _cli(["sweep", "--param", "front_end=dis,emd", "--param", "seed=0,1,2", "--out",
                 str(tmp_path / "s.zarr"), "--dry-run", "--builtin-profile"]) == 0
    assert "6 points (2 × 3)" in capsys.readouterr().out


def test_sweeping_the_front_end_gives_each_its_own_defaults():
    """front_end=emd in a sweep runs the EMD path as `VelocityConfig(front_end="emd")` does: the principal
    point for its epipole and the EMD fields' κ errors (not DIS's)."""
    from experiments.sweep_params import apply_value
    from lobula.config import VelocityConfig
    from stimuli.track import TrackRunConfig

    vel, _ = apply_value("velocity.front_end", "emd", VelocityConfig(), TrackRunConfig())
    want = VelocityConfig(front_end="emd")
    assert (vel.epipole, vel.readout.kappa_rel_error, vel.readout.shared_error_frac) == \
        (want.epipole, want.readout.kappa_rel_error, want.readout.shared_error_frac) == ("principal", 0.5, 0.8)
    back, _ = apply_value("velocity.front_end", "dis", vel, TrackRunConfig())
    assert back.readout.kappa_rel_error == VelocityConfig().readout.kappa_rel_error


def test_the_summary_names_the_lowest_mean_not_the_luckiest_point():
    from experiments.sweep import rmse_summary

    # size × seed: the single lowest point is at 15° (seed 2), yet 15° has the worst mean over seeds.
    r = np.array([[0.010, 0.012, 0.011], [0.013, 0.014, 0.012], [0.030, 0.025, 0.005]])
    ds = xr.Dataset({"rmse_m_s": (("fields.size_deg", "seed"), r)},
                    coords={"fields.size_deg": [5.0, 10.0, 15.0], "seed": [0, 1, 2]})
    lines = rmse_summary(ds, ["fields.size_deg", "seed"])
    assert "lowest single point: fields.size_deg=15, seed=2" in lines[0]
    size = next(ln for ln in lines if ln.startswith("fields.size_deg:"))
    assert "mean RMSE over the 3 values of seed" in size and "5: 0.0110; 10: 0.0130; 15: 0.0200" in size
    assert size.endswith("lowest at fields.size_deg=5")
    assert int(np.argmin(r.mean(1))) == 0                      # the known answer: argmin of the mean
    # Failed points (NaN): a value with points missing is flagged and not preferred over a complete one.
    r2 = r.copy()
    r2[0, :2] = np.nan
    lines = rmse_summary(ds.assign(rmse_m_s=(("fields.size_deg", "seed"), r2)), ["fields.size_deg", "seed"])
    size = next(ln for ln in lines if ln.startswith("fields.size_deg:"))
    assert "5: 0.0110 (1 of 3 scored)" in size and size.endswith("lowest at fields.size_deg=10")
    assert "over 7 of 9 points" in lines[0]
    assert rmse_summary(ds.assign(rmse_m_s=ds.rmse_m_s * np.nan), ["fields.size_deg", "seed"]) == [
        "RMSE: no point was scored (every point's RMSE is NaN)"]


def test_a_sweep_whose_every_point_fails_writes_no_store(tmp_path, monkeypatch):
    """A store of NaN alone would read as a result: when no point succeeds (here a full disk under the
    renders) the sweep says the first failure and leaves no store."""
    import errno

    from experiments import sweep

    def full_disk(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(sweep, "ensure_render", lambda *a, **k: "render")
    monkeypatch.setattr(sweep, "compute_point", full_disk)
    spec = SweepSpec.from_strings(["readout.cutoff_hz=1,2"], run=TrackRunConfig(**TINY), skip_s=0.5)
    out = tmp_path / "full.zarr"
    with pytest.raises(SweepError, match=r"every point failed, so no store is written .*No space left"):
        run_sweep(spec, out, scheduler="synchronous", progress=False)
    assert not out.exists()


def _sigint_disposition(q):
    import signal

    q.put(signal.getsignal(signal.SIGINT) == signal.SIG_IGN)


def test_worker_processes_leave_ctrl_c_to_the_sweep():
    """A Ctrl-C reaches the terminal's whole process group: the cluster's workers, started inside
    _workers_ignore_sigint, ignore it (no traceback of theirs), and the sweep's own handler is back after."""
    import multiprocessing
    import signal

    from experiments.sweep import _workers_ignore_sigint

    ctx = multiprocessing.get_context("spawn")  # as dask's nanny starts its workers
    q = ctx.Queue()

    def ignored_in_child() -> bool:
        child = ctx.Process(target=_sigint_disposition, args=(q,))
        child.start()
        got = q.get(timeout=60)
        child.join(timeout=60)
        return got

    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as at a terminal, whatever runs the tests
    try:
        assert ignored_in_child() is False
        with _workers_ignore_sigint():
            assert ignored_in_child() is True
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)
