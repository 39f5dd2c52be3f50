"""stimuli: synthetic worlds with exact truth and their writers (the readers of footage are :mod:`lobula.readers`)."""
from __future__ import annotations

from lobula._lazy import lazy_api

#: public name -> the module of this package that defines it (imported on first use)
_API = {
    "write_footage": "footage_writer",
    "IMUConfig": "imu", "synthesize_imu": "imu",
    "SceneConfig": "worlds", "TrackScene": "scene", "band_limited_texture": "worlds",
    "Trajectory": "trajectory", "read_velocity_profile": "trajectory", "trajectory_from_function": "trajectory",
    "trajectory_from_profile": "trajectory",
    "GratingConfig": "gratings", "drifting_grating_frames": "gratings", "drifting_grating_lattice": "gratings",
    "TrackRunConfig": "track", "build_track": "track", "builtin_profile": "track", "make_track_run": "track",
    "GratingSource": "lattice_stimuli", "dot_field": "lattice_stimuli", "drifting_grating": "lattice_stimuli",
    "looming_angular_size": "lattice_stimuli", "looming_disc": "lattice_stimuli", "moving_edge": "lattice_stimuli",
    "moving_spot": "lattice_stimuli", "noise_panorama": "lattice_stimuli", "radial_grating": "lattice_stimuli",
    "sparse_noise": "lattice_stimuli",
    "EyeFootage": "eye", "open_eye_footage": "eye", "write_eye_footage": "eye", "make_eye_run": "eye",
    "render_eye": "eye",
}
__all__ = sorted(_API)


# Lazy public API: importing the package stays light, so the command line starts fast.
__getattr__, __dir__ = lazy_api(__name__, _API, __all__)
