"""ON/OFF motion pathways (lamina → T4/T5) and the HS/VS tangential cells, against known answers.

Known answers:
- A moving ON edge (dark → bright) only brightens each ommatidium: the photoreceptor's low-pass
  output rises monotonically and a first-order high-pass of a rising signal is ≥ 0, so the OFF
  channel (and T5) stays exactly 0, and vice versa for an OFF edge.
- A half-correlator ``LP_τ(c_A)·c_B`` of the rectified channels of a sine grating has a mean of
  (DC)² + ½a²·|H|·cos(θ − Δϕ), |H| = 1/√(1+(ωτ)²), θ = atan ωτ: its direction-dependent part
  ½a²·ωτ/(1+(ωτ)²)·sin Δϕ peaks at TF = 1/(2πτ) when Δϕ = 90° (λ = 4Δφ), and the rectified
  sine's DC (a/π against a fundamental a/2) caps the DSI of a pure half-correlator near 0.6–0.7.
- The tangential cells' steady state is V∞ = (E_exc·g_e + E_inh·g_i)/(1 + g_e + g_i), reached with
  the time constant τ_m/(1 + g_e + g_i); its conductances grow with the number of columns a
  pattern covers, so the potential saturates with pattern size.
"""
import math

import numpy as np
import pytest
import torch

import lobula
from lobula.camera import PinholeCamera
from lobula.lattice import Lattice, LatticeConfig
from lobula.motion_pathways import DIRECTIONS, OnOffConfig, cardinal_neighbours, lamina_on_off, t4_t5
from lobula.photoreceptor import PhotoreceptorConfig, photoreceptor_run
from lobula.tangential_cells import TangentialConfig, hs_vs, shunting_potential, tangential_fields
from stimuli.lattice_stimuli import drifting_grating, moving_edge

CAM = PinholeCamera().scaled(0.5)
DPHI = 4.6
FPS = 200.0                       # frames/s: a 4.5 Hz grating and its 9 Hz product term far below Nyquist
DT = 1.0 / FPS
#: image direction (deg; 0 right, 90 down) of each T4/T5 direction for a right eye
IMAGE_DEG = {"front_to_back": 0.0, "back_to_front": 180.0, "upward": 270.0, "downward": 90.0}
OPPOSITE = {"front_to_back": "back_to_front", "back_to_front": "front_to_back", "upward": "downward",
            "downward": "upward"}


@pytest.fixture(scope="module")
def lat():
    return Lattice(CAM, LatticeConfig(dphi_deg=DPHI))


def _pathways(lat, lum, config=OnOffConfig(), fps=FPS):
    x, _ = photoreceptor_run(PhotoreceptorConfig(), 1.0 / fps, lum)
    ch = lamina_on_off(x, 1.0 / fps, config)
    return ch, t4_t5(ch.on, ch.off, lat, config, 1.0 / fps)


def test_public_names():
    """The new public names resolve through the package's lazy table."""
    for name in ("OnOffConfig", "lamina_on_off", "t4_t5", "cardinal_neighbours", "TangentialConfig", "hs_vs",
                 "tangential_fields"):
        assert callable(getattr(lobula, name))
    assert OnOffConfig().to_dict()["tau_delay_t4_s"] == 0.035 and TangentialConfig().to_dict()["n_hs"] == 3


def test_cardinal_neighbours_geometry(lat):
    """Front-to-back is one Δφ step rightward (right eye), leftward for a left eye; vertical directions use
    the two oblique hexagonal neighbours, ±Δφ/2 across and √3/2·Δφ up or down."""
    for eye, sign in (("right", 1.0), ("left", -1.0)):
        nbr = cardinal_neighbours(lat, eye)
        assert nbr.shape == (4, lat.n, 2)
        for d, name in enumerate(DIRECTIONS):
            a, j = np.nonzero(nbr[d] >= 0)
            step = (lat.plane[nbr[d][a, j]] - lat.plane[a]) / math.radians(DPHI)
            assert len(a) > lat.n // 2
            if name in ("front_to_back", "back_to_front"):
                want = sign if name == "front_to_back" else -sign
                np.testing.assert_allclose(step, np.tile([want, 0.0], (len(a), 1)), atol=1e-9)
                assert (nbr[d][:, 1] == -1).all()
            else:
                down = 1.0 if name == "downward" else -1.0
                np.testing.assert_allclose(step[:, 1], down * math.sqrt(3) / 2, atol=1e-9)
                np.testing.assert_allclose(np.abs(step[:, 0]), 0.5, atol=1e-9)
                # the two slots hold the two oblique steps, one to each side
                both = (nbr[d] >= 0).all(1)
                s0 = lat.plane[nbr[d][both, 0], 0] - lat.plane[both, 0]
                s1 = lat.plane[nbr[d][both, 1], 0] - lat.plane[both, 0]
                assert both.sum() > lat.n // 2 and (np.sign(s0) == -np.sign(s1)).all()


