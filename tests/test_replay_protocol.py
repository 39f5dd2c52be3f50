"""The velocity-replay ephys protocol: labelled recording of the velocity circuit, seeded."""
import numpy as np
import xarray as xr

from experiments.cli import main
from experiments.replay_protocol import velocity_replay
from stimuli.scene import SceneConfig
from stimuli.track import TrackRunConfig, make_track_run


def test_velocity_replay_records_the_circuit(tmp_path, capsys):
    run = make_track_run(tmp_path / "run", TrackRunConfig(profile=None, start_s=5.0, duration_s=4.0, scale=0.25,
                                                          scene=SceneConfig(seed=4)), progress=False)
    out = tmp_path / "rec.nc"
    assert main(["ephys", "velocity-replay", "--footage", str(run), "--trials", "3", "--seed", "7",
                 "--out", str(out), "--plot", str(tmp_path / "rec.png")]) == 0
    rec = xr.open_dataset(out)
    assert rec.readout_spikes.dims == ("trial", "spike_time", "neuron") and rec.sizes["trial"] == 3
    assert list(rec.neuron.values) == ["plus", "minus"]
    assert {"azimuth_deg", "elevation_deg", "size_deg"} <= set(rec.coords)
    assert rec.attrs["lobula_version"] and "readout_neuron" in rec.attrs["config"]
    # Push–pull: never both neurons driven at once.
    rates = rec.readout_rate.values
    assert np.all(np.minimum(rates[..., 0], rates[..., 1]) == 0)
    # Same seed, same spikes; another seed, other spikes.
    again = velocity_replay(run, trials=3, seed=7)
    np.testing.assert_array_equal(again.readout_spikes.values, rec.readout_spikes.values)
    other = velocity_replay(run, trials=3, seed=8)
    assert not np.array_equal(other.readout_spikes.values, rec.readout_spikes.values)
    assert (tmp_path / "rec.png").stat().st_size > 10_000
