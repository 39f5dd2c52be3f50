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
# columnar (LC) units → readout neuron) is recorded the way a physiologist records a fly:
# choose a protocol, choose what to record, get a labelled, self-describing file (NetCDF, and
# NWB to share). In this recording session: a temporal-frequency tuning curve (the known answer: EMDs
# peak at 1/(2πτ)), a receptive-field map, and a raster with its PSTH.
#
# Each `lobula(...)` call is exactly the shell command `lobula ...`. Open this file as a
# notebook with jupytext, or run it as a script.

# %%
import os
import shlex
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import xarray as xr

from experiments.cli import main
from experiments.ephys import psth, psth_sem, raster


def lobula(command: str) -> None:
    """Run a `lobula` command line (the same as typing it in a shell)."""
    print("$ lobula", command)
    assert main(shlex.split(command)) == 0


QUICK = os.environ.get("LOBULA_TUTORIAL_QUICK") == "1"  # the test suite's tiny run
if QUICK:
    matplotlib.use("Agg")
work = Path("tutorial_output")
work.mkdir(exist_ok=True)
# A coarse eye and short stimuli keep the tiny run to seconds; the full run uses the defaults.
eye = "--dphi 4" if QUICK else ""
tfs = "1 4 16" if QUICK else "0.5 1 2 3 4 6 8 12 16 32"
duration = 1.0 if QUICK else 2.0

# %% [markdown]
# ## 1. Temporal-frequency tuning of Poisson-spiking LC units
# Rings expanding about the epipole at several temporal frequencies; we record the spikes and
# rates of the LC units and the responses of a few probe EMDs. `--out` takes both formats.

# %%
tau = 0.035
lobula(f"ephys tf-tuning {eye} --tau {tau} --neuron-model poisson --trials 3 --tf {tfs} --duration {duration} "
       f"--record lc.rate lc.spikes --out {work}/tf.nc {work}/tf.nwb --plot {work}/tf.png")
tf = xr.open_dataset(work / "tf.nc")
print(tf.lc_spikes.attrs)        # neuron model, dt and its parameters travel with the spikes

# %% [markdown]
# The tuning curve of the expansion units, mean ± SEM across units, against the EMD optimum
# 1/(2πτ):

# %%
expansion = tf.neuron_type == "expansion"
curve = tf.lc_spikes_tuning.sel(contrast=0.5).where(expansion, drop=True)
fig, ax = plt.subplots(figsize=(5, 3.5), layout="constrained")
ax.errorbar(tf.temporal_frequency_hz, curve.mean("neuron"),
            yerr=curve.std("neuron") / np.sqrt(curve.sizes["neuron"]), marker="o", capsize=3)
ax.axvline(1 / (2 * np.pi * tau), color="0.5", ls="--", label="1/(2πτ)")
ax.set(xscale="log", xlabel="temporal frequency (Hz)", ylabel="firing rate (Hz)",
       title="LC expansion units (mean ± SEM over units)")
ax.legend()
fig.savefig(work / "tutorial2_tuning.png", dpi=150)

# %% [markdown]
# ## 2. A raster and its PSTH
# One expansion unit at the preferred frequency: spike times per trial, and the PSTH with its
# SEM across trials (10 ms bins).

# %%
best = float(tf.temporal_frequency_hz[int(curve.mean("neuron").argmax("temporal_frequency_hz"))])
unit = int(curve.neuron[0])
times, trials = raster(tf, unit, var="lc_spikes", temporal_frequency_hz=best, contrast=0.5)
rate = psth(tf, "lc_spikes", 0.01).sel(temporal_frequency_hz=best, contrast=0.5, neuron=unit)
sem = psth_sem(tf, "lc_spikes", 0.01).sel(temporal_frequency_hz=best, contrast=0.5, neuron=unit)
fig, (ax, ax2) = plt.subplots(2, 1, figsize=(6, 4.5), sharex=True, layout="constrained")
ax.eventplot([times[trials == k] for k in range(tf.sizes["trial"])], colors="k", linelengths=0.8)
ax.set(ylabel="trial", yticks=range(tf.sizes["trial"]), title=f"unit {unit} at {best:g} Hz")
t = rate[rate.dims[-1]]
ax2.plot(t, rate, color="tab:red")
ax2.fill_between(t, rate - sem, rate + sem, color="tab:red", alpha=0.3, lw=0)
ax2.set(xlabel="time (s)", ylabel="PSTH (Hz)")
fig.savefig(work / "tutorial2_raster.png", dpi=150)

# %% [markdown]
# ## 3. Receptive-field map of one LC field
# A small spot moves locally in several directions over a grid around the field; the map is
# each position's motion sensitivity, and its centre and size are estimated from it.

# %%
lobula(f"ephys rf-map {eye} --fields 0 --out {work}/rf.nc --plot {work}/rf.png")
rf = xr.open_dataset(work / "rf.nc")
print(rf)

# %% [markdown]
# ## 4. Sharing: the NWB file
# The same recording as Neurodata Without Borders: spike times in the Units table (with each
# unit's type and receptive field), rates as TimeSeries, conditions as trials.

# %%
from pynwb import NWBHDF5IO

with NWBHDF5IO(str(work / "tf.nwb"), "r") as io:
    nwb = io.read()
    units = nwb.units.to_dataframe()
    print(units[["unit_type", "rf_azimuth_deg", "rf_elevation_deg"]].head()
          if "unit_type" in units else units.head())
    print(f"{len(units)} units, {len(nwb.trials)} trials")
