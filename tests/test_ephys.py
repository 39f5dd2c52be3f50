"""Virtual electrophysiology against known answers (experiments.ephys).

- tf-tuning: EMDs and LC units peak at f = 1/(2πτ) (within one step of the sweep) for two τ.
- rf-map: each probed LC field's designed centre within one ommatidial spacing, its size within 20 %.
- looming: expansion units respond more to an approaching disc than to the same disc receding.
- recordings reopen with xarray carrying configuration and version; the same seed gives
  identical arrays; the command line writes both files.
Small eye (Δφ = 2°, ~550 ommatidia), 1 ms steps; the file takes ~1–2 min on two shared cores.
"""
import argparse
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import xarray as xr

from experiments.ephys import (EphysConfig, Rig, add_parser, looming, parse_monitor, psth, raster, rf_map,
                               steady_state_mean, tf_tuning)
from experiments.store import write_netcdf


def _with_fields(cfg: EphysConfig, **fields) -> EphysConfig:
    pop = cfg.circuit.population
    return replace(cfg, circuit=replace(cfg.circuit, population=replace(pop, fields=replace(pop.fields, **fields))))


def _with_neurons(cfg: EphysConfig, **kw) -> EphysConfig:
    pop = cfg.circuit.population
    return replace(cfg, circuit=replace(cfg.circuit, population=replace(pop, neurons=replace(pop.neurons, **kw))))


@pytest.mark.parametrize("tau", [0.035, 0.07])
def test_tf_tuning_peaks_at_one_over_two_pi_tau(tau):
    tf = np.geomspace(0.5, 32.0, 16)                       # steps of 32 %
    cfg = EphysConfig(trials=1)
    ds = tf_tuning(cfg, temporal_frequencies_hz=tf, tau_s=tau, duration_s=1.5, settle_s=0.5,
                   record=None)
    f0 = 1 / (2 * math.pi * tau)
    assert ds.attrs["optimum_hz"] == pytest.approx(f0)
    k0 = np.argmin(np.abs(np.log(tf / f0)))

    def within_one_step(peaks):
        k = np.searchsorted(tf, np.asarray(peaks) - 1e-9)
        return np.abs(k - k0) <= 1

    # EMDs: every probe pair (one per field, along the rings' motion).
    assert ds.sizes["pair"] >= 5
    assert np.all(within_one_step(ds.emd_response_peak_temporal_frequency_hz.values[0]))
    # ... and the whole curve is the exact discrete prediction (× photoreceptor transfer).
    curve = ds.emd_response_tuning.isel(contrast=0).mean("pair").values
    np.testing.assert_allclose(curve / curve.max(), ds.emd_prediction.values, atol=0.03)
    # LC expansion units (rate neurons): their trial-averaged steady-state rates.
    exp = ds.neuron_type.values == "expansion"
    peaks = ds.lc_rate_peak_temporal_frequency_hz.values[0][exp]
    assert np.all(within_one_step(peaks)), peaks


def test_rf_map_recovers_designed_centres_and_sizes():
    centres = ((12.0, 0.0), (-10.0, 6.0))
    cfg = _with_fields(EphysConfig(trials=1), size_deg=10.0, centres_deg=centres, shape="gaussian")
    ds = rf_map(cfg, extent_deg=13.0)
    dphi = ds.attrs["dphi_deg"]
    for f, (az, el) in enumerate(centres):
        err = math.hypot(float(ds.rf_centre_azimuth_deg[f]) - az, float(ds.rf_centre_elevation_deg[f]) - el)
        assert err < dphi, (f, err)
        assert float(ds.rf_size_deg[f]) == pytest.approx(10.0, rel=0.2)
    # The local preferred directions point away from the epipole (expansion), where the map is strong.
    s = ds.rf_sensitivity.isel(field=0)
    strong = (s > 0.5 * s.max()).values
    pref = np.radians(ds.rf_preferred_direction_deg.isel(field=0).values[strong])
    az = ds.location_azimuth_deg.values[strong]
    el = ds.location_elevation_deg.values[strong]
    outward = np.cos(pref) * az + np.sin(pref) * el
    assert np.all(outward > 0)
    # Push–pull units inherit their field's estimate.
    assert np.isfinite(ds.neuron_rf_size_deg.sel(neuron=ds.neuron_type == "expansion")).all()


