"""The velocity-replay ephys protocol: labelled recording of the velocity circuit, seeded."""
import numpy as np
import pytest
import xarray as xr

from experiments.cli import main
from experiments.replay_protocol import velocity_replay
from stimuli.scene import SceneConfig
from stimuli.track import TrackRunConfig, make_track_run


@pytest.fixture(scope="module")
def footage(tmp_path_factory):
    return make_track_run(tmp_path_factory.mktemp("replay") / "run",
                          TrackRunConfig(profile=None, start_s=5.0, duration_s=4.0, scale=0.25,
                                         scene=SceneConfig(seed=4)), progress=False)


def test_velocity_replay_records_the_circuit(footage, tmp_path, capsys):
    run = footage
    out = tmp_path / "rec.nc"
    assert main(["ephys", "velocity-replay", "--footage", str(run), "--trials", "3", "--seed", "7",
                 "--out", str(out), "--plot", str(tmp_path / "rec.png")]) == 0
    rec = xr.open_dataset(out)
    assert rec.readout_spikes.dims == ("trial", "spike_time", "unit") and rec.sizes["trial"] == 3
    assert list(rec.neuron.values) == ["plus", "minus"] and list(rec.unit_neuron.values) == ["plus", "minus"]
    assert {"azimuth_deg", "elevation_deg", "size_deg"} <= set(rec.coords)
    assert rec.attrs["lobula_version"] and "readout_neuron" in rec.attrs["config"]
    # Push–pull: never both neurons driven at once.
    rates = rec.readout_rate.values
    assert np.all(np.minimum(rates[..., 0], rates[..., 1]) == 0)
    # Same seed, same spikes; another seed, other spikes.
    again = velocity_replay(run, trials=3, seed=7)
    np.testing.assert_array_equal(again.readout_spikes.values, rec.readout_spikes.values)
    other = velocity_replay(run, trials=3, seed=8)
    assert not np.array_equal(other.readout_spikes.values, rec.readout_spikes.values)
    assert (tmp_path / "rec.png").stat().st_size > 10_000


# --------------------------------------------------------------------------- options, errors, NWB

import json  # noqa: E402

from experiments.ephys.command import APPLIES, run_protocol  # noqa: E402


def _cfg(ds):
    return json.loads(ds.attrs["config"])


def test_every_replay_option_changes_the_recording(footage):
    base = run_protocol("velocity-replay", {"footage": str(footage), "seed": 7})
    assert base.attrs["emd_tau_s"] == 0.01 and base.sizes["trial"] == 4
    checks = {
        "tau": (0.02, lambda ds: ds.attrs["emd_tau_s"] == 0.02 and _cfg(ds)["velocity"]["emd"]["emd"]["tau_s"] == 0.02),
        "dphi": (1.5, lambda ds: _cfg(ds)["velocity"]["emd"]["lattice"]["dphi_deg"] == 1.5),
        "field_size": (10.0, lambda ds: float(ds.size_deg[0]) == 10.0 and ds.sizes["field"] < base.sizes["field"]),
        "trials": (2, lambda ds: ds.sizes["trial"] == 2),
        "seed": (8, lambda ds: ds.attrs["seed"] == 8),
        "record": (["readout.v", "lc.r"], lambda ds: "lc_r" in ds and "readout_spikes" not in ds),
        "neuron_model": ("rate", lambda ds: ds.attrs["neuron_model"] == "rate" and "readout_spikes" not in ds),
    }
    documented = {k for k, ps in APPLIES.items() if "velocity-replay" in ps}
    # --eye fly and the eye circuit's --rotation, --haltere-gain: tests/test_eye_replay.py (refused here, below)
    assert documented == set(checks) | {"footage", "duration", "eye", "rotation", "haltere_gain"}
    for opt, (val, ok) in checks.items():
        extra = {"trials": 1} if opt == "neuron_model" else {}
        ds = run_protocol("velocity-replay", {"footage": str(footage), "seed": 7, **extra, opt: val})
        assert ok(ds), opt
        assert ds.attrs["config"] != base.attrs["config"] or ds.attrs["seed"] != base.attrs["seed"], opt
        if opt not in ("record",):  # the responses change (record only chooses what is stored)
            var = "readout_spikes" if opt == "seed" else "readout_rate"  # the seed draws other spikes
            a = ds[var].values if var in ds else None
            b = base[var].values
            assert a is None or a.shape != b.shape or not np.array_equal(a, b), opt
    # --duration renders the built-in run of that length (footage brings its own).
    with pytest.raises(ValueError, match="drop --duration"):
        run_protocol("velocity-replay", {"footage": str(footage), "duration": 3.0})


