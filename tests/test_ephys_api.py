"""experiments.ephys.run / to_nwb: the Python API is the command line's run (same numbers), refuses what the
command refuses with the fix named, and writes its outputs; the pre-stimulus baseline; the raster/ISI/PSTH
helpers; the published LGMD data and its agreement score.

Tiny rig (Δφ = 4°, 20° fields), short stimuli: a few seconds each.
"""
import json

import numpy as np
import pytest
import xarray as xr

pytest.importorskip("torch")

from experiments.ephys import api  # noqa: E402
from experiments.ephys.command import PROTOCOLS, run_protocol  # noqa: E402

TINY = dict(dphi=4.0, field_size=20.0)


def test_run_is_the_command_lines_run():
    ds = api.run("tf-tuning", **TINY, temporal_frequencies_hz=[2.0, 6.0], contrasts=0.5, duration_s=0.3,
                 settle=0.05, neuron_model="poisson", trials=2, seed=3, record=["lc.rate", "lc.spikes"])
    ref = run_protocol("tf-tuning", dict(TINY, tf=[2.0, 6.0], contrast=[0.5], duration=0.3, settle=0.05,
                                         neuron_model="poisson", trials=2, seed=3, record=["lc.rate", "lc.spikes"]))
    np.testing.assert_array_equal(ds.lc_spikes.values, ref.lc_spikes.values)
    np.testing.assert_array_equal(ds.lc_rate_tuning.values, ref.lc_rate_tuning.values)
    assert ds.lc_spikes.values.sum() > 0
    assert ds.attrs["command_line"] == ("lobula ephys tf-tuning --dphi 4.0 --field-size 20.0 --tf 2.0 6.0 "
                                        "--contrast 0.5 --duration 0.3 --settle 0.05 --neuron-model poisson "
                                        "--trials 2 --seed 3 --record lc.rate lc.spikes")


def test_every_protocol_of_the_command_is_dispatched():
    for p in PROTOCOLS:  # whatever the command lists, run builds its command line (no table of its own)
        assert api.command_argv(p) == ["ephys", p]
    assert api.command_argv("looming", "fly", l_over_v_s=[0.02, 0.04]) == [
        "ephys", "looming", "--eye", "fly", "--l-over-v", "0.02", "0.04"]


@pytest.mark.parametrize("call, match", [
    (dict(protocol="tf-tuning", temporal_frequency_hz=[1.0]), "unknown option temporal_frequency_hz=; did you mean "
                                                              "temporal_frequencies_hz"),
    (dict(protocol="rf-map", trials=3), r"trials= does not apply to rf-map; it applies to tf-tuning, looming"),
    (dict(protocol="edges", l_over_v=[0.02]), "l_over_v= does not apply to edges; it applies to looming"),
    (dict(protocol="looming", l_over_v=[-0.02]), "l-over-v"),
    (dict(protocol="looming", neuron_model="hodgkin"), "invalid choice: 'hodgkin'"),
    (dict(protocol="tf-tuning", tf=[600.0]), "Nyquist"),
    (dict(protocol="loomin"), "did you mean 'looming'"),
    (dict(protocol="edges", circuit="fly"), "circuit='fly' does not apply to edges"),
    (dict(protocol="edges", circuit="compound"), "circuit must be 'pinhole'"),
    (dict(protocol="looming", circuit="fly", baseline_s=0.1), "--baseline: the compound eye"),
    (dict(protocol="tf-tuning", neuron_model="rate", trials=3), "deterministic"),
])
def test_run_refuses_with_the_fix_named(call, match):
    with pytest.raises(ValueError, match=match):
        api.run(**call)


def test_options_list_each_protocols_own(tmp_path):
    opts = api.options("looming")
    assert {"l_over_v", "baseline", "trials", "record"} <= set(opts) and "tf" not in opts
    assert "(default: 0.3)" in opts["baseline"]
    assert "speed" in api.options("edges") and "trials" not in api.options("rf-map")


def test_outputs_and_to_nwb(tmp_path):
    from tests.test_nwb import critical_findings

    ds = api.run("looming", **TINY, l_over_v=[0.02, 0.04], duration=0.3, baseline_s=0.1,
                 out=[tmp_path / "loom.nc", tmp_path / "loom.nwb"])
    back = xr.open_dataset(tmp_path / "loom.nc", engine="h5netcdf").load()
    np.testing.assert_array_equal(back.lc_rate.values, ds.lc_rate.values)
    assert back.attrs["command_line"].startswith("lobula ephys looming --dphi 4.0")
    assert critical_findings(tmp_path / "loom.nwb") == []
    path = api.to_nwb(ds, tmp_path / "again.nwb", experimenter="Borst, Alexander")
    from pynwb import NWBHDF5IO
    with NWBHDF5IO(str(path), "r") as io:
        f = io.read()
        assert list(f.experimenter) == ["Borst, Alexander"]
        # the baseline: each epoch's stimulus_time_zero lies baseline + collision time after its start
        tr = f.trials.to_dataframe()
        np.testing.assert_allclose(tr.stimulus_time_zero - tr.start_time, 0.1 + 0.8 * 0.3, atol=1e-9)
    with pytest.raises(ValueError, match=r"\.nc \(NetCDF\) or \.nwb"):
        api.run("looming", **TINY, l_over_v=[0.04], duration=0.2, out=tmp_path / "loom.txt")


