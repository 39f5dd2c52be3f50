"""The ommatidial lattice against known answers: geometry, the sampling operator, the optics."""

import numpy as np
import pytest
import torch

from lobula.camera import PinholeCamera, angles_to_normalised
from lobula.lattice import (Lattice, LatticeConfig, acceptance_attenuation, directions_to_plane,
                            dphi_for_count, plane_to_directions)
from stimuli.gratings import drifting_grating_frames, drifting_grating_lattice, drum_coordinates

CAM = PinholeCamera().scaled(0.5)          # 320×240, the D435i's 55°×42° field of view


@pytest.fixture(scope="module")
def fly_eye():
    return Lattice(CAM, LatticeConfig())   # hex, Δφ = Δρ = 4.6°


# ----------------------------------------------------------------------------- geometry

@pytest.mark.parametrize("projection", ["equidistant", "azel"])
def test_projection_round_trip(projection):
    rng = np.random.default_rng(0)
    q = rng.uniform(-0.8, 0.8, size=(200, 2))
    d = plane_to_directions(q, projection)
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    assert np.allclose(directions_to_plane(d, projection), q, atol=1e-12)


@pytest.mark.parametrize("camera", [PinholeCamera(), CAM], ids=["640x480", "320x240"])
@pytest.mark.parametrize("dphi", [4.6, 1.0])
def test_hex_neighbours_are_dphi_apart(camera, dphi):
    lat = Lattice(camera, LatticeConfig(kind="hex", dphi_deg=dphi))
    sep = np.degrees(lat.pair_separation) / dphi
    # Radial distances are exact in the equidistant projection; tangential ones shrink
    # by sin θ/θ, at most 5.5 % at the 33° corner of this camera.
    assert lat.n_axes == 3
    assert sep.max() <= 1.0 + 1e-9 and sep.min() >= 0.94
    assert abs(np.median(sep) - 1.0) < 0.01
    # Interior ommatidia have six neighbours (each pair counted at both ends).
    degree = np.bincount(np.concatenate([lat.pairs_a, lat.pairs_b]), minlength=lat.n)
    assert degree.max() == 6 and (degree == 6).mean() > 0.5


def test_axes_and_pairs(fly_eye):
    lat = fly_eye
    assert np.allclose(np.linalg.norm(lat.axis_vectors, axis=1), 1.0)
    assert np.allclose(np.degrees(np.arctan2(lat.axis_vectors[:, 1], lat.axis_vectors[:, 0])), [0, 60, 120])
    for k, (a, b) in enumerate(lat.axis_pairs):
        step = (lat.plane[b] - lat.plane[a]) / lat.dphi
        assert np.allclose(step, lat.axis_vectors[k], atol=1e-9)
    # Near the optical axis the image direction of each axis is the lattice direction.
    centre = np.linalg.norm(lat.pair_midpoint, axis=1) < 0.05
    for k in range(3):
        sel = centre & (lat.pair_axis == k)
        assert sel.any()
        assert np.allclose(lat.pair_direction[sel], lat.axis_vectors[k], atol=0.01)
    rect = Lattice(CAM, LatticeConfig(kind="rect"))
    assert rect.n_axes == 2
    assert np.allclose(np.degrees(rect.pair_separation), 4.6, rtol=0.06)


def test_angles_and_coordinates_agree(fly_eye):
    lat = fly_eye
    x, y = angles_to_normalised(lat.azimuth, lat.elevation)
    assert np.allclose(np.stack([x, y], -1), lat.normalised, atol=1e-12)
    assert np.allclose(lat.azimuth_deg, np.degrees(lat.azimuth))
    u, v = lat.pixel.T
    assert (u >= 0).all() and (u <= CAM.width - 1).all() and (v >= 0).all() and (v <= CAM.height - 1).all()
    on_axis = np.nonzero((lat.index == 0).all(axis=1))[0]
    assert len(on_axis) == 1 and np.allclose(lat.pixel[on_axis[0]], [CAM.cx, CAM.cy])
    # azel rows are lines of constant elevation, spaced Δφ in azimuth.
    azel = Lattice(CAM, LatticeConfig(projection="azel"))
    a, b = azel.axis_pairs[0]
    assert np.allclose(azel.elevation[a], azel.elevation[b])
    assert np.allclose(azel.azimuth[b] - azel.azimuth[a], azel.dphi)


def test_count_and_margin():
    dphi = dphi_for_count(CAM, 5000)
    lat = Lattice(CAM, LatticeConfig(dphi_deg=dphi))
    assert abs(lat.n - 5000) < 250
    wide = Lattice(CAM, LatticeConfig(margin=0.0))
    assert wide.n > Lattice(CAM, LatticeConfig()).n
    full = Lattice(CAM, LatticeConfig(margin=4.0 / 2.3548))
    assert full.unclipped.all()


