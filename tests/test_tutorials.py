"""The tutorials run end to end on tiny inputs (LOBULA_TUTORIAL_QUICK=1), so they cannot rot.

Each runs the two ways `tutorials/README.md` offers: as a script (``python tutorials/NN_x.py`` in
a fresh folder, with the scheduler a user gets: tutorial 3's Dask workers are spawned processes
that import the script again) and as a notebook (jupytext's conversion executed cell by cell by
an IPython kernel; skipped where the `tutorials` extra is not installed). Either way every output
lands in ``tutorial_output/`` of the folder it runs in, nothing else is written there or beside
the tutorials, and the outputs hold the tutorial's known answers.

Both ways run the same cells, so the default run takes each tutorial one way, the way with more to
break (:data:`DEFAULT_WAY`): tutorial 3 as a script, whose spawned workers import it again; the
others as notebooks, where a cell that leans on being a script (``__file__``) would fail. The other
way is marked ``slow`` (``make test-slow``).
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = sorted((ROOT / "tutorials").glob("[0-9][0-9]_*.py"))
OUTPUT = "tutorial_output"


def _png_ok(path: Path) -> None:
    """A real figure: a PNG over 5 kB whose pixels are not all one colour."""
    import matplotlib.image

    assert path.is_file(), f"{path.name} not written"
    assert path.stat().st_size > 5_000, f"{path.name}: {path.stat().st_size} bytes"
    assert float(matplotlib.image.imread(path)[..., :3].std()) > 0.01, f"{path.name} is blank"


def _rmse_after_1s(ds: xr.Dataset) -> float:
    err = (ds.v_hat - ds.v_true).where(ds.time > ds.time[0] + 1)
    return float(np.sqrt((err ** 2).mean()))


def check_01(out: Path) -> None:
    """Footage with exact truth; zero-phase and causal estimates within 2 cm/s of it (the speed spans
    ≈ 0.7 m/s), answered once the camera has moved (the still start has shown no depth); both figures."""
    frames = sorted((out / "track" / "frames").glob("*.png"))
    assert len(frames) == 120  # 4 s at 30 Hz
    assert len((out / "track" / "frames.csv").read_text().splitlines()) == 1 + len(frames)
    for kind in ("zero-phase", "causal"):
        with xr.open_dataset(out / f"{kind}.nc") as ds:
            assert ds.attrs["filter"].startswith(kind)
            assert float(ds.observable.where(ds.time > ds.time[0] + 1).mean()) > 0.9
            assert _rmse_after_1s(ds) < 0.02, kind
            assert float(ds.v_true.max() - ds.v_true.min()) > 0.3  # a moving profile: the bound above means something
    for name in ("tutorial1_velocity.png", "tutorial1_fields.png"):
        _png_ok(out / name)


def check_02(out: Path) -> None:
    """The LC expansion units' tuning peaks at the grid's frequency nearest the EMD optimum 1/(2πτ), and their
    PSTH rises from the baseline before the grating's onset; the receptive-field map finds field 0 within half
    its size of its centre; every T4 and T5 layer is direction selective and HS depolarises most for
    front-to-back ON edges; the NWB files hold every unit and trial of the NetCDF, and the HS cells."""
    from experiments.ephys import psth

    with xr.open_dataset(out / "tf.nc") as tf:
        assert tf.attrs["optimum_hz"] == pytest.approx(1 / (2 * np.pi * 0.035))
        assert tf.attrs["command_line"].startswith("lobula ephys tf-tuning")
        curve = tf.lc_spikes_tuning.sel(contrast=0.5).where(tf.neuron_type == "expansion", drop=True)
        grid = tf.temporal_frequency_hz.values
        best = grid[int(curve.mean("neuron").argmax("temporal_frequency_hz"))]
        assert best == grid[np.argmin(abs(np.log(grid / tf.attrs["optimum_hz"])))]
        assert float(tf.time[0]) == pytest.approx(-0.3)
        rate = psth(tf.load(), "lc_spikes", 0.02).sel(temporal_frequency_hz=best, contrast=0.5)
        rate = rate.where(tf.neuron_type == "expansion", drop=True).mean("neuron")
        assert float(rate.where(rate.time > 0.1).mean()) > 10 * float(rate.where(rate.time < -0.02).mean()) + 5
        n_units, n_trials = tf.sizes["neuron"], tf.sizes["temporal_frequency_hz"] * tf.sizes["trial"]
    with xr.open_dataset(out / "rf.nc") as rf:
        offset = np.hypot(float(rf.rf_centre_azimuth_deg[0] - rf.field_azimuth_deg[0]),
                          float(rf.rf_centre_elevation_deg[0] - rf.field_elevation_deg[0]))
        assert offset < float(rf.field_size_deg[0]) / 2
    with xr.open_dataset(out / "edges.nc") as edges:
        assert (edges.t4_dsi.values > 0).all() and (edges.t5_dsi.values > 0).all()
        hs = edges.hs_v_mean.sel(polarity="on").mean("hs_cell")
        assert str(hs.direction.values[int(hs.argmax("direction"))]) == "front_to_back"
        hs_names = edges.hs_cell_name.values.tolist()
    from pynwb import NWBHDF5IO

    with NWBHDF5IO(str(out / "tf.nwb"), "r") as io:
        nwb = io.read()
        assert len(nwb.units) == n_units and len(nwb.trials) == n_trials
    with NWBHDF5IO(str(out / "edges.nwb"), "r") as io:
        nwb = io.read()
        assert nwb.processing["channels"]["hs_cell"].to_dataframe().hs_cell_name.tolist() == hs_names
        assert {"hs_v", "vs_v", "t4_response", "t5_response"} <= set(nwb.acquisition)
    assert (out / "tf_shared.nwb").is_file()
    for name in ("tutorial2_tuning.png", "tutorial2_raster.png", "tf.png", "rf.png", "edges.png"):
        _png_ok(out / name)


def check_03(out: Path) -> None:
    """The 2 × 2 grid computed on the default scheduler (local worker processes), every point scored
    within 2 cm/s; the figure."""
    ds = xr.open_zarr(out / "field_size.zarr")
    assert dict(ds.rmse_m_s.sizes) == {"fields.size_deg": 2, "seed": 2}
    assert (ds.attrs["scheduler"], ds.attrs["workers"]) == ("processes", 2), "not the scheduler a user gets"
    assert ds.attrs["points_computed"] == 4 and ds.attrs["failed"] == "{}"
    rmse = ds.rmse_m_s.values
    assert np.all(np.isfinite(rmse)) and np.all(rmse < 0.02), rmse
    _png_ok(out / "tutorial3_sweep.png")


def check_04(out: Path) -> None:
    """Frame by frame: an estimate for every flow pair, within 3 cm/s of the truth where observable, and the
    whole-record causal run's σ to 1e-9; the figure."""
    _png_ok(out / "tutorial4_frame_by_frame.png")
    with np.load(out / "tutorial4_states.npz") as z:
        v, truth, gap = z["v"], z["truth"], float(z["gap"])
    ok = np.isfinite(v)
    assert ok.mean() > 0.5 and np.sqrt(np.mean((v - truth)[ok] ** 2)) < 0.03
    assert gap < 1e-9


