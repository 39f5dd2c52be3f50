"""The online/offline information bound (experiments.online_bound) against known answers."""
import json
from dataclasses import replace

import numpy as np
import pytest

from experiments.online_bound import (InformationModel, family_trajectory, filter_and_smoother, main,
                                      online_offline, readout_latency_s)

T = np.arange(300) / 30.0


def test_latency_is_the_causal_readouts():
    # 1.5σ of the 1 Hz Gaussian at 30 frames/s (σ = 5.6 frames: 9 frames) plus half the stagger of 4 (2 frames)
    assert round(readout_latency_s(1 / 30) * 30) == 11


def test_a_known_offset_and_a_deterministic_motion_measure_the_start_velocity_frame_by_frame():
    # With b known and no acceleration noise, v_k = v_0 + a·t_k is known up to v_0, and frame k measures v_0 with
    # variance (floor·v_k/a)²: the filter's variance is 1/(1/prior + Σ_{j≤k} info_j), the smoother's the sum over all.
    a = 0.3
    v = 0.2 + a * T
    m = InformationModel(kappa_rel_error=0.0, kappa_abs_error=0.0, accel_floor=0.02, accel_noise=0.0,
                         bias_walk=0.0, bias_prior=1e-9, v_prior=1.0, latency_s=0.0)
    pf, ps, pl = filter_and_smoother(T, v, np.full_like(T, a), m)
    info = (a / (m.accel_floor * v)) ** 2
    expect_f = 1.0 / (1.0 / m.v_prior ** 2 + np.cumsum(info))
    expect_s = np.full_like(T, 1.0 / (1.0 / m.v_prior ** 2 + info.sum()))
    np.testing.assert_allclose(pf, expect_f, rtol=1e-5)
    np.testing.assert_allclose(ps, expect_s, rtol=1e-5)
    np.testing.assert_allclose(pl, pf)  # on time: the online estimate is the filter's


def test_a_random_walk_observed_each_frame_has_the_scalar_riccati_steady_states():
    # κ = a/v = 1 and b known: y = v + n each frame, v a random walk. Mid-record the filter and the smoother sit
    # at the scalar Riccati fixed points, and in the continuous limit (q·dt ≪ R) their ratio of variances is 2.
    v = np.exp(T)
    q, r = 0.01 ** 2, 0.02 ** 2
    m = InformationModel(kappa_rel_error=0.0, kappa_abs_error=0.0, accel_floor=np.sqrt(r), accel_noise=np.sqrt(q),
                         bias_walk=0.0, bias_prior=1e-9, latency_s=0.0)
    pf, ps, _ = filter_and_smoother(T, v, v, m)
    dt = T[1]
    qd = q * dt
    pminus = 0.5 * (qd + np.sqrt(qd ** 2 + 4 * qd * r))  # P⁻ = P + q·dt with P = P⁻·r/(P⁻ + r)
    p = pminus * r / (pminus + r)
    c = p / pminus
    p_s = (p - c ** 2 * pminus) / (1 - c ** 2)  # the RTS recursion's fixed point
    np.testing.assert_allclose(pf[150], p, rtol=1e-6)
    np.testing.assert_allclose(ps[150], p_s, rtol=1e-6)
    assert 1.85 < pf[150] / ps[150] < 2.0  # → 2 as q·dt/R → 0 (here 0.008)


def test_latency_only_adds_uncertainty_and_the_scale_error_is_common():
    t, v, a = T, 0.5 + 0.3 * np.sin(T), 0.3 * np.cos(T)
    on_time = online_offline(t, v, a, InformationModel(latency_s=0.0))
    late = online_offline(t, v, a, InformationModel(latency_s=0.4))
    assert on_time["online"] == pytest.approx(on_time["filter"])
    assert late["online"] > 1.05 * late["filter"]
    assert late["offline"] == pytest.approx(on_time["offline"])
    assert 1.0 < on_time["filter_ratio"] < late["online_ratio"]
    # a larger error common to both pulls the ratio toward 1
    big = online_offline(t, v, a, InformationModel(latency_s=0.4, scale_error=0.1))
    assert 1.0 < big["online_ratio"] < late["online_ratio"]


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="finite"):
        filter_and_smoother(T, np.full_like(T, np.nan), T, InformationModel())


def test_family_trajectory_is_the_rendered_truth(tmp_path):
    from experiments.suite import family_config
    from stimuli.footage import open_footage
    from stimuli.track import make_track_run

    cfg = replace(family_config("rotation", 5, 1.0, scale=0.1), depth_every=0)
    folder = make_track_run(tmp_path / "rot", cfg, progress=False)
    truth = open_footage(folder).truth
    t, v, a = family_trajectory("rotation", 5, 1.0)
    np.testing.assert_allclose(t, truth["time_s"], atol=1e-6)
    np.testing.assert_allclose(v, truth["v_forward_m_s"], atol=2e-6)
    np.testing.assert_allclose(a, truth["a_forward_m_s2"], atol=2e-6)


def test_command_line_writes_rows_and_provenance(tmp_path, capsys):
    out = tmp_path / "bound.json"
    assert main(["--families", "rest", "--seeds", "7,", "--duration", "4", "--models", "measured",
                 "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    (row,) = doc["rows"]
    assert row["family"] == "rest" and row["seed"] == 7 and row["online_ratio"] > row["filter_ratio"] > 1.0
    assert {"git_commit", "command_line", "config", "lobula_version"} <= set(doc["provenance"])
    assert "| rest |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--models", "nonesuch"])