@pytest.mark.parametrize("opts,fix", [
    ({"record": ["lc.spikes[expansion]"]}, r"no subsets.*readout\.v"),
    ({"record": ["lc.spikes"]}, r"records readout\.v, readout\.rate.*belong to tf-tuning"),
    ({"record": ["readout.spikes"], "neuron_model": "rate", "trials": 1}, r"--neuron-model poisson"),
    ({"neuron_model": "lif"}, r"--neuron-model rate or poisson"),
    ({"neuron_model": "rate", "trials": 3}, r"use --trials 1, or --neuron-model poisson"),
    ({"tf": [3.0]}, r"--tf does not apply to velocity-replay"),
    ({"device": "cuda"}, r"--device does not apply to velocity-replay"),
    ({"rotation": "wide-field"}, r"--rotation set\(s\) the compound eye's circuit.*add --eye fly"),
    ({"haltere_gain": "1"}, r"--haltere-gain set\(s\) the compound eye's circuit.*add --eye fly"),
])
def test_replay_requests_that_cannot_work_fail_naming_the_fix(footage, opts, fix):
    with pytest.raises(ValueError, match=fix):
        run_protocol("velocity-replay", {"footage": str(footage), **opts})


def test_replay_spikes_are_at_1_ms_and_nwb_round_trips(footage, tmp_path):
    from nwbinspector import Importance, inspect_nwbfile

    from experiments.nwb import epoch_layout, read_nwb_series, read_nwb_spike_counts, write_nwb
    from experiments.store import write_netcdf

    ds = run_protocol("velocity-replay", {"footage": str(footage), "trials": 3, "seed": 2})
    frame = float(np.median(np.diff(ds.time.values)))
    assert ds.readout_spikes.attrs["dt_s"] == pytest.approx(frame / round(frame / 1e-3))
    assert ds.sizes["spike_time"] == ds.sizes["time"] * round(frame / 1e-3)
    # Counts per 1 ms step, summed per frame, are the frame-rate Poisson counts' statistics: mean rate ≈ rate.
    rate = ds.readout_rate.sel(neuron="plus").values.mean()
    spk = ds.readout_spikes.sel(unit="plus 0").values.sum(1).mean() / (ds.sizes["time"] * frame)
    assert spk == pytest.approx(rate, rel=0.15)
    for name in ds.variables:
        assert "long_name" in ds[name].attrs, name
    nc = write_netcdf(ds, tmp_path / "r.nc")
    back = xr.open_dataset(nc, engine="h5netcdf").load()
    nwb = write_nwb(back, tmp_path / "r.nwb")
    assert list(inspect_nwbfile(nwbfile_path=str(nwb), importance_threshold=Importance.BEST_PRACTICE_VIOLATION)) == []
    lay = epoch_layout(back)
    assert lay["C"] == 1 and lay["K"] == 3
    counts = read_nwb_spike_counts(nwb, back, "readout_spikes")
    np.testing.assert_array_equal(counts[0], back.readout_spikes.transpose("trial", "spike_time", "unit").values)
    data, ts, unit = read_nwb_series(nwb, "readout_rate")
    np.testing.assert_array_equal(data.reshape(3, back.sizes["time"], 2), back.readout_rate.values)
    assert unit == "Hz"
    v, _, _ = read_nwb_series(nwb, "arithmetic_v")
    np.testing.assert_array_equal(v, back.arithmetic_v.values)


