"""LC populations and the lattice stimulus library against known answers.

Small eyes (Δφ = 2°, ~550 ommatidia) and short runs: the file takes ~20 s on two shared
CPU cores. Known answers: the circuit's EMD stage is lobula.emd's correlator; pathways
are exact for ramps and constants; push–pull pairs carry the sign of r for exact flow
fields; stimuli have their stated geometry.
"""
import math

import numpy as np
import pytest
import torch

from lobula.camera import PinholeCamera, angles_to_normalised
from lobula.circuit import Circuit, CircuitConfig
from lobula.emd import EMDState, emd_run
from lobula.lattice import Lattice, LatticeConfig
from lobula.population import (LCNeuronConfig, LCPopulation, LCPopulationConfig, MatchedFilterConfig,
                               NormalisationConfig, PopulationState, ReceptiveFieldConfig, config_from_dict,
                               pair_templates)
from stimuli.gratings import drifting_grating_lattice
from stimuli.lattice_stimuli import (GratingSource, dot_field, looming_angular_size, looming_disc, moving_edge,
                                     moving_spot, noise_panorama, radial_grating, sparse_noise)

CAM = PinholeCamera(frame_rate_hz=1000.0).scaled(0.5)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # Per-step tensors are small; a second OpenMP thread on a busy shared core is 5–10× slower.
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def eye():
    return Lattice(CAM, LatticeConfig(dphi_deg=2.0))


# --------------------------------------------------------------------------- the circuit's EMD stage

@pytest.mark.parametrize("kind", ["hex", "rect"])
def test_grid_correlator_equals_lobula_emd(kind):
    lat = Lattice(CAM, LatticeConfig(kind=kind, dphi_deg=3.0))
    circ = Circuit(lat, CircuitConfig(chunk_steps=7))
    rng = np.random.default_rng(0)
    stim = torch.as_tensor(1.0 + 0.3 * rng.standard_normal((2, 40, lat.n)), dtype=torch.float64)
    rec = circ.run(stim, record=("photoreceptor.v", "emd.response"), baseline=1.0)
    y = rec["photoreceptor.v"]
    rest = EMDState(torch.zeros(2, lat.n, dtype=torch.float64), torch.zeros(2, lat.n, dtype=torch.float64))
    R, _ = emd_run(circ.config.emd, circ.config.dt_s, y, lat.pairs_a, lat.pairs_b, state=rest)
    torch.testing.assert_close(rec["emd.response"], R, rtol=1e-9, atol=1e-12)


