# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     name: python3
# ---

# %% [markdown]
# # Tutorial 1 — velocity from footage, and reading the result
#
# What you will do: render a synthetic footage folder with exact ground truth, estimate forward
# velocity from it with the default pipeline (DIS optic flow → receptive fields → readout with
# the accelerometer), and open the NetCDF it writes to look at v̂, its uncertainty, the
# per-field expansion rates and the provenance of the run.
#
# Each `lobula(...)` call below is exactly the shell command `lobula ...`; run them in a
# terminal instead if you prefer. Open this file as a notebook (`tutorials/README.md` says how)
# or run it as a script; either way its outputs go to `tutorial_output/` of the folder it runs in.

# %%
import os
import shlex
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import xarray as xr

from experiments.cli import main


def lobula(command: str) -> None:
    """Run a `lobula` command line (the same as typing it in a shell)."""
    print("$ lobula", command)
    assert main(shlex.split(command)) == 0


# The test suite runs every tutorial on tiny inputs (LOBULA_TUTORIAL_QUICK=1) so they cannot rot.
QUICK = os.environ.get("LOBULA_TUTORIAL_QUICK") == "1"
if QUICK:
    matplotlib.use("Agg")
DURATION, SCALE = (4, 0.25) if QUICK else (20, 0.5)
work = Path("tutorial_output")
work.mkdir(exist_ok=True)

# %% [markdown]
# ## 1. Footage with exact truth
# `lobula scene` ray-casts textured panels and a floor as the camera follows a velocity
# profile (the real FLIVVER run when `../shared` is beside the project, else a built-in one),
# and writes a footage folder: `camera.json`, `frames/`, `frames.csv`, a 250 Hz `imu.csv`
# (accelerometer with gravity, bias and noise; gyroscope), `truth.csv` and depth maps.

# %%
footage = work / "track"
if not (footage / "frames.csv").exists():
    lobula(f"scene {footage} --builtin-profile --start 2 --duration {DURATION} --scale {SCALE} --seed 1 --quiet")
print(sorted(p.name for p in footage.iterdir()))
print((footage / "camera.json").read_text())

# %% [markdown]
# ## 2. Estimate velocity
# The default is zero-phase (an offline smoother); `--filter causal` is what a fly could do
# online. Both write the same variables.

# %%
for kind in ("zero-phase", "causal"):
    lobula(f"velocity {footage} --front-end dis --filter {kind} --out {work}/{kind}.nc --skip 1 --quiet")

# %% [markdown]
# ## 3. Read the NetCDF
# Dims are `time` (s) and `field` (receptive fields, with their centres and size in degrees).
# `v_hat` is NaN where the readout cannot know the speed (`observable` False); `v_std` is its
# posterior standard deviation; `r`, `r2`, `r_dot` are the pooled expansion rate, its mean
# square and its rate of change per field.

# %%
ds = xr.open_dataset(work / "zero-phase.nc")
print(ds)

# %%
err = (ds.v_hat - ds.v_true).where(ds.time > ds.time[0] + 1)
print(f"RMSE after 1 s: {float(np.sqrt((err ** 2).mean())):.3f} m/s; "
      f"observable {float(ds.observable.mean()):.0%} of frames")
inside = (abs(err) <= 2 * ds.v_std).where(np.isfinite(err))
print(f"truth inside ±2σ for {float(inside.mean()):.0%} of observable frames")

# %% [markdown]
# Every output says where it came from: the whole configuration (JSON), the version, the git
# commit and the command line.

# %%
for key in ("front_end", "filter", "acceleration_source", "lobula_version", "git_commit", "command_line"):
    print(f"{key:>20}: {ds.attrs.get(key)}")

# %% [markdown]
# ## 4. Look at it

# %%
causal = xr.open_dataset(work / "causal.nc")
fig, (ax, ax2) = plt.subplots(2, 1, figsize=(8, 5), sharex=True, layout="constrained")
ax.plot(ds.time, ds.v_true, "k--", label="truth")
for d, c, name in ((ds, "m", "zero-phase"), (causal, "tab:blue", "causal")):
    ax.plot(d.time, d.v_hat, color=c, label=name)
    ax.fill_between(d.time, d.v_hat - 2 * d.v_std, d.v_hat + 2 * d.v_std, color=c, alpha=0.15, lw=0)
ax.set(ylabel="forward velocity (m/s)", title="v̂ ± 2σ against truth")
ax.legend()
ax2.plot(ds.time, ds.r.median("field"), color="tab:green")
ax2.set(xlabel="time (s)", ylabel="median r̄ over fields (1/s)")
fig.savefig(work / "tutorial1_velocity.png", dpi=150)

# %% [markdown]
# The expansion rate in one field over time, and the fields' layout in the view:

# %%
fig, ax = plt.subplots(figsize=(5, 3.5), layout="constrained")
sc = ax.scatter(ds.azimuth_deg, ds.elevation_deg, c=ds.r.mean("time"), s=60 * ds.size_deg / ds.size_deg.max(),
                cmap="viridis", marker="s")
ax.invert_yaxis()
fig.colorbar(sc, label="mean r̄ (1/s)")
ax.set(xlabel="azimuth (deg)", ylabel="elevation (deg, down)", title="receptive fields")
fig.savefig(work / "tutorial1_fields.png", dpi=150)
