"""The lobula plate in the virtual-electrophysiology rig (T4/T5 layers, HS/VS cells) and the ``edges`` protocol.

Known answers:
- The rig's T4/T5 are the library chain on the same stimulus: the photoreceptor's low-pass stage, the
  lamina's own high-pass and rectification (lamina_on_off), the half-correlators (t4_t5). The rig
  recovers the low-pass stage from the circuit's high-passed photoreceptor output, so the high-pass
  is applied once.
- An ON edge only brightens each ommatidium, so the OFF channel and T5 stay at 0 (and vice versa);
  the chain is linear up to the rectifiers, so T5's responses to OFF edges equal T4's to ON edges.
- A half-correlator's direction selectivity for an edge comes from the delay acting on the channel's
  transient: the shorter the lamina's high-pass, the larger the DSI (≈ 0.1 with the 0.25 s default,
  > 0.3 with 50 ms), and only then do HS cells hyperpolarise for back-to-front edges (their shunting
  inhibition must outweigh the excitation the null direction still drives).
Tiny rig (Δφ = 4°, ~110 ommatidia): about a second per edges run.
"""
import json
from dataclasses import replace

import numpy as np
import pytest
import xarray as xr

from experiments.cli import main as cli_main
from experiments.ephys.command import run_protocol
from experiments.ephys.edges import edges
from experiments.ephys.rig import EphysConfig, Rig, parse_monitor, record_dataset
from experiments.store import cf_problems
from lobula.lattice import LatticeConfig
from lobula.motion_pathways import DIRECTIONS, OnOffConfig, lamina_on_off, t4_t5
from lobula.photoreceptor import PhotoreceptorConfig, photoreceptor_run
from stimuli.lattice_stimuli import moving_edge

TINY = EphysConfig(lattice=LatticeConfig(dphi_deg=4.0), trials=1)
#: L1/L2 with a 50 ms high-pass: transient channels
TRANSIENT = replace(TINY, on_off=OnOffConfig(tau_hp_on_s=0.05, tau_hp_off_s=0.05))


@pytest.fixture(scope="module")
def rig():
    return Rig(TINY)


@pytest.fixture(scope="module")
def runs():
    """edges on the tiny rig with the default lamina (0.25 s high-pass) and with a transient one (50 ms)."""
    return {"default": edges(TINY), "transient": edges(TRANSIENT)}


def _edge(rig, polarity="on", n=600):
    lum, _ = moving_edge(rig.lattice, n, polarity=polarity, direction_deg=[0.0, 90.0], speed_deg_s=50.0,
                         contrast=0.5, frame_rate_hz=1.0 / rig.dt)
    return lum


def test_monitors_record_the_lobula_plate_with_dims_and_units(rig):
    specs = ["t4.response", "t5.response[front-to-back, upward]", "hs.v", "vs.v[0:2]", "photoreceptor.v[0:3]"]
    mons = [parse_monitor(s, rig) for s in specs]
    assert parse_monitor("t5.response[front_to_back,upward]", rig) == mons[1]
    n = 600
    recs = rig.run(_edge(rig), n, mons)
    ds = record_dataset(rig, recs, mons, {"direction_deg": np.array([0.0, 90.0])}, n, {})
    assert ds.t4_response.dims == ("direction_deg", "time", "ommatidium", "preferred_direction")
    assert ds.t4_response.shape == (2, n, rig.lattice.n, 4)
    assert ds.preferred_direction.values.tolist() == list(DIRECTIONS)
    # T5 recorded two layers: the shared layer dim holds all four, the others NaN
    t5 = ds.t5_response
    assert np.isfinite(t5.sel(preferred_direction=["front_to_back", "upward"])).all()
    assert np.isnan(t5.sel(preferred_direction=["back_to_front", "downward"])).all()
    assert ds.hs_v.dims == ("direction_deg", "time", "hs_cell") and ds.sizes["hs_cell"] == 3
    assert ds.hs_cell_name.values.tolist() == ["HSN", "HSE", "HSS"]
    assert ds.vs_v.dims == ("direction_deg", "time", "vs_cell") and ds.vs_cell.values.tolist() == [0, 1]
    # photoreceptor.v[0:3] shares the ommatidium dim with T4 (all of it): NaN beyond its own three
    pv = ds.photoreceptor_v.values
    assert pv.shape == (2, n, rig.lattice.n) and np.isfinite(pv[..., :3]).all() and np.isnan(pv[..., 3:]).all()
    for v, units in (("t4_response", "1"), ("t5_response", "1"), ("hs_v", "mV"), ("vs_v", "mV")):
        assert ds[v].attrs["units"] == units and ds[v].attrs["long_name"], v
    for c in ("hs_cell_elevation_deg", "vs_cell_azimuth_deg"):
        assert ds[c].attrs["units"] == "degree" and ds[c].attrs["long_name"]
    # an ON edge: T4 responds, T5 is silent; HS depolarises for the rightward (front-to-back) edge
    assert float(ds.t4_response.max()) > 0.05 and float(np.nanmax(ds.t5_response.values)) < 1e-6
    assert float(ds.hs_v.sel(direction_deg=0.0).mean()) > 5.0