def test_looming_drives_expansion_units_more_than_receding():
    ds = looming(EphysConfig(trials=2), l_over_v_s=(0.02, 0.05), duration_s=0.8)
    peak = ds.lc_rate_peak.sel(neuron=ds.neuron_type == "expansion")
    app = peak.sel(motion="approach").mean("neuron")
    rec = peak.sel(motion="recede").mean("neuron")
    assert np.all(app.values > 5.0 * rec.values + 5.0), (app.values, rec.values)
    con = ds.lc_rate_peak.sel(neuron=ds.neuron_type == "contraction").mean("neuron")
    assert np.all(con.sel(motion="recede").values > con.sel(motion="approach").values)
    # The disc grows exactly as 2·atan((l/v)/(t_c − t)) until its cap; time is relative to collision.
    t = ds.time.values
    tc = 0.0
    lv = float(ds.l_over_v_s[0])
    early = (t < tc - 0.2) & (t >= -ds.attrs["t_collision_s"])  # from the disc's appearance, after the baseline
    np.testing.assert_allclose(ds.angular_size_deg.sel(motion="approach").isel(l_over_v_s=0).values[early],
                               np.degrees(2 * np.arctan(lv / (tc - t[early]))), rtol=1e-12)



def test_recording_reopens_with_config_and_version_and_seed_reproduces(tmp_path):
    import lobula
    cfg = _with_neurons(EphysConfig(trials=3, seed=7), model="poisson")
    kw = dict(temporal_frequencies_hz=[2.0, 8.0], duration_s=0.3, settle_s=0.1,
              record=["lc.spikes[expansion]", "lc.rate[contraction]", "photoreceptor.v[0,5,9]"])
    ds = tf_tuning(cfg, **kw)
    path = write_netcdf(ds, tmp_path / "rec.nc")
    back = xr.open_dataset(path, engine="h5netcdf")
    assert back.attrs["lobula_version"] == lobula.__version__
    conf = json.loads(back.attrs["config"])
    assert EphysConfig.from_dict(conf["ephys"]) == cfg
    assert back.lc_spikes.dims == ("temporal_frequency_hz", "contrast", "trial", "time", "neuron")
    # Monitors of different subsets share the neuron dim; each is NaN where it did not record.
    exp = back.neuron_type == "expansion"
    con = back.neuron_type == "contraction"
    assert set(back.neuron_type.values) == {"expansion", "contraction"}
    assert np.isnan(back.lc_spikes.sel(neuron=con)).all() and np.isfinite(back.lc_spikes.sel(neuron=exp)).all()
    assert np.isnan(back.lc_rate.sel(neuron=exp)).all() and np.isfinite(back.lc_rate.sel(neuron=con)).all()
    assert back.photoreceptor_v.dims == ("temporal_frequency_hz", "contrast", "time", "ommatidium")
    assert back.lc_rate.attrs["units"] == "Hz"
    np.testing.assert_array_equal(back.lc_spikes.values, ds.lc_spikes.values)
    np.testing.assert_array_equal(back.photoreceptor_v.ommatidium.values, [0, 5, 9])
    back.close()
    again = tf_tuning(cfg, **kw)
    np.testing.assert_array_equal(again.lc_spikes.values, ds.lc_spikes.values)
    other = tf_tuning(replace(cfg, seed=8), **kw)
    assert not np.array_equal(other.lc_spikes.values, ds.lc_spikes.values)
    assert ds.lc_spikes.sum() > 0
    # PSTH (Hz, trial-averaged) and raster of a spiking unit.
    p = psth(ds, bin_s=0.02)
    assert p.attrs["units"] == "Hz" and "trial" not in p.dims
    n = int(ds.neuron[exp.values][0])
    times, trials = raster(ds, n, temporal_frequency_hz=8.0)
    assert len(times) == int(ds.lc_spikes.sel(neuron=n, temporal_frequency_hz=8.0).sum())
    assert set(np.unique(trials)) <= {0, 1, 2}


def test_lif_units_record_membrane_and_spikes():
    cfg = _with_neurons(EphysConfig(trials=2, seed=1), model="lif")
    ds = looming(cfg, l_over_v_s=(0.04,), duration_s=0.5)
    assert "lc_v" in ds and "lc_spikes" in ds
    v = ds.lc_v.values
    assert v.min() > -0.08 and v.max() < -0.049                      # volts, below threshold after reset
    ex = ds.neuron_type.values == "expansion"
    counts = ds.lc_spikes.sum(["time", "trial"]).isel(neuron=np.nonzero(ex)[0]).mean("neuron").squeeze("l_over_v_s")
    assert float(counts.sel(motion="approach")) > float(counts.sel(motion="recede"))


