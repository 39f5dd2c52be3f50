"""Every documented `lobula ephys` option does what it says, in every protocol it applies to, or fails
loudly with a message that names the fix; recordings are self-describing (CF-1.10) in every protocol.

Tiny rig (Δφ = 4°, 20° fields: 4 LC fields × 5 unit types), 0.3 s stimuli: a few seconds per protocol.
(velocity-replay's options are tested in test_replay_protocol.py, on its footage.)
"""
import json

import numpy as np
import pytest
import xarray as xr

from experiments.cli import main as cli_main
from experiments.ephys.command import APPLIES, parse_command, run_protocol, summary

TINY = dict(dphi=4.0, field_size=20.0)
BASE = {"tf-tuning": dict(TINY, tf=[4.0], duration=0.3, settle=0.1),
        "looming": dict(TINY, l_over_v=[0.04], duration=0.3),
        "rf-map": dict(TINY, fields=[0], directions=3, spot_speed=400.0)}

# option → (value, what the stored file must show, whether the responses must change)
VARIANTS = {
    "tf-tuning": {
        "tau": (0.07, lambda ds: ds.attrs["emd_tau_s"] == 0.07, True),
        "dphi": (5.0, lambda ds: json.loads(ds.attrs["config"])["ephys"]["lattice"]["dphi_deg"] == 5.0, True),
        "field_size": (24.0, lambda ds: float(ds.size_deg[0]) == 24.0, True),
        "duration": (0.4, lambda ds: ds.sizes["time"] == 400 + 300, True),  # after the 0.3 s baseline
        "baseline": (0.1, lambda ds: _par(ds)["baseline_s"] == 0.1 and float(ds.time[0]) == pytest.approx(-0.1),
                     False),  # the steady state after onset does not depend on the rest before it
        "contrast": ([0.2, 0.8], lambda ds: list(ds.contrast.values) == [0.2, 0.8], True),
        "tf": ([2.0, 8.0], lambda ds: list(ds.temporal_frequency_hz.values) == [2.0, 8.0], True),
        "wavelength": (30.0, lambda ds: _par(ds)["wavelength_deg"] == 30.0, True),
        "stimulus": ("grating", lambda ds: _par(ds)["stimulus"] == "grating", True),
        "settle": (0.2, lambda ds: _par(ds)["settle_s"] == 0.2, True),
        "neuron_model": ("lif", lambda ds: ds.attrs["neuron_model"] == "lif" and "lc_v" in ds, True),
        "record": (["lc.r"], lambda ds: "lc_r" in ds and "lc_rate" not in ds, True),
        # the drum grating's direction (rings have none): compared with a grating at 0°
        "direction": (90.0, lambda ds: _par(ds)["direction_deg"] == 90.0, True, {"stimulus": "grating"}),
        # the compound eye's velocity circuit instead of the pinhole lattice (tests/test_eye_ephys.py)
        "eye": ("fly", lambda ds: ds.attrs["eye"] == "fly" and "lc_input" in ds, True),
    },
    "looming": {
        "tau": (0.07, lambda ds: ds.attrs["emd_tau_s"] == 0.07, True),
        "dphi": (5.0, lambda ds: json.loads(ds.attrs["config"])["ephys"]["lattice"]["dphi_deg"] == 5.0, True),
        "field_size": (24.0, lambda ds: float(ds.size_deg[0]) == 24.0, True),
        "duration": (0.4, lambda ds: ds.sizes["time"] == 400 + 300, True),  # after the 0.3 s baseline
        "baseline": (0.1, lambda ds: _par(ds)["baseline_s"] == 0.1 and float(ds.time[0]) == pytest.approx(-0.1 - 0.24),
                     False),  # nor the peaks, after the disc appears
        "contrast": ([0.5], lambda ds: _par(ds)["contrast"] == 0.5, True),
        "l_over_v": ([0.02, 0.08], lambda ds: list(ds.l_over_v_s.values) == [0.02, 0.08], True),
        "max_size": (20.0, lambda ds: float(ds.angular_size_deg.max()) == pytest.approx(20.0), True),
        "eye": ("fly", lambda ds: ds.attrs["eye"] == "fly" and "lc_r" in ds, True),
        "collision_time": (0.2, lambda ds: ds.attrs["t_collision_s"] == 0.2 and float(ds.time[0]) == pytest.approx(-0.2 - 0.3), True),
        "neuron_model": ("lif", lambda ds: ds.attrs["neuron_model"] == "lif" and "lc_spikes" in ds, True),
        "record": (["lc.r2"], lambda ds: "lc_r2" in ds and "lc_rate" not in ds, True),
    },
    "rf-map": {
        "tau": (0.07, lambda ds: ds.attrs["emd_tau_s"] == 0.07, True),
        "dphi": (5.0, lambda ds: ds.attrs["dphi_deg"] == 5.0, True),
        "field_size": (24.0, lambda ds: float(ds.field_size_deg[0]) == 24.0, True),
        "contrast": ([0.5], lambda ds: _par(ds)["contrast"] == 0.5, True),
        "fields": ([1], lambda ds: ds.field.values.tolist() == [1], True),
        "directions": (4, lambda ds: ds.sizes["direction_deg"] == 4, True),
        "spacing": (6.0, lambda ds: _par(ds)["spacing_deg"] == 6.0, True),
        "extent": (20.0, lambda ds: _par(ds)["extent_deg"] == 20.0, True),
        "spot_size": (6.0, lambda ds: _par(ds)["spot_size_deg"] == 6.0, True),
        "spot_path": (12.0, lambda ds: _par(ds)["path_deg"] == 12.0, True),
        "spot_speed": (300.0, lambda ds: _par(ds)["speed_deg_s"] == 300.0, True),
        "record": (["lc.r"], lambda ds: ds.rf_response.attrs["monitor"] == "lc.r", True),
        "eye": ("fly", lambda ds: ds.attrs["eye"] == "fly" and "rf_weight" in ds, True,
                {"spacing": 12.0, "extent": 24.0}),
    },
}
# Options whose effect needs a spiking model (checked separately below), and the device.
SHARED = {"tf-tuning": {"trials", "seed", "device"}, "looming": {"trials", "seed", "device"}, "rf-map": {"device"}}