def test_rig_t4_t5_are_the_library_chain_on_the_same_stimulus(rig):
    lum = _edge(rig, n=500)
    out = rig.run(lum, 500, [parse_monitor("t4.response", rig)])
    x, _ = photoreceptor_run(PhotoreceptorConfig(tau_s=TINY.circuit.photoreceptor.tau_s), rig.dt, lum.double())
    ch = lamina_on_off(x, rig.dt, TINY.on_off)
    ref = t4_t5(ch.on, ch.off, rig.lattice, TINY.on_off, rig.dt).t4
    err = float((out["t4.response"].double() - ref).abs().max() / ref.abs().max())
    assert err < 1e-3, err


def test_the_lobula_plate_costs_nothing_unless_monitored(rig, monkeypatch):
    import experiments.ephys.edges as plate

    def refuse(*a, **k):
        raise AssertionError("the lobula plate ran without a monitor asking for it")

    monkeypatch.setattr(plate, "plate_records", refuse)
    out = rig.run(_edge(rig, n=50), 50, [parse_monitor("photoreceptor.v", rig)])
    assert set(out) == {"photoreceptor.v"}
    with pytest.raises(AssertionError, match="without a monitor"):
        rig.run(_edge(rig, n=50), 50, [parse_monitor("hs.v", rig)])


@pytest.mark.parametrize("spec,fix", [
    ("t4.response[sideways]", r"i:j, i,j,k, .* for T4/T5, directions \['front-to-back'"),
    ("hs.v[front-to-back]", r"a direction selects T4/T5 layers.*t4\.response\[front-to-back\]"),
    ("t4.response[front-to-back,3]", r"directions only .* not both"),
    ("t6.response", r"t4\.response, t5\.response, hs\.v, vs\.v.*front-to-back"),
])
def test_monitor_errors_name_the_fix(rig, spec, fix):
    with pytest.raises(ValueError, match=fix):
        parse_monitor(spec, rig)


def test_edge_polarity_selects_t4_or_t5(runs):
    ds = runs["default"]
    t4 = ds.t4_mean_response.mean(("direction", "preferred_direction"))
    t5 = ds.t5_mean_response.mean(("direction", "preferred_direction"))
    on = float(t4.sel(polarity="on")) / float(t5.sel(polarity="on"))
    off = float(t5.sel(polarity="off")) / float(t4.sel(polarity="off"))
    print(f"\nmean T4/T5: ON edges {on:.3g}, OFF edges T5/T4 {off:.3g}")
    assert on > 10.0 and off > 10.0
    # mirror image: T5 to OFF edges is T4 to ON edges
    np.testing.assert_allclose(ds.t5_mean_response.sel(polarity="off"), ds.t4_mean_response.sel(polarity="on"),
                               rtol=1e-3)
    for v in ("t4_dsi", "t5_dsi"):
        assert ds[v].attrs["units"] == "1" and ds[v].dims == ("preferred_direction",)


def test_t4_direction_selectivity_grows_as_the_lamina_turns_transient(runs):
    slow, fast = runs["default"].t4_dsi, runs["transient"].t4_dsi
    print(f"\nT4 DSI, L1/L2 high-pass 0.25 s: {slow.values.round(3)}; 50 ms: {fast.values.round(3)}")
    # every layer prefers its own direction over the opposite one ...
    assert (slow > 0.05).all() and (fast > 0.05).all()
    # ... weakly with sustained channels, clearly with transient ones (the front-to-back layer above 0.3)
    assert float(fast.sel(preferred_direction="front_to_back")) > 0.3
    assert (fast > slow + 0.1).all()
    np.testing.assert_allclose(runs["transient"].t5_dsi, fast, rtol=1e-3)          # OFF edges on T5: the same


