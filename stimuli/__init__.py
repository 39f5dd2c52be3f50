"""stimuli: everything that makes or reads input — synthetic scenes with exact truth, footage readers."""
from .footage_core import IMU, Footage, FootageError, frame_gaps, read_frame
from .footage import (FloUnits, acceleration_from_truth, flo_to_normalised, footage_provenance,
                      open_footage, read_flo, read_imu_csv, write_footage)
from .imu import IMUConfig, synthesize_imu
from .scene import SceneConfig, TrackScene, band_limited_texture
from .trajectory import Trajectory, read_velocity_profile, trajectory_from_function, trajectory_from_profile
from .gratings import GratingConfig, drifting_grating_frames, drifting_grating_lattice
from .track import TrackRunConfig, build_track, builtin_profile, make_track_run
from .lattice_stimuli import (GratingSource, dot_field, drifting_grating, looming_angular_size, looming_disc,
                              moving_edge, moving_spot, noise_panorama, radial_grating, sparse_noise)
from .realsense_bag import BagFootage, open_realsense_bag