def test_monitor_parsing_and_errors():
    rig = Rig(EphysConfig())
    m = parse_monitor("lc.rate[expansion]", rig)
    assert len(m.neurons) == rig.population.n_fields
    assert parse_monitor("emd.response[0:5]", rig).neurons == (0, 1, 2, 3, 4)
    assert parse_monitor("lc.r", rig).neurons is None
    for bad in ("lc.volts", "lc.v", "lc.r[expansion]", "emd.response[99999]", "rate"):
        with pytest.raises(ValueError):
            parse_monitor(bad, rig)


def test_steady_state_mean_uses_whole_periods():
    t = np.arange(0, 2.0, 1e-3)
    f = np.array([1.3, 3.7])
    x = 2.0 + np.sin(2 * np.pi * f[:, None] * t[None, :])[..., None]      # (2, T, 1)
    np.testing.assert_allclose(steady_state_mean(x, t, f, 0.25)[:, 0], 2.0, atol=2e-3)


def test_command_line_writes_recording_and_plot(tmp_path):
    parser = argparse.ArgumentParser(prog="lobula")
    add_parser(parser.add_subparsers(dest="command"))
    out, png = tmp_path / "loom.nc", tmp_path / "loom.png"
    args = parser.parse_args(["ephys", "looming", "--l-over-v", "0.04", "--duration", "0.4", "--trials", "2",
                              "--neuron-model", "poisson", "--seed", "3", "--record", "lc.spikes", "lc.rate",
                              "--out", str(out), "--plot", str(png)])
    assert args.func(args) == 0
    assert out.exists() and png.exists() and png.stat().st_size > 1000
    with xr.open_dataset(out, engine="h5netcdf") as ds:
        assert ds.attrs["protocol"] == "looming" and ds.attrs["seed"] == 3
        assert ds.sizes["trial"] == 2


def test_rf_map_recovers_a_box_field():
    cfg = _with_fields(EphysConfig(trials=1), size_deg=10.0, centres_deg=((-8.0, -4.0),), shape="box")
    ds = rf_map(cfg, extent_deg=11.0, directions=3)
    err = math.hypot(float(ds.rf_centre_azimuth_deg[0]) + 8.0, float(ds.rf_centre_elevation_deg[0]) + 4.0)
    assert err < ds.attrs["dphi_deg"]
    assert float(ds.rf_size_deg[0]) == pytest.approx(10.0, rel=0.2)


def _blank_margins(png) -> dict:
    """The blank (white) band at each edge of a PNG written at experiments.ephys.figures.DPI (inches)."""
    import matplotlib.image as mpimg

    from experiments.ephys.figures import DPI

    img = mpimg.imread(str(png))[..., :3]
    ink = (img < 0.97).any(-1)
    cols, rows = np.flatnonzero(ink.any(0)), np.flatnonzero(ink.any(1))
    w, h = ink.shape[1], ink.shape[0]
    return {k: px / DPI for k, px in dict(left=cols[0], right=w - 1 - cols[-1], top=rows[0],
                                          bottom=h - 1 - rows[-1]).items()}


def test_figures_have_no_blank_margins_when_a_panel_has_no_data(tmp_path):
    from experiments.ephys.figures import plot_recording

    # LC rates only (no EMD probe pairs): one tuning panel, not a blank one beside it.
    tuning = tf_tuning(EphysConfig(trials=1), temporal_frequencies_hz=(1.0, 4.0, 16.0), duration_s=0.6,
                       settle_s=0.2, record=["lc.rate"])
    assert "emd_response_tuning" not in tuning
    # One mapped field in a figure sized for several.
    cfg = _with_fields(EphysConfig(trials=1), size_deg=10.0, centres_deg=((-8.0, -4.0),), shape="gaussian")
    one_field = rf_map(cfg, extent_deg=11.0, directions=3)
    for name, ds in (("tuning", tuning), ("rf", one_field)):
        png, pdf = plot_recording(ds, tmp_path / f"{name}.png")
        assert pdf.exists()
        m = _blank_margins(png)
        assert max(m.values()) < 0.2, (name, m)               # inches: the saved pad, not an empty panel