def test_hs_cells_follow_the_direction_of_horizontal_edges(runs):
    for name, ds in runs.items():
        hs = ds.hs_v_mean.sel(polarity="on")
        ftb, btf = hs.sel(direction="front_to_back").values, hs.sel(direction="back_to_front").values
        print(f"\n{name} lamina: HS mean (mV) front-to-back {ftb.round(1)}, back-to-front {btf.round(1)}")
        assert (ftb > 5.0).all() and (ftb - btf > 5.0).all()
        assert ds.hs_v_peak.attrs["units"] == "mV"
    # with transient channels every HS cell hyperpolarises for back-to-front edges, ON and OFF alike
    hs = runs["transient"].hs_v_mean.sel(direction="back_to_front")
    assert (hs < -1.0).all(), hs.values
    # and each VS cell depolarises for downward edges more than for upward ones
    vs = runs["transient"].vs_v_mean.sel(polarity="on")
    assert (vs.sel(direction="downward") > vs.sel(direction="upward") + 5.0).all()


def test_command_line_writes_cf_clean_netcdf_and_the_figure(tmp_path):
    out, png = tmp_path / "edges.nc", tmp_path / "edges.png"
    assert cli_main(["ephys", "edges", "--dphi", "4", "--speed", "100", "--contrast", "0.4", "--out", str(out),
                     "--plot", str(png)]) == 0
    assert png.exists() and png.with_suffix(".pdf").exists() and png.stat().st_size > 20_000
    with xr.open_dataset(out, engine="h5netcdf") as ds:
        ds = ds.load()
    assert cf_problems(ds) == []
    assert ds.attrs["protocol"] == "edges" and ds.attrs["Conventions"] == "CF-1.10"
    par = json.loads(ds.attrs["parameters"])
    assert par["speed_deg_s"] == 100.0 and par["contrast"] == 0.4 and par["bar_width_deg"] is None
    assert ds.polarity.values.tolist() == ["on", "off"] and ds.direction.values.tolist() == list(DIRECTIONS)
    assert {"t4_response", "t5_response", "hs_v", "vs_v", "t4_dsi", "t5_dsi", "hs_v_peak", "vs_v_trough"} <= set(ds)
    assert float(ds.t4_dsi.sel(preferred_direction="front_to_back")) > 0.0
    # NWB holds the lobula plate's dims too (tests/test_nwb.py checks the file)
    assert cli_main(["ephys", "edges", "--dphi", "4", "--speed", "100", "--out", str(tmp_path / "edges.nwb")]) == 0


def test_edges_options_bars_and_refusals():
    bars = run_protocol("edges", {"dphi": 4.0, "bar_width": 8.0, "record": ["hs.v"], "duration": 0.5})
    assert bars.attrs["stimulus"] == "bars" and json.loads(bars.attrs["parameters"])["bar_width_deg"] == 8.0
    assert bars.sizes["time"] == 500 and "t4_response" not in bars and "hs_v" in bars
    # a bright bar has a trailing OFF edge: both pathways respond, T4 more
    t4 = float(bars.t4_mean_response.sel(polarity="on").mean())
    t5 = float(bars.t5_mean_response.sel(polarity="on").mean())
    assert t4 > t5 > 0.0
    with pytest.raises(ValueError, match="--eye does not apply to edges"):
        run_protocol("edges", {"eye": "fly"})
    with pytest.raises(ValueError, match="--speed does not apply to looming; it applies to edges"):
        run_protocol("looming", {"speed": 10.0})


def test_tf_tuning_records_t4_layers(rig):
    from experiments.ephys import tf_tuning

    ds = tf_tuning(TINY, temporal_frequencies_hz=[1.0, 4.5, 16.0], stimulus="grating", direction_deg=0.0,
                   duration_s=1.0, settle_s=0.5, record=["t4.response[front-to-back,back-to-front]", "hs.v"])
    tun = ds.t4_response_tuning
    assert tun.dims == ("temporal_frequency_hz", "contrast", "preferred_direction", "ommatidium")
    m = tun.mean("ommatidium").isel(contrast=0)
    # the rightward (front-to-back) grating drives its own layer more than the opposite one at every TF
    assert (m.sel(preferred_direction="front_to_back") > m.sel(preferred_direction="back_to_front")).all()
    assert (ds.hs_v_tuning.isel(contrast=0) > 0).all()