def _par(ds):
    return json.loads(ds.attrs["parameters"])


def _response(ds) -> np.ndarray:
    for v in ("lc_rate_tuning", "lc_rate_peak", "rf_response", "lc_v_peak", "lc_spikes_peak"):
        if v in ds:
            return np.asarray(ds[v].values, dtype=float)
    return np.asarray(ds[[v for v in ds.data_vars][0]].values, dtype=float)


@pytest.fixture(scope="module")
def baselines():
    return {p: run_protocol(p, dict(o)) for p, o in BASE.items()}


@pytest.mark.parametrize("protocol", list(BASE))
def test_every_documented_option_is_tested(protocol):
    documented = {k for k, ps in APPLIES.items() if protocol in ps}
    assert documented == set(VARIANTS[protocol]) | SHARED[protocol]


@pytest.mark.parametrize("protocol,option", [(p, o) for p in VARIANTS for o in VARIANTS[p]])
def test_option_changes_the_stored_configuration_and_responses(protocol, option, baselines):
    value, stored, changes, *extra = VARIANTS[protocol][option]
    base = baselines[protocol]
    if extra:  # an option that needs another one: its own baseline
        base = run_protocol(protocol, {**BASE[protocol], **extra[0]})
    extra = extra[0] if extra else {}
    ds = run_protocol(protocol, {**BASE[protocol], **extra, option: value})

    assert stored(ds), (option, value)
    assert (ds.attrs["config"], ds.attrs["parameters"]) != (base.attrs["config"], base.attrs["parameters"])
    if changes:
        a, b = _response(ds), _response(base)
        assert a.shape != b.shape or not np.allclose(a, b, equal_nan=True), option


@pytest.mark.parametrize("protocol", ["tf-tuning", "looming"])
def test_trials_and_seed_need_and_drive_a_spiking_model(protocol):
    opts = {**BASE[protocol], "neuron_model": "poisson"}
    a = run_protocol(protocol, {**opts, "trials": 3, "seed": 1})
    assert a.sizes["trial"] == 3 and a.attrs["trials"] == 3 and a.attrs["seed"] == 1
    again = run_protocol(protocol, {**opts, "trials": 3, "seed": 1})
    other = run_protocol(protocol, {**opts, "trials": 3, "seed": 2})
    np.testing.assert_array_equal(again.lc_spikes.values, a.lc_spikes.values)
    assert not np.array_equal(other.lc_spikes.values, a.lc_spikes.values)
    # The deterministic rate model stores one trial and refuses more, naming the fix.
    rate = run_protocol(protocol, dict(BASE[protocol]))
    assert rate.sizes["trial"] == 1 and rate.attrs["trials"] == 1 and "deterministic" in rate.attrs["trials_note"]
    with pytest.raises(ValueError, match="--trials 1, or --neuron-model poisson or lif"):
        run_protocol(protocol, {**BASE[protocol], "trials": 4})


