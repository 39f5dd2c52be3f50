"""lobula: a model of the fly's lobula that estimates absolute velocity from vision plus acceleration."""
from .version import __version__, git_commit

from .camera import PinholeCamera, angles_to_normalised, normalised_to_angles
from .config import VelocityConfig
from .epipole import EpipoleEstimator, derotate, rotational_flow
from .flow import FlowConfig, FlowSample, StaggeredFlow, pixel_to_angular
from .haltere import forward_acceleration, resample_to
from .readout import ReadoutConfig, ReadoutResult, readout
from .receptive_field import FieldConfig, ReceptiveFields, gap_correction, pool_fields, tile_fields
from .depth import DepthConfig, DepthResult, depth_metrics, depth_parallax, depth_ratio, depth_tv
from .emd_decoding import EMDFrontEnd, EMDFrontEndConfig, fit_calibration, pair_pooling_weights
from .emd import (EMDArray, EMDConfig, emd_coefficients, emd_init, emd_run, emd_sine_response,
                  emd_sine_response_discrete, emd_step)
from .lattice import Lattice, LatticeConfig, acceptance_attenuation, dphi_for_count
from .neurons import (LIFConfig, LIFNeuron, PoissonConfig, PoissonNeuron, RateNeuron, RateNeuronConfig,
                      lif_fi_curve, lif_step, naka_rushton, poisson_spikes, rate_step)
from .population import (UNIT_TYPES, LCNeuronConfig, LCNeurons, LCPopulation,
                         LCPopulationConfig, MatchedFilterConfig, NormalisationConfig, PathwayConfig,
                         ReceptiveFieldConfig)
from .circuit import Circuit, CircuitConfig
from .readout_neuron import ReadoutNeuronConfig, readout_neuron
from .photoreceptor import PhotoreceptorConfig, Photoreceptors, photoreceptor_run, photoreceptor_step