@pytest.mark.parametrize("polarity", ["on", "off"])
def test_edge_polarity_selects_t4_or_t5(lat, polarity):
    """An ON edge drives T4 and not T5; an OFF edge T5 and not T4 (ratio > 10; the wrong pathway is silent)."""
    lum, _ = moving_edge(lat, int(1.5 * FPS), polarity=polarity, direction_deg=0.0, speed_deg_s=50.0, contrast=0.5,
                         frame_rate_hz=FPS)
    ch, out = _pathways(lat, lum)
    t4, t5 = float(out.t4.double().mean()), float(out.t5.double().mean())
    right, wrong = (t4, t5) if polarity == "on" else (t5, t4)
    print(f"\n{polarity} edge: mean T4 {t4:.3e}, mean T5 {t5:.3e}")
    assert right > 1e-3                                        # (0.5 contrast, unit mean luminance: ≈ 0.05)
    assert right > 10.0 * wrong
    assert float((ch.off if polarity == "on" else ch.on).max()) == 0.0


@pytest.fixture(scope="module")
def grating_layers(lat):
    """Mean T4 and T5 (K = 4 grating directions, 4 layers) for a 15° sine grating at 4.5 Hz (≈ 1/(2πτ))."""
    dirs = [IMAGE_DEG[d] for d in DIRECTIONS]
    lum, _ = drifting_grating(lat, int(2.0 * FPS), frame_rate_hz=FPS, direction_deg=dirs, wavelength_deg=15.0,
                              temporal_freq_hz=4.5, contrast=0.5)
    _, out = _pathways(lat, lum)
    settle = int(1.0 * FPS)
    return (out.t4[:, settle:].double().mean((1, 2)).numpy(), out.t5[:, settle:].double().mean((1, 2)).numpy())


@pytest.mark.parametrize("cell", ["t4", "t5"])
def test_direction_selectivity(grating_layers, cell):
    """Each direction's layer prefers its own direction: DSI = (P − N)/(P + N) > 0.5, P and N the layer's mean
    response to the grating moving in its preferred and in the opposite direction."""
    m = grating_layers[0 if cell == "t4" else 1]               # (grating direction, layer)
    for d, name in enumerate(DIRECTIONS):
        P, N = m[d, d], m[DIRECTIONS.index(OPPOSITE[name]), d]
        dsi = (P - N) / (P + N)
        print(f"\n{cell} {name}: P {P:.4f} N {N:.4f} DSI {dsi:.3f}")
        assert dsi > 0.5
        assert (m[:, d] >= 0).all()


def test_temporal_frequency_optimum(lat):
    """The mean preferred-direction T4 response vs TF (λ = 4Δφ, so Δϕ = 90°) peaks within a factor 2 of
    1/(2πτ), for two delay time constants."""
    fps = 400.0
    tf = np.geomspace(0.5, 32.0, 25)
    for tau in (0.035, 0.07):
        cfg = OnOffConfig(tau_delay_t4_s=tau)
        lum, _ = drifting_grating(lat, int(4.0 * fps), frame_rate_hz=fps, direction_deg=0.0, wavelength_deg=4 * DPHI,
                                  temporal_freq_hz=tf, contrast=0.5)
        _, out = _pathways(lat, lum, cfg, fps)
        P = out.t4[:, int(2.0 * fps):, :, DIRECTIONS.index("front_to_back")].double().mean((1, 2)).numpy()
        k = int(np.argmax(P))
        assert 0 < k < len(tf) - 1                             # an interior maximum, not the sweep's end
        # parabola through the peak and its neighbours in log TF
        y0, y1, y2 = P[k - 1], P[k], P[k + 1]
        step = math.log(tf[1] / tf[0])
        peak = tf[k] * math.exp(0.5 * step * (y0 - y2) / (y0 - 2 * y1 + y2))
        expected = 1.0 / (2 * math.pi * tau)
        print(f"\nτ = {tau * 1e3:.0f} ms: T4 optimum {peak:.2f} Hz, 1/(2πτ) = {expected:.2f} Hz")
        assert expected / 2 < peak < 2 * expected
        assert P[k] > 1.5 * P[0] and P[k] > 1.5 * P[-1]       # a tuned peak, not a plateau