def test_replay_trial_k_and_spike_steps_are_what_is_stated(footage, tmp_path):
    from pynwb import NWBHDF5IO

    from experiments.nwb import epoch_layout, write_nwb
    one = run_protocol("velocity-replay", {"footage": str(footage), "trials": 1, "seed": 3})
    three = run_protocol("velocity-replay", {"footage": str(footage), "trials": 3, "seed": 3})
    # Trial 0 is the same whatever the number of trials; the trials differ from one another.
    np.testing.assert_array_equal(one.readout_spikes.isel(trial=0).values, three.readout_spikes.isel(trial=0).values)
    assert not np.array_equal(three.readout_spikes.isel(trial=0).values, three.readout_spikes.isel(trial=1).values)
    # At most one spike per unit per step (Bernoulli, p = 1 − exp(−rate·step)).
    assert int(three.readout_spikes.max()) == 1 and int(three.readout_spikes.sum()) > 100
    # The step is the one stated: the spike_time coordinate's spacing, dt_s, and its long_name in ms.
    dt = float(three.readout_spikes.attrs["dt_s"])
    np.testing.assert_allclose(np.diff(three.spike_time.values), dt, rtol=1e-9)
    sub = round(float(np.median(np.diff(three.time.values))) / dt)
    assert f"{dt * 1e3:.5g} ms: the frame interval / {sub}" in three.spike_time.attrs["long_name"]
    # A spike's time is its step's start in the NetCDF coordinate and in the NWB Units table alike.
    path = write_nwb(three, tmp_path / "r.nwb")
    lay = epoch_layout(three)
    with NWBHDF5IO(str(path), "r") as io:
        st = np.asarray(io.read().units.to_dataframe().spike_times.values[0])
    s = three.readout_spikes.isel(unit=0).transpose("trial", "spike_time").values
    k, i = np.nonzero(s)
    want = np.sort(lay["starts"][0, k] + three.spike_time.values[i] - lay["t0"])
    np.testing.assert_allclose(st, want, atol=1e-9)


@pytest.mark.parametrize("model", ["lif", "poisson"])
def test_output_neurons_trial_k_is_the_same_whatever_the_number_of_trials(model):
    from dataclasses import replace

    from experiments.eye_velocity import EyeVelocityConfig
    from experiments.replay_protocol import per_trial
    from lobula.readout_neuron import spiking_output
    t = np.arange(0, 2.0, 0.02)
    v = 0.3 + 0.2 * np.sin(2 * np.pi * 0.5 * t)
    ncfg = replace(EyeVelocityConfig().neuron, spiking=True, seed=5, spike_model=model)
    one = per_trial(lambda c: spiking_output(t, v, np.zeros_like(t), c), 1, ncfg)
    three = per_trial(lambda c: spiking_output(t, v, np.zeros_like(t), c), 3, ncfg)
    np.testing.assert_array_equal(one["spikes_units"][0], three["spikes_units"][0])
    assert not np.array_equal(three["spikes_units"][0], three["spikes_units"][1])
    assert three["spikes_units"].sum() > 0


def test_eye_footage_without_eye_fly_is_refused_naming_the_fix(tmp_path, capsys):
    from stimuli.eye import make_eye_run

    eye = make_eye_run(tmp_path / "eye", TrackRunConfig(profile=None, duration_s=0.2, scale=0.25,
                                                        scene=SceneConfig(seed=4)), progress=False, cast_every=5)
    out = tmp_path / "rec.nc"
    assert main(["ephys", "velocity-replay", "--footage", str(eye), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert f"--footage {eye}: compound-eye footage" in err and err.endswith("add --eye fly to replay it through the "
                                                                            "compound eye's circuit")
    assert not out.exists()