def test_chunking_does_not_change_results(eye):
    stim, _ = radial_grating(eye, 90, temporal_freq_hz=4.0, frame_rate_hz=1000, dtype=torch.float64)
    outs = [Circuit(eye, CircuitConfig(chunk_steps=c)).run(stim, record=("lc.r", "lc.r2", "lc.rdot", "lc.rate"))
            for c in (1, 16, 90)]
    for o in outs[1:]:
        for k in o:
            torch.testing.assert_close(o[k], outs[0][k], rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------------- geometry and pathways

def test_templates_point_along_expansion(eye):
    mu, t = pair_templates(eye, (0.0, 0.0), "direction")
    assert np.all(mu * t >= -1e-12)
    assert np.all(np.abs(mu) <= 1 + 1e-12)
    # A pair pointing away from the epipole has μ ≈ +1 and t ≈ eccentricity / step.
    mid = eye.pair_midpoint
    out = np.einsum("pk,pk->p", eye.pair_direction, mid / np.linalg.norm(mid, axis=1, keepdims=True))
    radial = out > 0.999
    assert radial.any() and np.all(mu[radial] > 0.99)
    step = np.linalg.norm(eye.normalised[eye.pairs_b] - eye.normalised[eye.pairs_a], axis=1)
    np.testing.assert_allclose(t[radial], np.linalg.norm(mid[radial], axis=1) / step[radial], rtol=0.02)
    mu_f, t_f = pair_templates(eye, (0.0, 0.0), "flow")
    np.testing.assert_array_equal(mu_f, t_f)


def test_pathways_are_exact_for_constant_and_ramping_r(eye):
    # Drive the field stage with subunit signals of an exact expansion r(t): num_s = r·D_s.
    pop = LCPopulation(eye, LCPopulationConfig(normalisation=NormalisationConfig(floor=0.0)))
    S = pop.n_subunits
    D = torch.as_tensor(pop.kappa * pop.static_s, dtype=torch.float64).expand(1, S)
    dt, T = 1e-3, 3000
    t = torch.arange(T, dtype=torch.float64) * dt
    slope = 0.4
    r = 0.5 + slope * t                                                   # 1/s, a ramp
    num = r[:, None, None] * D[None]
    state = PopulationState(D.clone(), num[0].clone(), r[0].expand(1, pop.n_fields).clone(),
                            (r[0] - slope * 0.2).expand(1, pop.n_fields).clone())
    out, _ = pop.advance(num, D.expand(T, 1, S), state, dt, {"lc.r", "lc.r2", "lc.rdot"})
    torch.testing.assert_close(out["lc.r"][:, 0], r[:, None].expand(T, pop.n_fields), rtol=1e-12, atol=1e-12)
    late = slice(2000, None)                                              # after ~10 slow time constants
    torch.testing.assert_close(out["lc.rdot"][late], torch.full_like(out["lc.rdot"][late], slope), rtol=1e-6,
                               atol=1e-6)
    # r²̄ of a uniform r is r², up to the local low-pass's lag of the ramp (≈ slope·τ_local).
    lagged = r - slope * pop.config.pathways.tau_local_s
    torch.testing.assert_close(out["lc.r2"][late, 0], (lagged[late, None] ** 2).expand(-1, pop.n_fields),
                               rtol=2e-3, atol=0)


def test_decode_rates_inverts_push_pull_units(eye):
    pop = LCPopulation(eye, LCPopulationConfig())
    F = pop.n_fields
    r_true = torch.linspace(-3, 3, F, dtype=torch.float64)
    drive = {"r": r_true, "r2": r_true ** 2, "rdot": -r_true}
    nc, rc = pop.config.neurons, pop.config.neurons.rate
    from lobula.neurons import naka_rushton
    units = []
    for typ in pop.types:
        sig, sgn = {"expansion": ("r", 1), "contraction": ("r", -1), "r2": ("r2", 1), "rdot+": ("rdot", 1),
                    "rdot-": ("rdot", -1)}[typ]
        scale = {"r": nc.scale_r, "r2": nc.scale_r2, "rdot": nc.scale_rdot}[sig]
        units.append(naka_rushton(sgn * drive[sig] / scale, rc.r_max, rc.c50, rc.n))
    dec = pop.decode_rates(torch.cat(units))
    for k in ("r", "r2", "rdot"):
        torch.testing.assert_close(dec[k], drive[k], rtol=1e-5, atol=1e-5)


def test_bad_configurations_say_what_is_wrong(eye):
    with pytest.raises(ValueError, match="template"):
        MatchedFilterConfig(template="radial")
    with pytest.raises(ValueError, match="model"):
        LCNeuronConfig(model="hodgkin-huxley")
    with pytest.raises(ValueError, match="no EMD pair"):
        LCPopulation(eye, LCPopulationConfig(fields=ReceptiveFieldConfig(size_deg=5, centres_deg=((80.0, 0.0),))))
    with pytest.raises(ValueError, match="cannot record"):
        Circuit(eye).run(torch.ones(5, eye.n), record=("lc.v",))          # rate units have no membrane
    cfg = CircuitConfig(population=LCPopulationConfig(fields=ReceptiveFieldConfig(centres_deg=[[1, 2]])))
    assert config_from_dict(CircuitConfig, cfg.to_dict()) == cfg


# --------------------------------------------------------------------------- push–pull on exact flow

@pytest.mark.parametrize("r", [1.0, -1.0])
def test_push_pull_pair_signals_expansion_vs_contraction(eye, r):
    stim, info = dot_field(eye, 800, r_per_s=r, n_dots=150, seed=3, frame_rate_hz=1000)
    circ = Circuit(eye, CircuitConfig())
    out = circ.run(stim, record=("lc.r", "lc.rate"), baseline=1.0)
    F = circ.population.n_fields
    rate = out["lc.rate"][0, 0, 300:].mean(0)
    diff = (rate[circ.population.units_of("expansion")] - rate[circ.population.units_of("contraction")]).numpy()
    assert np.all(np.sign(diff) == np.sign(r)), diff
    # The gradient-ratio decoding gives r itself, underestimated by the EMD's 1/(1+(ωτ)²).
    r_hat = np.median(out["lc.r"][0, 300:].mean(0).numpy())
    assert 0.4 < r_hat / r < 1.2, r_hat
    assert F == len(diff)


# --------------------------------------------------------------------------- stimuli

def test_grating_source_equals_drifting_grating(eye):
    tf = np.array([1.0, 7.0])
    ref = drifting_grating_lattice(eye, 50, temporal_freq_hz=tf, wavelength_deg=15.0, contrast=0.4,
                                   direction_deg=30.0, acceptance=True, frame_rate_hz=1000, dtype=torch.float64)
    src = GratingSource(eye, temporal_freq_hz=tf, wavelength_deg=15.0, contrast=0.4, direction_deg=30.0,
                        frame_rate_hz=1000, dtype=torch.float64)
    torch.testing.assert_close(src(0, 50), ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(src(20, 30), ref[:, 20:30], rtol=1e-12, atol=1e-12)


def test_looming_disc_has_the_exact_angular_size(eye):
    lv, n = 0.04, 500
    lum, info = looming_disc(eye, n, l_over_v_s=lv, frame_rate_hz=1000, acceptance=False, max_size_deg=180)
    t = np.arange(n) / 1000.0
    expect = np.degrees(2 * np.arctan(lv / (t[-1] - t[:-1])))
    np.testing.assert_allclose(info["angular_size_deg"][:-1], expect, rtol=1e-12)
    assert looming_angular_size(1.0, lv, 1.0) == 180.0
    # Without optics an ommatidium is dark exactly when it lies inside the disc.
    c = np.array([0.0, 0.0, 1.0])
    delta = np.degrees(np.arccos(np.clip(eye.directions @ c, -1, 1)))
    k = 400
    inside = delta < info["angular_size_deg"][k] / 2
    np.testing.assert_array_equal(lum[k].numpy() < 0.5, inside)
    rec, info_r = looming_disc(eye, n, l_over_v_s=lv, frame_rate_hz=1000, receding=True, max_size_deg=180,
                               acceptance=False)
    np.testing.assert_array_equal(info_r["angular_size_deg"], info["angular_size_deg"][::-1])
    assert torch.equal(rec, lum.flip(0))


def test_edge_and_spot_are_where_they_are_said_to_be(eye):
    lum, info = moving_edge(eye, 200, polarity="on", speed_deg_s=100.0, start_deg=-20.0, frame_rate_hz=1000,
                            acceptance=False)
    k = 150
    pos = info["edge_position_deg"][k]
    assert pos == pytest.approx(-20.0 + 100.0 * 0.15)
    psi = np.degrees(np.arctan2(eye.directions[:, 0], eye.directions[:, 2]))
    np.testing.assert_array_equal(lum[k].numpy() > 1.0, psi < pos)          # behind an ON edge: bright
    lum, info = moving_spot(eye, 101, centre_deg=(10.0, -5.0), direction_deg=90.0, speed_deg_s=50.0,
                            frame_rate_hz=1000)
    np.testing.assert_allclose(info["spot_centre_deg"][50], [10.0, -5.0], atol=1e-9)
    assert info["spot_centre_deg"][100][1] > -5.0                           # 90° = downward: elevation grows
    brightest = int(torch.argmax(lum[50]))
    assert math.hypot(eye.azimuth_deg[brightest] - 10.0, eye.elevation_deg[brightest] + 5.0) < 2.0


def test_dot_field_moves_exactly_as_expansion(eye):
    r = 0.8
    _, info = dot_field(eye, 20, r_per_s=r, lifetime_s=10.0, seed=0, frame_rate_hz=1000, epipole_deg=(5.0, 0.0))
    xy = info["dot_xy"]
    e = np.array(angles_to_normalised(math.radians(5.0), 0.0))
    ratio = (xy[-1] - e) / (xy[0] - e)
    np.testing.assert_allclose(ratio, math.exp(r * 19e-3), rtol=1e-9)


def test_random_stimuli_are_seeded(eye):
    a, ia = sparse_noise(eye, 200, seed=4, frame_rate_hz=1000)
    b, _ = sparse_noise(eye, 200, seed=4, frame_rate_hz=1000)
    c, _ = sparse_noise(eye, 200, seed=5, frame_rate_hz=1000)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert len(ia["onset_s"]) == 4
    p1, _ = noise_panorama(eye, 3, seed=1, yaw_speed_deg_s=30.0, frame_rate_hz=100)
    p2, _ = noise_panorama(eye, 3, seed=1, yaw_speed_deg_s=30.0, frame_rate_hz=100)
    assert torch.equal(p1, p2) and p1.shape == (3, eye.n)
    assert 0.05 < float(p1[0].std()) < 0.5 and not torch.equal(p1[0], p1[2])


def test_noise_panorama_wraps_the_drum_at_every_time():
    """The rotating panorama samples its drum modulo 360° at any time and any ommatidium. A float's
    modulo can round up to the drum's length itself (−1e-17 % 288 == 288.0): at 10°/s on the fly's
    eye (seed 0, 500 Hz) that indexed past the texture. And one full turn later the image is the same."""
    from experiments.ephys.eye_rig import EyeLattice
    from lobula.compound_eye import CompoundEye

    fly = EyeLattice(CompoundEye(), 500.0)
    lum, _ = noise_panorama(fly, 750, yaw_speed_deg_s=10.0, seed=0, frame_rate_hz=500.0)
    assert lum.shape == (750, fly.n) and bool(torch.isfinite(lum).all())
    turned, _ = noise_panorama(fly, 1, yaw_speed_deg_s=10.0, seed=0, frame_rate_hz=500.0, t0_s=36.0)
    torch.testing.assert_close(turned[0], lum[0], rtol=0, atol=1e-4)


@pytest.mark.slow
def test_compiled_kernel_matches_eager(eye):
    # torch.compile takes ~30 s cold on two cores: a slow test (pytest -m slow).
    stim, _ = radial_grating(eye, 48, temporal_freq_hz=[3.0, 9.0], frame_rate_hz=1000)
    rec = ("lc.input", "lc.r", "lc.r2", "emd.response")
    a = Circuit(eye, CircuitConfig(chunk_steps=16)).run(stim, record=rec)
    b = Circuit(eye, CircuitConfig(chunk_steps=16, compile=True)).run(stim, record=rec)
    for k in rec:
        torch.testing.assert_close(b[k], a[k], rtol=1e-4, atol=1e-6 * float(a[k].abs().max()))


@pytest.mark.parametrize("kind", ["hex", "rect"])
def test_pool_pairs_equals_plain_sums(kind):
    # The CSR product on pair-major R and the run-sliced differences of y against a plain
    # per-pair index_add in float64, for R contiguous and as emd_run's pair-major view.
    lat = Lattice(CAM, LatticeConfig(kind=kind, dphi_deg=3.0))
    pop = LCPopulation(lat, LCPopulationConfig())
    rng = np.random.default_rng(1)
    y = torch.as_tensor(rng.standard_normal((3, 5, lat.n)), dtype=torch.float32)
    R = torch.as_tensor(rng.standard_normal((3, 5, lat.n_pairs)), dtype=torch.float32)
    sub = torch.as_tensor(pop.pair_subunit)
    mu, den = torch.as_tensor(pop.mu), torch.as_tensor(pop.kappa * pop.mu * pop.t)
    G = (y.double()[..., lat.pairs_b] - y.double()[..., lat.pairs_a]) ** 2
    ref_num = torch.zeros(3, 5, pop.n_subunits, dtype=torch.float64).index_add_(-1, sub, R.double() * mu)
    ref_den = torch.zeros(3, 5, pop.n_subunits, dtype=torch.float64).index_add_(-1, sub, G * den)
    pair_major = R.permute(2, 1, 0).contiguous().permute(2, 1, 0)        # (P, T, B) storage, as emd_run returns
    for r in (R, pair_major):
        num, dsum = pop.pool_pairs(r, y)
        assert num.shape == dsum.shape == (3, 5, pop.n_subunits)
        torch.testing.assert_close(num.double(), ref_num, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(dsum.double(), ref_den, rtol=1e-5, atol=1e-5)
    assert pop.pool_pairs(R[0, 0], None)[1] is None
    torch.testing.assert_close(pop.pool_pairs(R[0, 0], None)[0].double(), ref_num[0, 0], rtol=1e-5, atol=1e-5)