def test_shunting_membrane_known_answer(lat):
    """Constant inputs: V settles to (E_exc·g_e + E_inh·g_i)/(1 + g_e + g_i) with the time constant
    τ_m/(1 + g_e + g_i), starting from the first frame's steady state."""
    cfg = TangentialConfig(n_hs=1, n_vs=1, tau_m_s=0.01, g_exc=3.0, g_inh=2.0)
    T, dt = 40, 1e-3
    t4 = torch.zeros(T, lat.n, 4, dtype=torch.float64)
    t5 = torch.zeros_like(t4)
    t4[10:, :, DIRECTIONS.index("front_to_back")] = 1.0      # the whole field: g_e = 3 after frame 10
    t5[10:, :, DIRECTIONS.index("back_to_front")] = 0.5      # g_i = 2 · 0.5 = 1
    v = hs_vs(t4, t5, lat, cfg, dt).hs[:, 0].numpy()
    v_inf = shunting_potential(3.0, 1.0, cfg.e_exc_mv, cfg.e_inh_mv)
    assert v_inf == pytest.approx((50 * 3 - 30 * 1) / 5.0)
    np.testing.assert_allclose(v[:10], 0.0, atol=1e-12)
    k = np.arange(1, T - 9)
    np.testing.assert_allclose(v[10:], v_inf * (1 - np.exp(-k * dt * 5.0 / cfg.tau_m_s)), rtol=1e-9)


def test_tangential_fields_partition(lat):
    """Every ommatidium lies in exactly one HS band and one VS stripe; HSN is dorsal, HSS ventral."""
    w_hs, w_vs = tangential_fields(lat)
    assert w_hs.shape == (3, lat.n) and w_vs.shape == (6, lat.n)
    np.testing.assert_array_equal(w_hs.sum(0), 1.0)
    np.testing.assert_array_equal(w_vs.sum(0), 1.0)
    el = [lat.elevation[w > 0].mean() for w in w_hs]
    az = [lat.azimuth[w > 0].mean() for w in w_vs]
    assert np.all(np.diff(el) > 0) and np.all(np.diff(az) > 0)


@pytest.mark.parametrize("eye", ["right", "left"])
def test_hs_vs_signs(lat, eye):
    """HS cells depolarise for front-to-back and hyperpolarise for back-to-front motion; VS cells for downward
    and upward. Front-to-back is rightward in the image for a right eye, leftward for a left one."""
    cfg = OnOffConfig(eye=eye)
    ftb = 0.0 if eye == "right" else 180.0
    dirs = [ftb, ftb + 180.0, 90.0, 270.0]                    # front-to-back, back-to-front, down, up
    lum, _ = drifting_grating(lat, int(2.0 * FPS), frame_rate_hz=FPS, direction_deg=dirs, wavelength_deg=15.0,
                              temporal_freq_hz=4.5, contrast=0.5)
    _, out = _pathways(lat, lum, cfg)
    cells = hs_vs(out.t4, out.t5, lat, TangentialConfig(), DT)
    hs = cells.hs[:, int(FPS):].double().mean(1).numpy()        # (grating, HS cell) mV
    vs = cells.vs[:, int(FPS):].double().mean(1).numpy()
    print(f"\n{eye} eye HS (mV) front-to-back {hs[0].round(1)}, back-to-front {hs[1].round(1)}; "
          f"VS downward {vs[2].round(1)}, upward {vs[3].round(1)}")
    assert (hs[0] > 5.0).all() and (hs[1] < -5.0).all()
    assert (vs[2] > 5.0).all() and (vs[3] < -5.0).all()


def test_hs_gain_control_with_pattern_size(lat):
    """One HS cell over the whole eye: a grating over the whole field gives more than over half of it but less
    than twice as much (the shunting term saturates); with conductances 100× weaker (linear regime) the same
    stimuli give about twice as much, so the saturation is the gain control's."""
    lum, _ = drifting_grating(lat, int(2.0 * FPS), frame_rate_hz=FPS, direction_deg=0.0, wavelength_deg=15.0,
                              temporal_freq_hz=4.5, contrast=0.5)
    # half the field: the ommatidia with the smaller half of the azimuths; the rest sees the mean luminance
    half_mask = torch.zeros(lat.n)
    half_mask[np.argsort(lat.azimuth, kind="stable")[: lat.n // 2]] = 1.0
    half = 1.0 + half_mask * (lum - 1.0)
    _, full_out = _pathways(lat, lum)
    _, half_out = _pathways(lat, half)
    ratios = {}
    for g in (100.0, 1.0):
        cfg = TangentialConfig(n_hs=1, g_exc=g, g_inh=g)
        v_full, v_half = (float(hs_vs(o.t4, o.t5, lat, cfg, DT).hs[int(FPS):].double().mean())
                          for o in (full_out, half_out))
        ratios[g] = v_full / v_half
        print(f"\ng = {g:g}: HS half field {v_half:.3f} mV, full field {v_full:.3f} mV, ratio {ratios[g]:.2f}")
        assert v_full > v_half > 0
    assert ratios[100.0] < 2.0
    assert ratios[1.0] > 1.8 and ratios[100.0] < 0.75 * ratios[1.0]