def test_replay_scores_score_a_short_replay_after_a_quarter_of_it():
    from experiments.ephys.replay_figures import replay_scores

    t = np.arange(0.0, 1.9, 1 / 30)                             # shorter than the 2 s default skip
    v = 0.2 * np.sin(t)
    rec = xr.Dataset(dict(v_true=("time", v), arithmetic_v=("time", v + 0.01),
                          readout_v=(("trial", "time"), np.full((2, t.size), np.nan))), coords=dict(time=t))
    sc = replay_scores(rec)
    assert sc["scored_after_s"] == pytest.approx(0.25 * t[-1])
    assert sc["arithmetic_rmse_m_s"] == pytest.approx(0.01)
    assert np.isnan(sc["neuron_rmse_m_s"])                      # the neuron never confident: no score, not 0
    assert replay_scores(rec, skip_s=1.0)["scored_after_s"] == 1.0


def test_looming_figure_averages_only_the_expansion_units(tmp_path, monkeypatch):
    from experiments.ephys import figures
    cfg = _with_neurons(EphysConfig(trials=2, seed=2), model="poisson")
    ds = looming(cfg, l_over_v_s=(0.02,), duration_s=0.4, record=["lc.spikes"])
    drawn = []
    monkeypatch.setattr(figures, "save_png_and_pdf", lambda fig, path, **kw: drawn.append(fig) or [])
    figures.plot_looming(ds, tmp_path / "loom.png")
    ax = drawn[0].axes[0]
    # The expansion units' PSTH (20 ms bins, Hz), computed here from the stored counts.
    ex = ds.lc_spikes.sel(neuron=ds.neuron_type == "expansion").isel(l_over_v_s=0).sel(motion="approach")
    n_ex = ex.sizes["neuron"]
    s = ex.transpose("trial", "time", "neuron").values.astype(float)
    k = 20
    n = s.shape[1] // k * k
    want = s[:, :n].reshape(s.shape[0], -1, k, n_ex).sum(2).mean((0, 2)) / (k * 1e-3)
    np.testing.assert_allclose(ax.lines[0].get_ydata(), want, rtol=1e-5)
    assert want.max() > 100.0                                   # the expansion units fire hard near collision
    assert f"n = {n_ex};" in ax.get_title() and n_ex == 15


@pytest.mark.parametrize("model,record", [("poisson", ["lc.rate", "lc.drive[r2]"]),
                                          ("lif", ["lc.spikes[expansion]", "lc.v[20:23]"])])
def test_looming_records_monitors_of_different_subsets(tmp_path, model, record):
    from experiments.ephys.command import run_protocol, write_outputs
    from experiments.ephys.figures import plot_looming
    ds = run_protocol("looming", dict(neuron_model=model, trials=2, duration=0.3, l_over_v=[0.02], record=record))
    names = [r.split("[")[0].replace(".", "_") for r in record]
    for name, spec in zip(names, record):
        own = ds[name].notnull().any([d for d in ds[name].dims if d != "neuron"])
        peak = ds[f"{name}_peak"]
        # Each variable's peak is finite exactly on the neurons its monitor recorded.
        np.testing.assert_array_equal(np.isfinite(peak.isel(l_over_v_s=0, motion=0)).values, own.values)
        assert int(own.sum()) == (ds.sizes["neuron"] if "[" not in spec else
                                  3 if spec.endswith("[20:23]") else 15)
    written = write_outputs(ds, [tmp_path / "loom.nc", tmp_path / "loom.nwb"])
    assert all(p.exists() for p in written)
    assert plot_looming(ds, tmp_path / "loom.png")[0].exists()


def test_an_empty_slice_is_refused_naming_the_valid_range(tmp_path, capsys):
    rig = Rig(EphysConfig())
    n = rig.population.n_units
    for sub in ("5:2", "99999:100000"):
        with pytest.raises(ValueError, match=rf"the slice \[{sub}\] selects nothing; give \[i:j\] with 0 ≤ i < j ≤ "
                                             rf"{n}"):
            parse_monitor(f"lc.rate[{sub}]", rig)
    from experiments.cli import main
    assert main(["ephys", "looming", "--l-over-v", "0.04", "--duration", "0.3", "--dphi", "4", "--field-size", "20",
                 "--record", "lc.rate[5:2]", "--out", str(tmp_path / "never.nc")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "selects nothing" in err and "e.g. lc.rate[0:" in err
    assert not list(tmp_path.iterdir())
