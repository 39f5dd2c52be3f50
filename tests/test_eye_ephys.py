"""`lobula ephys … --eye fly`: the compound eye's velocity circuit recorded, against known answers."""
import math
from pathlib import Path

import numpy as np
import pytest

from experiments.ephys.command import run_protocol
from experiments.ephys.eye_rig import EyeEphysConfig, EyeRig, eye_rf_map, eye_tf_tuning
from experiments.eye_velocity import EyeVelocityConfig

TF = [1.0, 2.0, 3.0, 4.55, 6.0, 8.0, 12.0]


@pytest.fixture(scope="module")
def tuning():
    return eye_tf_tuning(temporal_frequencies_hz=TF, contrasts=(0.2, 0.5), duration_s=1.5)


def test_the_recorded_circuit_is_the_velocity_circuit():
    rig = EyeRig()
    assert rig.config.circuit.to_dict() == EyeVelocityConfig().circuit.to_dict()
    circ = rig.new_circuit()
    assert circ.config.emd.tau_s == EyeVelocityConfig().circuit.emd.tau_s
    assert rig.eye.n == 1574 and rig.fields.n_fields == 80 and rig.rate_hz == 500.0


def test_tf_tuning_peaks_at_one_over_two_pi_tau_and_rho_reports_speed(tuning):
    ds = tuning
    opt = 1.0 / (2.0 * math.pi * 0.035)
    nearest = TF[int(np.argmin(np.abs(np.log(np.array(TF) / opt))))]
    assert ds.attrs["optimum_hz"] == pytest.approx(opt)
    # The correlators and the LC matched filters they feed peak at the grid point nearest 1/(2πτ).
    for v in ("emd_response_peak_temporal_frequency_hz", "lc_input_peak_temporal_frequency_hz"):
        assert np.all(ds[v].values == nearest), v
    # The pooled ρ divides the correlator by a pool with its own temporal filtering: it grows in
    # proportion to temporal frequency (R̄/Ḡ = ωτ·cot(Δϕ/2)) and does not depend on contrast.
    r = np.nanmedian(ds.lc_r_tuning.values, axis=-1)                 # (TF, contrast)
    gain = r[:5] / np.array(TF[:5])[:, None]                          # 1–6 Hz
    assert gain.max() / gain.min() < 1.12
    assert np.all(np.diff(r[:, 1]) > 0)
    assert np.allclose(r[:, 0], r[:, 1], rtol=0.02)


def test_tf_tuning_follows_tau():
    ds = eye_tf_tuning(EyeEphysConfig().with_options(tau_s=0.07), temporal_frequencies_hz=[1.0, 1.6, 2.27, 3.2, 4.55],
                       duration_s=1.5, record=["lc.input"])
    assert np.median(ds.lc_input_peak_temporal_frequency_hz.values) == 2.27


@pytest.mark.slow
def test_rf_map_recovers_the_designed_centre_and_size():
    ds = eye_rf_map(fields=[19], spacing_deg=10.0, extent_deg=36.0, directions=3)
    f = EyeRig().fields
    assert float(ds.rf_centre_error_deg.sel(field=19)) < 1.5
    assert abs(float(ds.rf_centre_azimuth_deg.sel(field=19)) - f.centres_deg[19, 0]) < 1.5
    assert float(ds.rf_size_deg.sel(field=19)) == pytest.approx(f.size_deg, rel=0.15)
    # Preferred directions point away from the focus of expansion (rightward on the right eye's equator).
    strong = ds.rf_sensitivity.sel(field=19).values > 0.5 * ds.rf_sensitivity.sel(field=19).max().values
    pref = ds.rf_preferred_direction_deg.sel(field=19).values[strong]
    assert np.median(np.abs(((pref + 180) % 360) - 180)) < 20


def test_eye_options_fail_naming_the_fix():
    with pytest.raises(ValueError, match="deterministic"):
        run_protocol("tf-tuning", {"eye": "fly", "trials": 3})
    with pytest.raises(ValueError, match="readout neuron"):
        run_protocol("tf-tuning", {"eye": "fly", "record": ["lc.spikes"]})
    # velocity-replay on the eye replays eye footage (tests/test_eye_replay.py); camera footage is refused.
    with pytest.raises(ValueError, match="not an eye-footage folder.*--eye fly"):
        run_protocol("velocity-replay", {"eye": "fly", "footage": str(Path(__file__).parent)})
    with pytest.raises(ValueError, match=r"\[0, 80\)"):
        run_protocol("rf-map", {"eye": "fly", "fields": [80]})


def test_looming_expands_on_approach_contracts_on_recession_and_peaks_earlier_for_slower_discs(tmp_path):
    from experiments.ephys.figures import plot_recording

    ds = run_protocol("looming", {"eye": "fly", "l_over_v": [0.01, 0.02, 0.04, 0.08]})
    reached = np.flatnonzero(ds.field_sees_disc.values)
    assert 8 <= len(reached) <= 40                                          # the frontal fields, both eyes
    peak = ds.lc_r_peak.isel(field=reached).median("field")
    # The translation template reads a disc growing straight ahead as expansion, one shrinking as contraction.
    assert (peak.sel(motion="approach") > 0.5).all() and (peak.sel(motion="recede") < -0.2).all()
    # Known answer for a looming stimulus: the response peaks before collision, earlier in proportion to l/|v|
    # (a fixed angular size is reached at t = −l/|v|/tan(θ/2)).
    lv = ds.l_over_v_s.values
    tp = ds.lc_input_time_of_peak_s.isel(field=reached).median("field").sel(motion="approach").values
    assert np.all(tp < 0) and np.all(np.diff(tp) < 0)
    slope, icpt = np.polyfit(lv, tp, 1)
    assert slope < -0.5 and np.corrcoef(lv, tp)[0, 1] < -0.95
    assert all(p.stat().st_size > 10_000 for p in plot_recording(ds, tmp_path / "loom.png"))


def test_an_empty_slice_is_refused_naming_the_valid_range():
    rig = EyeRig()
    n = rig.size("lc.r")
    with pytest.raises(ValueError, match=rf"'lc.r\[5:2\]': the slice \[5:2\] selects nothing; .* lc\.r\[0:{n}\]"):
        rig.monitors(["lc.r[5:2]"], [])
