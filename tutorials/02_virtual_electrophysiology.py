# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     name: python3
# ---

# %% [markdown]
# # Tutorial 2 — a virtual electrophysiology recording session
#
# The model fly (ommatidial lattice → photoreceptors → Hassenstein–Reichardt EMDs → lobula-
# columnar (LC) units → readout neuron, and the lobula plate's T4/T5 → HS/VS) is recorded the way a
# physiologist records a fly: choose a protocol, choose what to record, get a labelled,
# self-describing recording (an xarray Dataset; NetCDF and NWB files to share). This tutorial: a
# temporal-frequency tuning curve of Poisson-spiking LC units (the known answer: EMDs peak at
# 1/(2πτ)), a raster and its PSTH with the pre-stimulus baseline, a receptive-field map, ON and OFF
# edges through T4/T5 to HS, and the NWB export.
#
# Everything goes through one function, `experiments.ephys.run(protocol, **options)`: its options
# are those of `lobula ephys PROTOCOL`, by their Python names, and each recording remembers the
# equivalent command line. Open this file as a notebook with jupytext, or run it as a script.

# %%
import os
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from experiments.ephys import options, plot_recording, psth, psth_sem, raster, run, to_nwb

QUICK = os.environ.get("LOBULA_TUTORIAL_QUICK") == "1"  # the test suite's tiny run
if QUICK:
    matplotlib.use("Agg")
work = Path("tutorial_output")
work.mkdir(exist_ok=True)
# A coarse eye and short stimuli keep the tiny run to seconds; the full run uses the defaults.
eye = dict(dphi=4.0) if QUICK else {}
tfs = [1, 4, 16] if QUICK else [0.5, 1, 2, 3, 4, 6, 8, 12, 16, 32]
duration = 1.0 if QUICK else 2.0
print(options("tf-tuning")["baseline"])  # every option, with its help and default

# %% [markdown]
# ## 1. Temporal-frequency tuning of Poisson-spiking LC units
# Rings expanding about the epipole at several temporal frequencies, after 0.3 s of uniform mean
# luminance (the baseline); we record the spikes and rates of the LC units. `out=` writes the
# recording as NetCDF and NWB while `run` returns it.

# %%
tau = 0.035
tf = run("tf-tuning", **eye, tau_s=tau, neuron_model="poisson", trials=3, temporal_frequencies_hz=tfs,
         duration_s=duration, baseline_s=0.3, record=["lc.rate", "lc.spikes"], out=[work / "tf.nc", work / "tf.nwb"])
print(tf.attrs["command_line"])  # the same recording from the shell
print(tf.lc_spikes.attrs)        # neuron model, dt and its parameters travel with the spikes
plot_recording(tf, work / "tf.png")

# %% [markdown]
# The tuning curve of the expansion units, mean ± SEM across units, against the EMD optimum
# 1/(2πτ):

# %%
expansion = tf.neuron_type == "expansion"
curve = tf.lc_spikes_tuning.sel(contrast=0.5).where(expansion, drop=True)
fig, ax = plt.subplots(figsize=(5, 3.5), layout="constrained")
ax.errorbar(tf.temporal_frequency_hz, curve.mean("neuron"),
            yerr=curve.std("neuron") / np.sqrt(curve.sizes["neuron"]), marker="o", capsize=3,
            label="expansion units (mean ± SEM)")
ax.axvline(1 / (2 * np.pi * tau), color="0.5", ls="--", label="1/(2πτ)")
ax.set(xscale="log", xlabel="temporal frequency (Hz)", ylabel="firing rate (Hz)",
       title="LC expansion units")
ax.legend(fontsize=8, frameon=False)
fig.savefig(work / "tutorial2_tuning.png", dpi=150)

# %% [markdown]
# ## 2. A raster and its PSTH, with the pre-stimulus baseline
# One expansion unit at the preferred frequency: spike times per trial, and the PSTH with its
# SEM across trials (20 ms bins). Time is relative to the grating's onset: the 0.3 s before it is
# the baseline (grey), where the unit fires at its spontaneous rate.