def test_rf_map_refuses_neuron_options_and_checks_the_device():
    for opt, val in (("trials", 2), ("seed", 3), ("neuron_model", "poisson")):
        with pytest.raises(ValueError, match="does not apply to rf-map"):
            run_protocol("rf-map", {**BASE["rf-map"], opt: val})
    ds = run_protocol("rf-map", {**BASE["rf-map"], "device": "cpu"})
    assert json.loads(ds.attrs["config"])["ephys"]["device"] == "cpu"
    for bad in ("nonsense", "mps"):
        with pytest.raises(ValueError, match="--device"):
            run_protocol("rf-map", {**BASE["rf-map"], "device": bad})


@pytest.mark.parametrize("protocol,opts,fix", [
    ("looming", {"record": ["lc.spikes[expansion]"]}, r"--neuron-model poisson or lif.*lc\.rate.*expansion"),
    ("tf-tuning", {"record": ["lc.volts"]}, r"POPULATION\.VARIABLE\[subset\].*lc\.rate.*\[i:j\]"),
    ("tf-tuning", {"record": ["lc.v"]}, r"--neuron-model lif"),
    ("looming", {"record": ["lc.r[expansion]"]}, r"index subset"),
    ("looming", {"tf": [3.0]}, r"--tf does not apply to looming; it applies to tf-tuning"),
    ("tf-tuning", {"fields": [1]}, r"--fields does not apply to tf-tuning; it applies to rf-map"),
    ("rf-map", {"duration": 1.0}, r"--duration does not apply to rf-map"),
    ("rf-map", {"fields": [99]}, r"indices in \[0, 2\) \(this rig has 2 LC fields\)"),
    ("rf-map", {"directions": 2}, r"at least 3 spot directions"),
    ("rf-map", {"contrast": [0.2, 0.4]}, r"one --contrast value"),
    ("looming", {"collision_time": 2.0}, r"--duration or an earlier --collision-time"),
    ("looming", {"footage": "x"}, r"applies to velocity-replay"),
    ("tf-tuning", {"settle": 0.5}, r"longer --duration or a shorter --settle"),
    ("tf-tuning", {"direction": 30.0}, r"--stimulus grating"),
])
def test_impossible_requests_fail_naming_the_fix(protocol, opts, fix):
    with pytest.raises(ValueError, match=fix):
        run_protocol(protocol, {**BASE[protocol], **opts})


def test_recordings_are_self_describing_with_the_same_attributes(baselines, capsys):
    keys = None
    for p, ds in baselines.items():
        assert ds.attrs["Conventions"] == "CF-1.10" and ds.attrs["protocol"] == p
        for k in ("command_line", "created", "git_commit", "lobula_version", "config", "parameters", "history",
                  "neuron_model", "dt_s", "trials", "seed", "emd_tau_s"):
            assert k in ds.attrs, (p, k)
        for name in ds.variables:
            da = ds[name]
            assert "long_name" in da.attrs, (p, name)
            if da.dtype.kind in "fiu":
                assert "units" in da.attrs, (p, name)
        keys = set(ds.attrs) if keys is None else keys
        common = {"Conventions", "title", "source", "history", "config", "parameters", "protocol", "command_line",
                  "created", "git_commit", "lobula_version", "trials", "trials_requested", "seed", "neuron_model",
                  "dt_s", "emd_tau_s", "neuron_parameters"}
        assert common <= set(ds.attrs), (p, common - set(ds.attrs))
    # Looming: one time convention (relative to collision) for the coordinate and the peak times.
    lo = baselines["looming"]
    assert "collision" in lo.time.attrs["long_name"] and float(lo.time[0]) == pytest.approx(-0.8 * 0.3 - 0.3)
    tp = lo.lc_rate_time_of_peak_s
    assert np.all((tp.values >= lo.time.values[0]) & (tp.values <= lo.time.values[-1]))
    # Printed summaries: the contrast's value (not the dim's size) and selections named.
    text = "\n".join(summary(baselines["tf-tuning"]))
    assert "contrast values: 0.5" in text and "expansion units" in text and "all 10 recorded units" in text


