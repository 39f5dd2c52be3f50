"""Published data beside the model, the summary's neuron line and the flicker figure's two stages.

Known answers:
- edges_agreement: a layer driven only by the published polarity scores +1, only by the other −1; the
  selective fraction counts the layers whose DSI is > 0.
- The model's T4 layers answer ON edges only and T5 layers OFF edges only (the half-wave rectified lamina
  channels), so both polarity indices are +1 on a real edges run; the figure's JSON sidecar and the
  summary hold the same numbers.
- The summary names a neuron model only where the recording holds neuron variables.
- The flicker figure draws the photoreceptor and lamina gains in distinct, both visible styles.
Tiny rigs (Δφ = 6°): a few seconds.
"""
import json

import numpy as np
import pytest
import xarray as xr

from experiments.ephys import run
from experiments.ephys.command import summary
from experiments.ephys.published import DATASETS, T4_T5_SELECTIVITY, edges_agreement

DIRS = ["front_to_back", "back_to_front", "upward", "downward"]


def _edges_like(on: float, off: float, dsi) -> xr.Dataset:
    """An edges-shaped Dataset: every layer answers ``on`` to ON and ``off`` to OFF motion along its own
    preferred direction (0 elsewhere), T4 and T5 alike, with ``dsi`` per layer."""
    r = np.zeros((2, 4, 4))
    for k in range(4):
        r[0, k, k], r[1, k, k] = on, off
    coords = {"polarity": ["on", "off"], "direction": DIRS, "preferred_direction": DIRS}
    dims = ("polarity", "direction", "preferred_direction")
    return xr.Dataset({"t4_mean_response": (dims, r), "t5_mean_response": (dims, r),
                       "t4_dsi": ("preferred_direction", np.asarray(dsi, float)),
                       "t5_dsi": ("preferred_direction", np.asarray(dsi, float))}, coords=coords)


def test_edges_agreement_scores_polarity_and_selectivity():
    a = edges_agreement(_edges_like(on=2.0, off=0.0, dsi=[0.1, -0.1, 0.2, 0.3]))
    assert a["t4_polarity_index"] == pytest.approx(1.0)      # T4 published ON: ON only
    assert a["t5_polarity_index"] == pytest.approx(-1.0)     # T5 published OFF: ON only is the opposite
    assert a["polarity_agrees"] == 0.0
    assert a["t4_selective_fraction"] == pytest.approx(0.75)
    b = edges_agreement(_edges_like(on=3.0, off=1.0, dsi=[0.1, 0.1, 0.1, 0.1]))
    assert b["t4_polarity_index"] == pytest.approx(0.5) and b["t5_polarity_index"] == pytest.approx(-0.5)
    assert np.isnan(edges_agreement(_edges_like(on=0.0, off=0.0, dsi=[0, 0, 0, 0]))["t4_polarity_index"])
    assert T4_T5_SELECTIVITY["values"]["t4_preferred_polarity"] == "on"
    assert T4_T5_SELECTIVITY["values"]["t5_preferred_polarity"] == "off"
    for d in DATASETS.values():
        assert {"citation", "doi", "source", "measured", "values", "digitised"} <= set(d)
    assert T4_T5_SELECTIVITY["doi"] == "10.7554/eLife.29044"


def test_edges_figure_and_summary_report_the_published_selectivity(tmp_path):
    from experiments.ephys.figures import plot_recording

    ds = run("edges", dphi=6.0, field_size=24.0, speed=300.0, duration=0.3)
    want = edges_agreement(ds)
    # the model's ON and OFF channels are half-wave rectified: T4 sees ON edges only, T5 OFF edges only
    assert want["t4_polarity_index"] == pytest.approx(1.0, abs=1e-6)
    assert want["t5_polarity_index"] == pytest.approx(1.0, abs=1e-6)
    assert want["polarity_agrees"] == 1.0
    assert want["t4_selective_fraction"] == float(np.mean(ds.t4_dsi.values > 0))
    plot_recording(ds, tmp_path / "edges.png")
    side = json.loads((tmp_path / "edges.json").read_text())
    assert side["published"] == "t4_t5_selectivity"
    assert side["agreement"]["t5_polarity_index"] == pytest.approx(want["t5_polarity_index"])
    line = next(x for x in summary(ds) if x.startswith("published T4/T5 selectivity"))
    assert f"T4 polarity index {want['t4_polarity_index']:+.3g}" in line and "polarity agrees: yes" in line


def test_summary_names_a_neuron_model_only_for_recorded_neurons():
    flicker = run("flicker", dphi=6.0, tf=[2.0, 8.0], duration=0.2, settle=0.05)
    edges = run("edges", dphi=6.0, field_size=24.0, speed=300.0, duration=0.3)
    loom = run("looming", dphi=6.0, field_size=24.0, l_over_v=[0.04], duration=0.25, baseline=0.05)
    for ds in (flicker, edges):
        assert not any(x.startswith("neuron model") for x in summary(ds)), ds.attrs["protocol"]
    assert [x for x in summary(loom) if x.startswith("neuron model")] == ["neuron model rate, 1 trial(s) stored "
                                                                            "(the rate model is deterministic: every "
                                                                            "trial would be identical, one is stored)"]


def test_flicker_figure_keeps_the_photoreceptor_visible_under_the_lamina(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from experiments.ephys.flicker import plot_flicker

    ds = run("flicker", dphi=6.0, tf=[2.0, 8.0], duration=0.2, settle=0.05)
    # the two stages' gains coincide here, which is what would hide one curve under the other
    np.testing.assert_allclose(ds.photoreceptor_gain, ds.lamina_gain, rtol=0.01)
    kept = []
    monkeypatch.setattr(plt, "close", kept.append)  # keep the figure open to inspect its axes
    plot_flicker(ds, tmp_path / "flicker.png")
    fig = kept[0]
    lines = {ln.get_label(): ln for ln in fig.axes[0].lines}
    pr, la = lines["photoreceptor, exact discrete transfer"], lines["lamina, exact discrete transfer"]
    assert pr.get_linestyle() != la.get_linestyle()
    assert pr.get_linewidth() > la.get_linewidth()          # the wider line below stays visible on both sides
    pm, lm = lines["photoreceptor, measured"], lines["lamina, measured"]
    assert pm.get_marker() != lm.get_marker() and pm.get_markersize() > lm.get_markersize()
    assert lm.get_markerfacecolor() == "none"                # open markers: the ones below show through
    assert (tmp_path / "flicker.png").is_file()
    monkeypatch.undo()
    plt.close(fig)