def test_bad_input_is_refused(fly_eye):
    with pytest.raises(ValueError, match="kind"):
        LatticeConfig(kind="square")
    with pytest.raises(ValueError, match="dphi_deg"):
        LatticeConfig(dphi_deg=-1)
    with pytest.raises(ValueError, match="fits"):
        Lattice(CAM, LatticeConfig(dphi_deg=40.0))
    with pytest.raises(ValueError, match="shape"):
        fly_eye.sample(torch.zeros(10, 240, 321))


# ----------------------------------------------------------------------------- operator

@pytest.mark.parametrize("config", [LatticeConfig(), LatticeConfig(kind="rect", projection="azel", dphi_deg=2.0)],
                         ids=["hex", "rect-azel"])
def test_rows_sum_to_one_and_constant_frames_pass(config):
    lat = Lattice(CAM, config)
    op = lat.operator
    assert op.layout == torch.sparse_csr and tuple(op.shape) == (lat.n, CAM.width * CAM.height)
    rows = torch.segment_reduce(op.values(), "sum", offsets=op.crow_indices())
    assert torch.allclose(rows, torch.ones(lat.n), atol=1e-5)
    assert (op.values() > 0).all()
    const = torch.full((2, 3, CAM.height, CAM.width), 7.25, dtype=torch.float64)
    out = lat.sample(const)
    assert out.shape == (2, 3, lat.n) and out.dtype == torch.float64
    assert torch.allclose(out, torch.full_like(out, 7.25), rtol=1e-12)
    img = np.full((CAM.height, CAM.width), 200, dtype=np.uint8)   # integer images work too
    assert torch.allclose(lat.sample(img), torch.full((lat.n,), 200.0), rtol=1e-5)


def test_sampling_is_batched_and_linear(fly_eye):
    g = torch.Generator().manual_seed(0)
    frames = torch.rand(20, CAM.height, CAM.width, generator=g)
    single = torch.stack([fly_eye.sample(f) for f in frames])
    batched = fly_eye.sample(frames)
    assert torch.allclose(single, batched, atol=1e-5)
    dense = frames.reshape(20, -1).double() @ fly_eye.operator_on("cpu", torch.float64).to_dense().T
    assert torch.allclose(batched.double(), dense, atol=1e-5)


# ----------------------------------------------------------------------------- optics

@pytest.mark.parametrize("drho", [4.6, 2.0])
def test_grating_amplitude_follows_gaussian_transfer(drho):
    """Camera-rendered gratings through the optics fall off as exp(−(πΔρ/λ)²/(4 ln 2)).

    A drum grating's local wavelength at latitude β is λ·cos β; amplitude per ommatidium
    from four frames a quarter period apart. Ommatidia whose acceptance function is
    clipped by the image border are left out (``unclipped``).
    """
    lat = Lattice(CAM, LatticeConfig(dphi_deg=drho, drho_deg=drho))
    u = lat.unclipped
    assert u.sum() >= 50
    tf = CAM.frame_rate_hz / 4          # four frames = one period
    for direction in (0.0, 60.0):
        for ratio in (1.7, 2.5, 4.0, 10.0):     # λ/Δρ: M from 0.18 to 0.98
            lam = ratio * drho
            frames = drifting_grating_frames(CAM, 4, wavelength_deg=lam, temporal_freq_hz=tf, direction_deg=direction,
                                             contrast=1.0, mean_luminance=1.0, dtype=torch.float64)
            s = lat.sample(frames).numpy()[:, u] - 1.0
            amp = 0.5 * np.hypot(s[0] - s[2], s[1] - s[3])
            _, beta = drum_coordinates(lat.directions[u], direction)
            expected = acceptance_attenuation(lam * np.cos(beta), drho)
            assert np.allclose(amp, expected, rtol=0.01), (direction, lam, np.abs(amp / expected - 1).max())
            # The analytic shortcut on the lattice agrees with the optics frame by frame.
            direct = drifting_grating_lattice(lat, 4, wavelength_deg=lam, temporal_freq_hz=tf, direction_deg=direction,
                                              contrast=1.0, acceptance=True, dtype=torch.float64).numpy()[:, u] - 1.0
            assert np.abs(direct - s).max() < 0.005


def test_square_grating_through_optics_matches_analytic_blur(fly_eye):
    u = fly_eye.unclipped
    kw = dict(wavelength_deg=15.0, temporal_freq_hz=3.0, direction_deg=30.0, contrast=0.8, waveform="square")
    frames = drifting_grating_frames(CAM, 3, supersample=4, **kw)
    s = fly_eye.sample(frames)[:, u]
    direct = drifting_grating_lattice(fly_eye, 3, acceptance=True, **kw)[:, u]
    assert (s - direct).abs().max() < 0.01