def test_command_line_help_shows_defaults_and_writes_nc_nwb_and_figures(tmp_path, capsys):
    with pytest.raises(SystemExit):
        parse_command(["ephys", "--help"])
    helptext = capsys.readouterr().out.replace("\n", " ")
    import re
    helptext = re.sub(r"\s+", " ", helptext)
    for default in ("16 log-spaced from 0.5 to 32", "tf-tuning: 0.5", "default: 20", "0.01 0.02 0.04 0.08",
                    "default: 60", "0.8 × duration", "default: 4 for spiking", "default: 0.035", "default: Δφ",
                    "1.6 × field size"):
        assert default in helptext, default
    out, nwb, png = tmp_path / "loom.nc", tmp_path / "loom.nwb", tmp_path / "loom.png"
    assert cli_main(["ephys", "looming", "--l-over-v", "0.04", "--duration", "0.3", "--dphi", "4", "--field-size",
                     "20", "--out", str(out), str(nwb), "--plot", str(png)]) == 0
    assert out.exists() and nwb.exists() and png.exists() and png.with_suffix(".pdf").exists()
    with xr.open_dataset(out, engine="h5netcdf") as ds:
        assert ds.attrs["command_line"] and ds.attrs["protocol"] == "looming"
    assert cli_main(["ephys", "looming", "--out", str(tmp_path / "x.csv")]) == 2
    assert "use a .nc" in capsys.readouterr().err


@pytest.mark.parametrize("model", ["poisson", "lif"])
def test_trial_k_is_the_same_whatever_the_number_of_trials(model):
    opts = {**BASE["looming"], "neuron_model": model, "seed": 4}
    one = run_protocol("looming", {**opts, "trials": 1})
    three = run_protocol("looming", {**opts, "trials": 3})
    two = run_protocol("looming", {**opts, "trials": 2})
    np.testing.assert_array_equal(one.lc_spikes.isel(trial=0).values, three.lc_spikes.isel(trial=0).values)
    np.testing.assert_array_equal(two.lc_spikes.values, three.lc_spikes.isel(trial=[0, 1]).values)
    assert one.lc_spikes.sum() > 0
    # ... and the trials differ from one another.
    assert not np.array_equal(three.lc_spikes.isel(trial=0).values, three.lc_spikes.isel(trial=1).values)


def test_temporal_frequencies_above_the_nyquist_limit_are_refused(capsys):
    with pytest.raises(SystemExit):
        parse_command(["ephys", "tf-tuning", "--tf", "2", "600", "--out", "x.nc"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "500 Hz Nyquist limit" in err and "600" in err
    assert parse_command(["ephys", "tf-tuning", "--tf", "499", "--out", "x.nc"]).tf == [499.0]
    from experiments.ephys import EphysConfig, tf_tuning
    with pytest.raises(ValueError, match=r"Nyquist limit 500 Hz .*\[700\.0\]"):
        tf_tuning(EphysConfig(trials=1), temporal_frequencies_hz=[4.0, 700.0], duration_s=0.2, settle_s=0.0)


def test_lif_summary_gives_the_spike_rate_peak_not_the_membrane_potential():
    ds = run_protocol("tf-tuning", {**BASE["tf-tuning"], "tf": [2.0, 8.0], "neuron_model": "lif", "trials": 1})
    lines = summary(ds)
    assert "lc_v_peak_temporal_frequency_hz" in ds              # stored, but no tuning peak to report
    assert not any(line.startswith("lc_v:") for line in lines), lines
    assert any(line.startswith("lc_spikes: peak temporal frequency") for line in lines), lines


def test_trials_beyond_the_bound_are_refused_at_parse_time(capsys):
    from experiments.ephys.command import MAX_TRIALS

    assert cli_main(["ephys", "looming", "--trials", "1000000000", "--out", "x.nc"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert f"--trials: must be a whole number in [1, {MAX_TRIALS}], got '1000000000'" in err
    assert parse_command(["ephys", "looming", "--trials", str(MAX_TRIALS), "--out", "x.nc"]).trials == MAX_TRIALS
    with pytest.raises(SystemExit):
        parse_command(["ephys", "--help"])
    assert f"1 to {MAX_TRIALS}" in " ".join(capsys.readouterr().out.split())