def test_baseline_precedes_onset_and_leaves_the_response_unchanged():
    """The eye rests at the mean luminance during the baseline, so a deterministic rig's response after onset
    is the one without a baseline, shifted; stored times stay relative to onset (looming: collision)."""
    kw = dict(TINY, tf=[4.0], duration=0.3, settle=0.05, record=["lc.rate", "emd.response[0:5]"])
    with_b = run_protocol("tf-tuning", dict(kw, baseline=0.15))
    without = run_protocol("tf-tuning", dict(kw, baseline=0.0))
    assert with_b.sizes["time"] == without.sizes["time"] + 150 and float(with_b.time[0]) == pytest.approx(-0.15)
    after = with_b.sel(time=slice(-1e-9, None))
    np.testing.assert_allclose(after.lc_rate.values, without.lc_rate.values, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(with_b.lc_rate_tuning.values, without.lc_rate_tuning.values, rtol=1e-5, atol=1e-6)
    pre = with_b.emd_response.sel(time=slice(None, -1e-9)).values
    assert np.abs(pre).max() < 1e-6 < np.abs(without.emd_response.values).max()  # nothing moves before onset
    lo = run_protocol("looming", dict(TINY, l_over_v=[0.04], duration=0.3, baseline=0.1))
    assert float(lo.time[0]) == pytest.approx(-(0.1 + 0.8 * 0.3)) and lo.attrs["baseline_s"] == pytest.approx(0.1)
    assert float(lo.angular_size_deg.sel(time=slice(None, -0.24 - 1e-9)).max()) == 0.0   # no disc yet
    assert float(lo.angular_size_deg.sel(time=-0.24, method="nearest").min()) > 0.0       # the disc at onset


def test_raster_shows_a_few_seconds_and_turns_into_an_isi_histogram_when_solid(monkeypatch):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from experiments.ephys import figures

    ds = run_protocol("tf-tuning", dict(TINY, tf=[4.0], duration=4.0, settle=0.05, neuron_model="poisson",
                                        trials=3, record=["lc.spikes[0]"]))
    fig, (a_r, a_p) = plt.subplots(1, 2)
    assert figures._raster_psth(fig, a_r, a_p, ds, 0, "k", "t (s)", temporal_frequency_hz=4.0, contrast=0.5) == "raster"
    lo, hi = a_r.get_xlim()
    assert lo == pytest.approx(-0.3) and hi == pytest.approx(-0.3 + figures.RASTER_MAX_S)
    labels = [t.get_text() for t in a_p.get_legend().get_texts()]
    assert any(t.startswith("baseline mean") for t in labels) and "± SEM (3 trials)" in labels
    monkeypatch.setattr(figures, "RASTER_MAX_SPIKES", 1)
    fig, (a_r, a_p) = plt.subplots(1, 2)
    assert figures._raster_psth(fig, a_r, a_p, ds, 0, "k", "t (s)", temporal_frequency_hz=4.0, contrast=0.5) == "isi"
    assert a_r.get_xlabel() == "inter-spike interval (ms)"
    # the histogram's mean counts add up to the intervals per trial after onset
    ts, tr = figures.raster(ds, 0, temporal_frequency_hz=4.0, contrast=0.5)
    n = np.mean([max(0, int(((tr == k) & (ts >= 0)).sum()) - 1) for k in range(3)])
    drawn = a_r.lines[0].get_ydata().sum()
    assert drawn == pytest.approx(n, rel=0.02)  # all but the top 1 % of intervals are binned
    plt.close("all")


def test_published_lgmd_line_and_agreement():
    from experiments.ephys.published import DATASETS, LGMD_PEAK_TIME, lgmd_peak_time_s, looming_agreement

    # Gabbiani et al. 1999 Fig. 5: the peak comes 27 ms after the square subtends 24°.
    lv = np.array([0.01, 0.03, 0.05])
    t = lgmd_peak_time_s(lv)
    size_at_threshold = 2 * np.degrees(np.arctan(lv / -(t - 0.027)))
    np.testing.assert_allclose(size_at_threshold, 24.0)
    a = looming_agreement(lv, t)
    assert a["slope_ratio"] == pytest.approx(1.0) and a["model_theta_threshold_deg"] == pytest.approx(24.0)
    assert a["model_delta_s"] == pytest.approx(0.027)
    half = looming_agreement(lv, 0.5 * (t - 0.027) + 0.027)
    assert half["slope_ratio"] == pytest.approx(0.5)
    assert np.isnan(looming_agreement(lv, [np.nan, np.nan, -0.1])["slope_ratio"])
    for d in DATASETS.values():
        assert {"citation", "doi", "source", "measured", "values", "digitised"} <= set(d)
    assert LGMD_PEAK_TIME["doi"] == "10.1523/JNEUROSCI.19-03-01122.1999"


def test_looming_figure_overlays_the_lgmd_and_writes_the_agreement(tmp_path):
    from experiments.ephys.command import summary
    from experiments.ephys.figures import plot_recording
    from experiments.ephys.published import looming_agreement

    ds = api.run("looming", **TINY, l_over_v=[0.01, 0.02, 0.04], duration=0.6, baseline_s=0.1)
    paths = plot_recording(ds, tmp_path / "loom.png")
    assert [p.suffix for p in paths] == [".png", ".pdf"]
    side = json.loads((tmp_path / "loom.json").read_text())
    ex = ds.lc_rate_time_of_peak_s.sel(motion="approach").isel(
        neuron=np.flatnonzero(ds.neuron_type.values == "expansion"))
    want = looming_agreement(ds.l_over_v_s.values, ex.mean("neuron").values)
    assert side["published"] == "lgmd_peak_time"
    assert side["agreement"]["slope_ratio"] == pytest.approx(want["slope_ratio"])
    assert np.isfinite(want["slope_ratio"]) and want["model_slope"] < 0  # earlier peaks for slower approaches
    line = next(x for x in summary(ds) if x.startswith("lc_rate_time_of_peak_s: slope"))
    assert f"ratio {want['slope_ratio']:.3g}" in line