CHECKS = {"01": check_01, "02": check_02, "03": check_03, "04": check_04}
#: optional packages a tutorial needs beyond the core install: virtual electrophysiology runs on torch
NEEDS = {"02": ("torch", "the bio extra")}


#: the way each tutorial runs in the default test run; the other way is marked slow
DEFAULT_WAY = {"01": "notebook", "02": "notebook", "03": "script", "04": "notebook"}


def _ways(way: str) -> list:
    """The tutorials as parameters, marked slow where ``way`` is not their default."""
    return [pytest.param(p, id=p.stem, marks=() if DEFAULT_WAY[p.name[:2]] == way else pytest.mark.slow)
            for p in TUTORIALS]


def test_every_tutorial_is_checked():
    assert sorted(p.name[:2] for p in TUTORIALS) == sorted(CHECKS) == sorted(DEFAULT_WAY)


def _check_outputs(path: Path, cwd: Path, tutorials_before: set[str], root_had_output: bool) -> None:
    assert sorted(os.listdir(cwd)) == [OUTPUT], "outputs outside tutorial_output/"
    assert {p.name for p in (ROOT / "tutorials").iterdir()} == tutorials_before, "files written beside the tutorials"
    assert root_had_output or not (ROOT / OUTPUT).exists(), "outputs written at the repository root"
    CHECKS[path.name[:2]](cwd / OUTPUT)


def _before(path: Path) -> tuple[set[str], bool]:
    """Skip a tutorial whose optional packages are absent; else what exists before it runs."""
    module, extra = NEEDS.get(path.name[:2], (None, None))
    if module and importlib.util.find_spec(module) is None:
        pytest.skip(f"{path.name} needs {module} ({extra}), which is not installed")
    return {p.name for p in (ROOT / "tutorials").iterdir()}, (ROOT / OUTPUT).exists()


@pytest.mark.parametrize("path", _ways("script"))
def test_tutorial_as_script(path, tmp_path):
    """``python tutorials/NN_x.py`` as the README says, from a fresh folder."""
    before = _before(path)
    env = dict(os.environ, LOBULA_TUTORIAL_QUICK="1")
    run = subprocess.run([sys.executable, str(path)], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-5000:]
    _check_outputs(path, tmp_path, *before)


@pytest.mark.parametrize("path", _ways("notebook"))
def test_tutorial_as_notebook(path, tmp_path, monkeypatch):
    """The jupytext notebook of each tutorial, executed top to bottom in a kernel started in a fresh folder."""
    why = 'needs the tutorials extra (.venv/bin/pip install -e ".[tutorials]")'
    jupytext = pytest.importorskip("jupytext", reason=f"jupytext not installed: {why}")
    nbclient = pytest.importorskip("nbclient", reason=f"nbclient not installed: {why}")
    pytest.importorskip("ipykernel", reason=f"ipykernel not installed: {why}")
    before = _before(path)
    monkeypatch.setenv("LOBULA_TUTORIAL_QUICK", "1")  # the kernel inherits this process's environment
    nb = jupytext.read(path)
    assert sum(c.cell_type == "code" for c in nb.cells) >= 4  # cells, not one block
    nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    _check_outputs(path, tmp_path, *before)
