"""`lobula figures` regenerates its figures deterministically, and the committed figures' numbers are current."""
import json
from pathlib import Path

import numpy as np
import pytest

from experiments.figures import FIGURES, run_figures

COMMITTED = Path(__file__).resolve().parents[1] / "figures"
#: Figures whose numbers another CPU moves at the same code (the EMD circuit's floating point): 0.18 % (Δφ sweep,
#: 2° point) and 0.45 % (contrast × τ sweep) between the machine that made them and another; every other figure
#: matches to the digit. A code change that moves a figure moves it by more (a replay DIS RMSE of 0.00520
#: against 0.00513 is 1.4 %, far beyond the default 0.1 %).
RTOL = {"rmse_vs_dphi": 1e-2, "rmse_vs_tau_contrast_noise": 1e-2}


@pytest.mark.slow
def test_figures_are_deterministic(tmp_path):
    # One figure made twice, on the built-in profile the test suite renders on every machine: every
    # figure's numbers against its committed record (the recorded profile) is the slow test below.
    which = ("error_vs_acceleration",)
    a = run_figures(tmp_path / "a", which, start_s=5.0, duration_s=6.0, seed=3, quick=True, progress=False)
    b = run_figures(tmp_path / "b", which, start_s=5.0, duration_s=6.0, seed=3, quick=True, progress=False)
    for name in which:
        ra = json.loads((tmp_path / "a" / f"{name}.json").read_text())["results"]
        rb = json.loads((tmp_path / "b" / f"{name}.json").read_text())["results"]
        assert ra == rb, name
        assert (tmp_path / "a" / f"{name}.png").stat().st_size > 10_000
        assert "lobula figures" in a[name]["command"]
        assert a[name]["git_commit"] and a[name]["replay"]["profile"].startswith("built-in profile")


def _numbers(x):
    """The numeric leaves of a JSON record, in a stable order."""
    if isinstance(x, dict):
        return [v for k in sorted(x) for v in _numbers(x[k])]
    if isinstance(x, list):
        return [v for e in x for v in _numbers(e)]
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return [float(x)]
    return []


def test_every_committed_figure_has_its_record():
    for name in FIGURES:
        rec = json.loads((COMMITTED / f"{name}.json").read_text())
        assert (COMMITTED / f"{name}.png").exists() and rec["command"].startswith("lobula figures"), name
        assert "git_commit" in rec and rec["replay"]["profile"], name


@pytest.mark.slow
def test_committed_figures_are_reproduced(tmp_path, real_profile, monkeypatch):
    """Regenerate every figure with the committed command's settings; the numbers must match the JSON."""
    monkeypatch.delenv("LOBULA_PROFILE")  # the committed figures follow the recorded profile
    recs = run_figures(tmp_path, FIGURES, progress=False)
    for name in FIGURES:
        committed = json.loads((COMMITTED / f"{name}.json").read_text())["results"]
        fresh = json.loads(json.dumps(recs[name]["results"], default=lambda o: o.tolist() if hasattr(o, "tolist")
                                      else str(o)))
        np.testing.assert_allclose(_numbers(fresh), _numbers(committed), rtol=RTOL.get(name, 1e-3), atol=1e-6,
                                   err_msg=name)


def test_emd_gaze_figure_scores_and_draws(tmp_path):
    """The EMD-gaze figure's coverage is the share of scored steps inside ±2σ, and it draws what it is given."""
    import xarray as xr

    from experiments.gaze_figure import CONFIGURATIONS, coverage, plot_emd_gaze

    t = np.arange(0.0, 4.0, 0.5)
    ds = xr.Dataset(dict(v_hat=("time", np.array([9, 9, 9, 9, 1.0, 1.1, 1.3, np.nan])),
                         v_true=("time", np.ones(8)), v_std=("time", np.full(8, 0.1))), coords=dict(time=t))
    assert coverage(ds) == pytest.approx(2 / 3)          # after 2 s: 1.0 and 1.1 inside, 1.3 outside, NaN not counted
    numbers = {f: {k: dict(rmse=[0.1, 0.2, 0.05], coverage=[0.9, 1.0, 0.8]) for k in CONFIGURATIONS}
               for f in ("rotation", "panels")}
    traces = {k: (t, np.ones(8)) for k in list(CONFIGURATIONS) + ["truth"]}
    png = plot_emd_gaze(numbers, traces, tmp_path / "g.png", "rotation seed 0")
    assert png.stat().st_size > 10_000


def test_eye_rate_vs_spiking_draws_the_observable_seeds_where_one_never_is():
    """A seed that is never observable scores NaN: its configuration still gets a bar (the mean of the
    other seeds) and the missing seed a cross, instead of no bar at all."""
    import matplotlib.pyplot as plt

    from experiments.eye_figures import NEVER_OBSERVABLE_Y, draw_eye_rate_vs_spiking

    res = {"panels": {"rate (arithmetic readout)": [0.03, 0.05, 0.04], "readout neuron (rate)": [1.3, 0.04, np.nan],
                      "zero estimator": [0.3, 0.3, 0.3], "DIS on the D435i (causal)": [0.01, 0.012, 0.011]}}
    fig = draw_eye_rate_vs_spiking(res)
    ax = fig.axes[0]
    assert [b.get_height() for b in ax.containers[0]] == pytest.approx([0.04, 0.67])
    crosses = [ln for ln in ax.lines if ln.get_marker() == "x"]
    assert len(crosses) == 1 and list(crosses[0].get_xydata()[:, 1]) == [NEVER_OBSERVABLE_Y]
    plt.close(fig)


def test_a_replay_too_short_to_score_is_refused_before_it_is_rendered(tmp_path):
    from experiments.figures import MIN_REPLAY_S, run_figures

    with pytest.raises(ValueError, match=f"give at least {MIN_REPLAY_S:g} s"):
        run_figures(tmp_path / "f", ("error_vs_acceleration",), duration_s=2.0, quick=True, progress=False)
    assert not (tmp_path / "f").exists()


def test_replay_options_for_figures_that_render_their_own_worlds_are_refused(tmp_path, capsys):
    from experiments.cli import main

    assert main(["figures", "--only", "eye_rmse", "--quick", "--start", "1e9", "--out", str(tmp_path / "f")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--start, --quick set the replay's figures; eye_rmse renders its own worlds" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "f").exists()
