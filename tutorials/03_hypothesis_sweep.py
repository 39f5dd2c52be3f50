# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     name: python3
# ---

# %% [markdown]
# # Tutorial 3 — a hypothesis sweep on Dask, and its figure
#
# Hypothesis: *larger receptive fields pool more flow and so estimate velocity better, until
# they are so large that too few fields remain for a robust median.* We test it by sweeping the
# field size over several scene seeds: every grid point renders (or reuses) a synthetic run,
# estimates velocity and scores it against exact truth. `lobula sweep` runs the points on a
# local Dask cluster (or on any `dask.distributed` scheduler with `--scheduler ADDRESS`), writes
# one Zarr store with a dimension per parameter, and resumes where it stopped if interrupted.
#
# Open this file as a notebook with jupytext, or run it as a script. Dask starts each worker as a
# fresh Python process that imports this file again, so every cell that does work sits under
# `if __name__ == "__main__":` — true in the process you started (and always in a notebook),
# false in the workers, which so run only the first cell: imports and settings.

# %%
import os
import shlex
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import xarray as xr

from experiments.cli import main


def lobula(command: str) -> None:
    """Run a `lobula` command line (the same as typing it in a shell)."""
    print("$ lobula", command)
    assert main(shlex.split(command)) == 0


QUICK = os.environ.get("LOBULA_TUTORIAL_QUICK") == "1"  # the test suite's tiny run
if QUICK:
    matplotlib.use("Agg")
work = Path("tutorial_output")
work.mkdir(exist_ok=True)
sizes, seeds, duration, scale = ("5,15", "0,1", 4, 0.25) if QUICK else ("3,5,10,15", "0,1,2", 15, 0.5)
store = work / "field_size.zarr"

# %% [markdown]
# ## 1. What can be swept
# Any leaf of the velocity configuration or of the synthetic run, by its dotted path:

# %%
if __name__ == "__main__":
    lobula("sweep --list-params")

# %% [markdown]
# ## 2. Run the grid
# `--dry-run` first shows the grid and what is already recorded. Scenes differ by seed, so
# each seed is rendered once and shared by all field sizes.

# %%
if __name__ == "__main__":
    args = (f"sweep --param fields.size_deg={sizes} --param seed={seeds} --builtin-profile --start 2 "
            f"--base-duration {duration} --scale {scale} --skip 1 --workers 2 --out {store}")
    lobula(args + " --dry-run")
    lobula(args + (" --quiet" if QUICK else ""))  # the default scheduler: 2 local worker processes

# %% [markdown]
# ## 3. Read the store
# One dimension per swept parameter, named by its path; metrics are variables over the grid.

# %%
if __name__ == "__main__":
    ds = xr.open_zarr(store)
    print(ds[["rmse_m_s", "observable_fraction", "lock_on_s"]])

# %% [markdown]
# ## 4. The figure: RMSE against field size, mean ± sd over seeds

# %%
if __name__ == "__main__":
    rmse = ds.rmse_m_s
    mean, sd = rmse.mean("seed"), rmse.std("seed")
    fig, ax = plt.subplots(figsize=(5, 3.5), layout="constrained")
    ax.errorbar(ds["fields.size_deg"], mean, yerr=sd, marker="o", capsize=3)
    for s in ds.seed.values:
        ax.plot(ds["fields.size_deg"], rmse.sel(seed=s), ".", color="0.6")
    ax.set(xlabel="receptive-field size (deg)", ylabel="velocity RMSE (m/s)",
           title=f"field size sweep ({ds.sizes['seed']} seeds, mean ± sd)")
    fig.savefig(work / "tutorial3_sweep.png", dpi=150)
    print(mean.to_series())
