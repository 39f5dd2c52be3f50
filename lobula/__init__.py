"""lobula: a model of the fly's lobula that estimates absolute velocity from vision plus acceleration."""
from __future__ import annotations

from ._lazy import lazy_api
from .version import __version__, git_commit

#: public name -> the module of this package that defines it (imported on first use)
_API = {
    "PinholeCamera": "camera", "angles_to_normalised": "camera", "normalised_to_angles": "camera",
    "VelocityConfig": "config",
    "estimate_velocity": "velocity", "VelocityEstimator": "velocity", "VelocityState": "velocity", "field_rates": "velocity", "open_footage": "readers",
    "EpipoleEstimator": "epipole", "derotate": "epipole", "rotational_flow": "epipole",
    "HeadingBiasEstimator": "epipole", "residual_rotation": "epipole",
    "GyroAttitude": "imu", "rotation_increments": "imu",
    "FlowConfig": "flow", "FlowSample": "flow", "StaggeredFlow": "flow", "pixel_to_angular": "flow",
    "forward_acceleration": "imu", "forward_axis": "imu", "transport_rate": "imu", "resample_to": "imu", "turn_rate": "imu",
    "fused_gyro_bias": "imu", "attitude_leak": "imu", "leak_walk": "imu",
    "ReadoutConfig": "readout", "ReadoutResult": "readout", "readout": "readout",
    "FieldConfig": "receptive_field", "ReceptiveFields": "receptive_field", "gap_correction": "receptive_field",
    "pool_fields": "receptive_field", "pool_stride": "receptive_field", "tile_fields": "receptive_field",
    "DepthConfig": "depth", "DepthResult": "depth", "depth_metrics": "depth", "depth_parallax": "depth",
    "depth_ratio": "depth", "depth_tv": "depth", "scorable": "depth", "error_stats": "depth",
    "flow_noise": "depth_motion", "precision_weights": "depth_motion", "translational_snr": "depth_motion",
    "refine_motion": "depth_motion",
    "EMDFrontEnd": "emd_front_end", "EMDFrontEndConfig": "emd_front_end", "fit_calibration": "emd_front_end",
    "pair_pooling_weights": "emd_front_end", "epipole_pooling_weights": "emd_front_end",
    "pooled_at_epipole": "emd_front_end",
    "EMDArray": "emd", "EMDConfig": "emd", "emd_coefficients": "emd", "emd_init": "emd", "emd_run": "emd",
    "emd_sine_response": "emd", "emd_sine_response_discrete": "emd", "emd_step": "emd",
    "Lattice": "lattice", "LatticeConfig": "lattice", "acceptance_attenuation": "lattice",
    "dphi_for_count": "lattice",
    "LIFConfig": "neurons", "LIFNeuron": "neurons", "PoissonConfig": "neurons", "PoissonNeuron": "neurons",
    "RateNeuron": "neurons", "RateNeuronConfig": "neurons", "lif_fi_curve": "neurons", "lif_step": "neurons",
    "lif_rate": "neurons", "lif_isi_cv": "neurons", "lif_current_for_rate": "neurons",
    "naka_rushton": "neurons", "poisson_spikes": "neurons", "rate_step": "neurons",
    "UNIT_TYPES": "lc_config", "Circuit": "circuit", "CircuitConfig": "circuit",
    "LCNeuronConfig": "lc_config", "LCNeurons": "population", "LCPopulation": "population",
    "LCPopulationConfig": "lc_config", "MatchedFilterConfig": "lc_config", "NormalisationConfig": "lc_config",
    "PathwayConfig": "lc_config", "ReceptiveFieldConfig": "lc_config",
    "ReadoutNeuronConfig": "readout_neuron", "readout_neuron": "readout_neuron",
    "spiking_output": "readout_neuron", "phase_advance": "readout_neuron",
    "PhotoreceptorConfig": "photoreceptor", "Photoreceptors": "photoreceptor", "photoreceptor_run": "photoreceptor",
    "photoreceptor_step": "photoreceptor",
    "CompoundEye": "compound_eye", "CompoundEyeConfig": "compound_eye", "acceptance_rule": "compound_eye",
    "EyeCircuit": "eye_circuit", "EyeCircuitConfig": "eye_circuit", "EyeFieldConfig": "eye_circuit",
    "natural_scene_gain": "eye_circuit",
    "GazeConfig": "gaze", "head_angles": "gaze", "head_rotation": "gaze", "retinal_rotation": "gaze",
    "fixation_reference": "gaze",
    "OnOffConfig": "motion_pathways", "lamina_on_off": "motion_pathways", "t4_t5": "motion_pathways",
    "cardinal_neighbours": "motion_pathways",
    "TangentialConfig": "tangential_cells", "hs_vs": "tangential_cells", "tangential_fields": "tangential_cells",
}
__all__ = ["__version__", "git_commit", *sorted(_API)]


# Lazy public API: importing the package stays light, so the command line starts fast.
__getattr__, __dir__ = lazy_api(__name__, _API, __all__)