# %%
best = float(tf.temporal_frequency_hz[int(curve.mean("neuron").argmax("temporal_frequency_hz"))])
unit = int(curve.neuron[0])
times, trials = raster(tf, unit, var="lc_spikes", temporal_frequency_hz=best, contrast=0.5)
rate = psth(tf, "lc_spikes", 0.02).sel(temporal_frequency_hz=best, contrast=0.5, neuron=unit)
sem = psth_sem(tf, "lc_spikes", 0.02).sel(temporal_frequency_hz=best, contrast=0.5, neuron=unit)
t = rate.time.values
before = t < 0
print(f"unit {unit}: baseline {float(rate[before].mean()):.3g} Hz, after onset {float(rate[~before].mean()):.3g} Hz")
fig, (ax, ax2) = plt.subplots(2, 1, figsize=(6, 4.5), sharex=True, layout="constrained")
for a in (ax, ax2):
    a.axvspan(float(tf.time[0]), 0.0, color="0.9", lw=0)
    a.axvline(0.0, color="0.4", ls=":", lw=0.8)
ax.eventplot([times[trials == k] for k in range(tf.sizes["trial"])], colors="k", linelengths=0.8)
ax.set(ylabel="trial", yticks=range(tf.sizes["trial"]), title=f"unit {unit} at {best:g} Hz (grey: baseline)")
ax2.plot(t, rate, color="tab:red", label="PSTH (trial mean)")
ax2.fill_between(t, rate - sem, rate + sem, color="tab:red", alpha=0.3, lw=0, label="± SEM across trials")
ax2.set(xlabel="time since grating onset (s)", ylabel="PSTH (Hz, 20 ms bins)", xlim=(float(t[0]), float(t[-1])))
ax2.legend(fontsize=8, frameon=False, loc="upper left")
fig.savefig(work / "tutorial2_raster.png", dpi=150)

# %% [markdown]
# ## 3. Receptive-field map of one LC field
# A small spot moves locally in several directions over a grid around the field; the map is
# each position's motion sensitivity, and its centre and size are estimated from it.

# %%
rf = run("rf-map", **eye, fields=[0], out=work / "rf.nc")
plot_recording(rf, work / "rf.png")
print(f"field 0: mapped centre ({float(rf.rf_centre_azimuth_deg[0]):.1f}°, "
      f"{float(rf.rf_centre_elevation_deg[0]):.1f}°), designed ({float(rf.field_azimuth_deg[0]):.1f}°, "
      f"{float(rf.field_elevation_deg[0]):.1f}°); size {float(rf.rf_size_deg[0]):.1f}° "
      f"(designed {float(rf.field_size_deg[0]):.1f}°)")

# %% [markdown]
# ## 4. ON and OFF edges through T4/T5 to HS
# Edges sweep across the eye in four directions. T4 (ON) and T5 (OFF) layers prefer one direction
# each: the direction-selectivity index DSI = (R_pref − R_null)/(R_pref + R_null) is positive for
# every layer. The HS cells, pooling the horizontal layers, depolarise most for front-to-back motion.

# %%
edges = run("edges", **eye, out=[work / "edges.nc", work / "edges.nwb"])
plot_recording(edges, work / "edges.png")
for cell in ("t4", "t5"):
    print(cell.upper(), "DSI:", {str(d): round(float(v), 3) for d, v in zip(edges.preferred_direction.values,
                                                                            edges[f"{cell}_dsi"].values)})
hs = edges.hs_v_mean.sel(polarity="on").mean("hs_cell")
print("HS mean potential (mV) per ON-edge direction:", {str(d): round(float(v), 2)
                                                         for d, v in zip(hs.direction.values, hs.values)})

# %% [markdown]
# ## 5. Sharing: NWB
# `out=` wrote each recording as Neurodata Without Borders too; `to_nwb` writes one already in hand.
# In the file: spike times in the Units table (with each unit's type and receptive field), rates,
# potentials and T4/T5 layers as TimeSeries (each channel labelled, with one table per channel
# dim), conditions as trials.

# %%
from pynwb import NWBHDF5IO

to_nwb(tf, work / "tf_shared.nwb", experimenter="Doe, Jane", institution="lobula tutorial")
with NWBHDF5IO(str(work / "tf.nwb"), "r") as io:
    nwb = io.read()
    units = nwb.units.to_dataframe()
    print(units[["unit_type", "rf_azimuth_deg", "rf_elevation_deg"]].head())
    print(f"{len(units)} units, {len(nwb.trials)} trials")
with NWBHDF5IO(str(work / "edges.nwb"), "r") as io:
    nwb = io.read()
    print(list(nwb.acquisition), nwb.processing["channels"]["hs_cell"].to_dataframe())
