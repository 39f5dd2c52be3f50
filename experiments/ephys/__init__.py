"""Virtual electrophysiology: show the model fly a stimulus, record any neuron, get labelled arrays.

The package follows the physiologist's workflow, one module per stage:

- :mod:`.rig` — the recording layer: the rig (eye + :class:`lobula.circuit.Circuit`),
  Brian2-style monitors (``"lc.rate"``, ``"lc.spikes[expansion]"``,
  ``"emd.response[0:20]"``, ``"photoreceptor.v"``), labelled :class:`xarray.Dataset`
  recordings and their self-description (CF-1.10 units/long_name on every variable and
  coordinate; configuration, version, commit, command line, creation time).
- :mod:`.protocols` — ``tf-tuning`` (known answer: the optimum 1/(2πτ)), ``rf-map``
  (local-motion spot mapping: centre, size, preferred directions), ``looming``
  (approach vs recession, time relative to collision), ``edges`` (ON and OFF edges or bars in four
  directions through T4/T5 to HS/VS, with direction-selectivity indices; :mod:`.edges`);
  :func:`psth`, :func:`psth_sem`,
  :func:`raster`. ``velocity-replay`` lives in :mod:`experiments.replay_protocol`.
- :mod:`.injection` — ``current-injection`` (current steps into the LC units with the eye at rest:
  f–I curve against the LIF theory, rheobase, ISI CV); :mod:`.white_noise` — ``white-noise``
  (spatiotemporal white noise and reverse correlation: each recorded cell's receptive field).
- :mod:`.figures` — each protocol's figure (PNG + PDF), drawn from the stored data.
- :mod:`.command` — ``lobula ephys`` (NetCDF and/or NWB via :mod:`experiments.nwb`).
- :mod:`.api` — the same as Python: :func:`run` (protocol, circuit, options → Dataset),
  :func:`to_nwb`, :func:`options`; :mod:`.published` — published physiology beside the model.
- :mod:`.bench` — the tuning-sweep benchmark (a 5,000-ommatidia eye).

Recordings have dims ``trial``, ``time`` (s), ``neuron`` (LC units; coords ``neuron_type``,
``azimuth_deg``, ``elevation_deg``, ``size_deg``, ``field_index``), ``field``,
``ommatidium``, ``pair``, plus one dim per stimulus parameter. The front end is
deterministic and carries no ``trial`` dim; neuron variables do (one trial for a
deterministic neuron model). Spikes are counts per model step (``dt_s`` in their attrs,
with the neuron model and its parameters).
"""
from lobula._lazy import lazy_api

from .command import PROTOCOLS, add_parser, main, run_protocol, summary

#: public name -> the module of this package that defines it, imported on first use: the rig and
#: the protocols need torch, and `lobula ephys --help` (which needs only .command) should not
_API = {
    "bench_tuning_sweep": "bench",
    "run": "api", "to_nwb": "api", "options": "api",
    "current_injection": "injection", "injection_summary": "injection", "plot_current_injection": "injection",
    "white_noise": "white_noise", "white_noise_summary": "white_noise", "plot_white_noise": "white_noise",
    "contrast": "contrast", "flicker": "flicker", "plot_contrast": "contrast", "plot_flicker": "flicker",
    "adaptation": "adaptation", "plot_adaptation": "adaptation",
    "edges": "edges", "edges_summary": "edges", "plot_edges": "edges", "plot_looming": "figures", "plot_recording": "figures", "plot_rf_map": "figures", "plot_tf_tuning": "figures",
    "TF_GRID_HZ": "protocols", "looming": "protocols", "psth": "protocols", "psth_sem": "protocols",
    "raster": "protocols", "rf_map": "protocols", "steady_state_mean": "protocols", "tf_tuning": "protocols",
    "EphysConfig": "rig", "Monitor": "rig", "Rig": "rig", "cf_describe": "rig", "parse_monitor": "rig",
    "record_dataset": "rig", "recording_attrs": "rig", "torch_threads": "rig",
}

__all__ = ["EphysConfig", "Rig", "Monitor", "parse_monitor", "record_dataset", "recording_attrs", "cf_describe",
           "torch_threads", "tf_tuning", "rf_map", "looming", "psth", "psth_sem", "raster", "steady_state_mean",
           "TF_GRID_HZ", "edges", "edges_summary", "plot_edges", "plot_tf_tuning", "plot_rf_map", "plot_looming", "plot_recording", "bench_tuning_sweep",
           "contrast", "flicker", "adaptation", "plot_contrast", "plot_flicker", "plot_adaptation",
           "current_injection", "injection_summary", "plot_current_injection", "white_noise", "white_noise_summary",
           "plot_white_noise",
           "add_parser", "main", "run_protocol", "summary", "PROTOCOLS", "run", "to_nwb", "options"]


# Lazy public API: importing the package stays light, so the command line starts fast.
__getattr__, __dir__ = lazy_api(__name__, _API, __all__)
