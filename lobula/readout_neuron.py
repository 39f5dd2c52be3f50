"""A readout neuron that encodes forward velocity: LC terms + haltere acceleration, divided by shunting.

The arithmetic readout (:mod:`lobula.readout`) divides, takes a median and runs a
Kalman smoother; neurons do none of these. This module is the same computation in
circuit form, batched over trials in torch:

1. **LC pathways** per receptive field f: a sustained pathway r̄_f (two low-pass
   stages) and a transient pathway ṙ̄_f, the difference of the two stages over τ_s,
   which is exactly the derivative of the sustained signal. r²̄_f and a pass the same
   stages, so all terms stay in phase.
2. **Division by shunting inhibition** (Torre & Poggio 1978; Koch 1998): each field
   drives a dendritic branch with excitation a·r̄_f·sgn(D_f) (haltere-gated LC input)
   and a shunting conductance |D_f|, D_f = ṙ̄_f − r²̄_f, so the branch settles at
   v_f = a·r̄_f·sgn(D_f)/(g_L + |D_f|) ≈ a·r̄_f/D_f. The leak g_L makes the division
   safe where D ≈ 0: the branch then falls silent instead of diverging. The soma
   pools branches weighted by their conductance (|D_f| = |a|/d_f: how much a field
   knows), with presynaptic inhibition of branches that disagree with the output —
   the neural counterpart of the arithmetic readout's median. Shunting rather than a log domain,
   because the signs of a, r and D change and a shunting synapse handles a signed
   numerator (push–pull inputs) with a single positive conductance in the denominator,
   whereas logarithms need every term rectified into separate channels.
3. **Delay compensation**: the pathways' low-passes make the pooled estimate refer to
   δ = τ_fast + τ_sustained ago; a feedforward haltere term δ·LP(a) is added to it.
4. **Integration with the haltere** (a complementary filter): the readout's state
   follows dv̂/dt = a + κ·(v_vis − v̂), κ = κ_max·g_s/(g_s + g_half), so it integrates
   acceleration between informative moments and is pulled toward vision in
   proportion to the shunting conductance. Its confidence c (a low-pass of κ)
   says when v̂ is observable.
5. **Output**: a push–pull pair of rate neurons r± = gain·[±v̂]₊ (Hz), or spikes from them —
   Poisson (each step's count the Poisson quantile of its own uniform draw) or leaky
   integrate-and-fire neurons with membrane noise (``spike_model="lif"``) — decoded back by
   (r₊ − r₋)/gain, so rate and spiking readouts are compared on the same input.
   ``population`` independent push–pull pairs share the rate (a small population of
   descending neurons read together); their spikes are pooled.
6. **Decoding spikes, causally** (``decode="causal"``, the default): each spike train passes
   an exponential synaptic filter of time constant τ_d = window_s/2 (a postsynaptic
   neuron's rate estimate: no look-ahead). It lags v̂ by τ_d: the haltere's acceleration adds
   the first-order lead τ_d·a (as in 3; ``lead="haltere"``), or the output neurons are driven
   by v̂ phase-advanced by that filter (``lead="encoder"``, :func:`phase_advance`), which it
   then returns exactly. Its count noise is ``decode_std`` = √(Σ± F·r±/(2τ_d·population))/gain
   (m/s; F = 1 for Poisson, the LIF's ISI CV² plus the filter's ripple): the decoding's own
   uncertainty, not the estimate's model error. ``decode="centred"`` is a
   centred boxcar of window_s (it sees window_s/2 ahead: not causal; for comparison only).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np

from ._optional import torch
from .neurons import LIFConfig, LIFState, lif_current_for_rate, lif_isi_cv, lif_step, make_generator
from .photoreceptor import lowpass_scan


#: How the output neurons spike (:attr:`ReadoutNeuronConfig.spike_model`), and what they are called.
SPIKE_MODELS = {"poisson": "Poisson", "lif": "leaky integrate-and-fire"}


@dataclass
class ReadoutNeuronConfig:
    """Readout-neuron parameters (SI units).

    tau_fast_s / tau_sustained_s: the two low-pass stages of every LC pathway (s).
    g_leak: leak conductance in the units of g_s (1/s²): sets where division turns off.
    kappa_max: fastest visual correction rate (1/s); g_half: shunt conductance of half-maximal trust.
    disagreement_m_s: scale (m/s) of the presynaptic inhibition of branches that disagree with the output.
    tau_confidence_s: memory of the confidence (s); confidence_min: below it (dimensionless, 0..1) v̂ is
    unobservable.
    gain_hz_per_m_s: output rate per m/s (Hz per m/s); spiking: spiking output instead of rates; window_s:
    rate-decoding window (s). seed: seeds the output neurons' spike generator.
    spike_model: how the output neurons spike. "poisson": Poisson trains at r± (count variance =
        mean, the cortical textbook case). "lif": leaky integrate-and-fire neurons
        (:class:`lobula.neurons.LIFConfig`'s Dayan & Abbott defaults) with white membrane noise,
        each driven by the current at which it fires at ``spontaneous_hz`` + r± on average
        (:func:`lobula.neurons.lif_current_for_rate`, Siegert's formula): a driven neuron fires
        regularly, as the fly's motion-sensitive H1 does — its spike count varies far less than
        a Poisson count at high rates (de Ruyter van Steveninck et al. 1997, Science 275:1805).
    membrane_noise_mv: the LIF output neurons' free-membrane noise SD (mV): 1 mV gives an ISI CV of
        0.23 / 0.12 / 0.06 at 37 / 64 / 112 Hz (:func:`lobula.neurons.lif_isi_cv`).
    spontaneous_hz: the LIF output neurons' mean rate at v̂ = 0 (both of a pair; the push–pull
        difference cancels it). 0 (default): the idle neuron of a pair is silent (no current:
        15 mV below threshold, where 1 mV of noise fires it at ~1e-47 Hz). A spontaneous rate
        adds that neuron's irregular firing to the decoding noise (20 Hz: 0.005 → 0.010 m/s for
        10 pairs at 0.6 ± 0.5 m/s).
    lead: how the causal decoding's lag τ_d is made up. "haltere": the decoder adds τ_d·a
        (first order: on a changing acceleration, or with an accelerometer error, it leaves an
        error). "encoder": the output neurons are driven by v̂ phase-advanced by the decoder's
        own filter (:func:`phase_advance`: v̂_k + α/(1 − α)·(v̂_k − v̂_{k−1}), α = e^{−dt/τ_d}, while
        nothing saturates) — a derivative component such as spike-frequency adaptation gives a
        neuron's response — so the synaptic filter returns v̂ itself, lock-on included, with no
        acceleration at the decoder.
    spike_dt_s: the spike generator's step (s): each frame's rate is held over the frame and
        Poisson spikes are drawn every ``spike_dt_s`` (rounded to a whole number of steps per
        frame), so spike times resolve 1 ms rather than the 33 ms frame interval.
    decode: "causal" (exponential synaptic filter, τ_d = window_s/2, with the haltere lead) or
        "centred" (the centred boxcar of window_s: looks ahead; comparison only).
    population: independent push–pull pairs firing at the same rate, decoded together.
    """

    tau_fast_s: float = 0.10
    tau_sustained_s: float = 0.30
    g_leak: float = 0.002
    kappa_max: float = 2.0
    g_half: float = 0.05
    tau_confidence_s: float = 2.0
    confidence_min: float = 0.1
    disagreement_m_s: float = 0.1
    gain_hz_per_m_s: float = 200.0
    spiking: bool = False
    window_s: float = 0.2
    seed: int = 0
    spike_dt_s: float = 0.001
    decode: str = "causal"
    population: int = 1
    spike_model: str = "poisson"
    membrane_noise_mv: float = 1.0
    spontaneous_hz: float = 0.0
    lead: str = "haltere"

    def __post_init__(self):
        if self.decode not in ("causal", "centred"):
            raise ValueError(f"decode must be 'causal' or 'centred', got {self.decode!r}")
        if not (isinstance(self.population, (int, np.integer)) and self.population >= 1):
            raise ValueError(f"population must be a positive integer, got {self.population!r}")
        if self.lead not in ("haltere", "encoder"):
            raise ValueError(f"lead must be 'haltere' or 'encoder', got {self.lead!r}")
        if self.lead == "encoder" and self.decode != "causal":
            raise ValueError("lead='encoder' inverts the causal decoder's filter; it needs decode='causal'")
        if self.spike_model not in SPIKE_MODELS:
            raise ValueError(f"spike_model must be one of {tuple(SPIKE_MODELS)}, got {self.spike_model!r}")
        for name in ("membrane_noise_mv", "spontaneous_hz"):
            x = getattr(self, name)
            if not (np.isfinite(x) and x >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {x!r}")
        if not (self.spike_dt_s > 0 and np.isfinite(self.spike_dt_s)):
            raise ValueError(f"spike_dt_s must be a positive number of seconds, got {self.spike_dt_s!r}")

    def to_dict(self) -> dict:
        """Every field as a dict."""
        return asdict(self)


def _lowpass(x: torch.Tensor, tau: float, dt: float) -> torch.Tensor:
    """First-order low-pass along dim 1 (time) of (trials, time) or (trials, time, fields),
    starting at x[:, 0] — the photoreceptors' :func:`lobula.photoreceptor.lowpass_scan`."""
    a = float(np.exp(-dt / tau))
    if x.dim() == 2:
        return lowpass_scan(x[..., None], a)[..., 0]
    return lowpass_scan(x, a)


def lc_pathways(r: torch.Tensor, r2: torch.Tensor, dt: float, cfg: ReadoutNeuronConfig):
    """Sustained r̄ (1/s), r²̄ (1/s²) and transient ṙ̄ (1/s²) pathways of ``r`` (1/s) and ``r2`` (1/s²) sampled
    every ``dt`` s, the time constants of ``cfg``; inputs and outputs (trials, time, fields).

    Every signal passes the same two low-passes (τ_fast, then τ_sustained), so the terms
    of ṙ = a/d + r² stay in phase. The transient pathway is the difference between the
    two stages divided by τ_sustained, which is *exactly* the time derivative of the
    sustained signal (for y = LP_τ(x), dy/dt = (x − y)/τ).
    """
    r1, r2_1 = _lowpass(r, cfg.tau_fast_s, dt), _lowpass(r2, cfg.tau_fast_s, dt)
    r_s = _lowpass(r1, cfg.tau_sustained_s, dt)
    r2_s = _lowpass(r2_1, cfg.tau_sustained_s, dt)
    r_dot = (r1 - r_s) / cfg.tau_sustained_s
    return r_s, r2_s, r_dot


def shunting_division(a: torch.Tensor, r: torch.Tensor, r2: torch.Tensor, r_dot: torch.Tensor,
                      cfg: ReadoutNeuronConfig):
    """Per-field shunted velocities v_f and conductances |D_f|, (trials, time, fields) each.

    a: (trials, time) m/s²; r (1/s), r2, r_dot (1/s²): (trials, time, fields); cfg: its g_leak. v_f in
    m/s, |D_f| in 1/s². Non-finite fields are silent.
    v_f = a·r̄_f·sgn(D_f)/(g_L + |D_f|): the steady state of a dendritic branch with
    excitation a·r̄_f·sgn(D_f) and shunting conductance |D_f|.
    """
    d = r_dot - r2
    ok = torch.isfinite(d) & torch.isfinite(r)
    d = torch.where(ok, d, 0.0)
    r = torch.where(ok, r, 0.0)
    g_s = d.abs()
    return a[..., None] * r * torch.sign(d) / (cfg.g_leak + g_s), g_s


def pool_branches(v_f: torch.Tensor, g_s: torch.Tensor, v_now: torch.Tensor, cfg: ReadoutNeuronConfig):
    """Soma: branches weighted by their shunt conductance, with presynaptic inhibition of
    branches that disagree with the neuron's own output (a Cauchy weight of scale
    ``disagreement_m_s``; the neural form of the median's robustness).

    v_f (m/s), g_s (1/s²): (trials, fields); v_now: (trials,) m/s; cfg: its disagreement_m_s and g_leak.
    Returns v_vis (m/s) and the total conductance (1/s²), each (trials,).
    """
    w = g_s / (1.0 + ((v_f - v_now[:, None]) / cfg.disagreement_m_s) ** 2)
    # Mean rather than total conductance: synaptic scaling keeps the soma's operating
    # point independent of how many fields converge on it.
    g = w.mean(-1)
    return (w * v_f).mean(-1) / (cfg.g_leak + g), g


def spike_steps_per_frame(frame_dt: float, config: ReadoutNeuronConfig) -> int:
    """Spike-generator steps per frame interval ``frame_dt`` (s): round(frame_dt / spike_dt_s) of ``config``,
    at least 1."""
    return max(1, int(round(frame_dt / config.spike_dt_s)))


def output_lif(membrane_noise_mv: float) -> LIFConfig:
    """The LIF output neurons' parameters: Dayan & Abbott's defaults, white noise of
    ``membrane_noise_mv`` (mV) free-membrane SD (R·σ_I/√2, :class:`lobula.neurons.LIFConfig`)."""
    return LIFConfig(noise="white", noise_std=membrane_noise_mv * 1e-3 * np.sqrt(2.0) / LIFConfig().R)


@lru_cache(maxsize=8)
def _lif_table(membrane_noise_mv: float, spontaneous_hz: float):
    """Rates (Hz) from the spontaneous rate to 95 % of the refractory limit, the currents (A)
    that give them and the ISI CV there: interpolated per step instead of solved per step."""
    lif = output_lif(membrane_noise_mv)
    top = 0.95 / lif.t_ref
    # Every 1 Hz over the range (the current's curve bends most at high rates: a coarse table
    # there misplaces the rate by a few Hz, i.e. a bias of 0.01 m/s at 200 Hz per m/s), finer
    # just above the spontaneous rate.
    above = np.concatenate([np.geomspace(1e-3, 1.0, 12, endpoint=False), np.arange(1.0, top - spontaneous_hz, 1.0)])
    rates = np.concatenate([[spontaneous_hz], spontaneous_hz + above])
    current = lif_current_for_rate(rates, lif)
    # The CV changes slowly with the rate (it only sets the stated noise): computed at 48 rates.
    coarse = np.unique(np.geomspace(1, len(rates), 48).astype(int) - 1)
    cv = np.interp(rates, rates[coarse], lif_isi_cv(current[coarse], lif))
    return lif, rates, current, cv


def _lif_counts(rate_p: torch.Tensor, rate_m: torch.Tensor, sub: int, dt: float, N: int,
                cfg: ReadoutNeuronConfig, gen: torch.Generator):
    """Pooled spike counts per generator step (trials, time·sub) of N + and N − LIF output
    neurons firing at spontaneous_hz + rate± on average; the Fano factors of their decoded
    rate (trials, time) each; and every neuron's own counts (trials, time·sub, 2N: the N + neurons,
    then the N −). Rates above 95 % of 1/t_ref saturate there."""
    lif, rates, current, cv = _lif_table(cfg.membrane_noise_mv, cfg.spontaneous_hz)
    trials, n = rate_p.shape
    target = [np.minimum(cfg.spontaneous_hz + r.numpy(), rates[-1]) for r in (rate_p, rate_m)]
    drive = [np.interp(r, rates, current) for r in target]
    # (trials, time, 2N): the first N neurons carry +, the last N carry −.
    I = torch.as_tensor(np.concatenate([np.repeat(d[..., None], N, -1) for d in drive], -1))
    # Membranes start at independent random points between reset and threshold, so the
    # population does not begin in lock-step.
    v0 = lif.V_reset + (lif.V_threshold - lif.V_reset) * torch.rand((trials, 2 * N), generator=gen, dtype=I.dtype)
    z = torch.zeros_like(v0)
    state = LIFState(v0, z, z, z, torch.full_like(v0, float("nan")))
    counts = torch.empty(trials, n * sub, 2 * N, dtype=I.dtype)
    h = dt / sub
    for k in range(n * sub):  # the membranes evolve in time; trials and neurons are batched
        state = lif_step(state, I[:, k // sub], h, lif, gen)
        counts[:, k] = state.spikes
    fano = [torch.as_tensor(np.interp(r, rates, cv ** 2)) for r in target]
    return counts[..., :N].sum(-1), counts[..., N:].sum(-1), fano, counts


def phase_advance(v: torch.Tensor, tau: float, dt: float, limit: float = float("inf")) -> torch.Tensor:
    """The drive x (trials, time) whose causal low-pass of time constant ``tau`` (s) returns v
    (trials, time; NaN: the neurons silent, decoding 0): x_0 = v_0, x_k = (v_k − α·y_{k−1})/(1 − α),
    α = e^{−dt/τ}, y the low-pass's own state — the inverse of y_k = α·y_{k−1} + (1 − α)·x_k,
    i.e. x_k = v_k + α/(1 − α)·(v_k − v_{k−1}) while nothing saturates. |x| ≤ ``limit`` (the
    output neurons' largest rate, in the units of v); dt: the step (s); a clipped step is made up in the next
    ones, since y is the state the clipped drive leaves. Causal: x_k depends on v up to k."""
    alpha = float(np.exp(-dt / tau))
    target = torch.nan_to_num(v)
    x = torch.empty_like(target)
    # The decoder's low-pass starts at its first input (:func:`_lowpass`), so x_0 = v_0.
    x[:, 0] = y = target[:, 0].clamp(-limit, limit)
    for k in range(1, target.shape[1]):  # the decoder's state evolves in time; trials are batched
        x[:, k] = ((target[:, k] - alpha * y) / (1.0 - alpha)).clamp(-limit, limit)
        y = alpha * y + (1.0 - alpha) * x[:, k]
    return x


def _spikes(v: torch.Tensor, a: torch.Tensor, dt: float, cfg: ReadoutNeuronConfig) -> dict:
    """Push–pull spiking output neurons for v (trials, time) m/s (NaN: silent), decoded back (see 5–6)."""
    gain = cfg.gain_hz_per_m_s
    if cfg.lead == "encoder":
        top = (_lif_table(cfg.membrane_noise_mv, cfg.spontaneous_hz)[1][-1] - cfg.spontaneous_hz
               if cfg.spike_model == "lif" else float("inf"))
        v = phase_advance(v, 0.5 * cfg.window_s, dt, top / gain)
    v = torch.nan_to_num(v)
    rate_p, rate_m = gain * v.clamp_min(0), gain * (-v).clamp_min(0)
    trials, n = v.shape
    gen = make_generator(cfg.seed)
    sub = spike_steps_per_frame(dt, cfg)
    N = int(cfg.population)
    if cfg.spike_model == "lif":
        sp_fine, sm_fine, fano, units = _lif_counts(rate_p, rate_m, sub, dt, N, cfg, gen)
        base = cfg.spontaneous_hz
    else:
        hold = lambda r: r.double().repeat_interleave(sub, dim=1)  # noqa: E731  (trials, time·sub)
        # N independent neurons per sign, each at most one spike per step: a Bernoulli draw with
        # p = 1 − exp(−rate·step), the chance that a Poisson train at that rate fires in the step.
        # Each step's spikes come from its own uniform draws, so they depend on its own rate only:
        # changing later rates leaves earlier spikes unchanged (a causal simulation).
        p_p, p_m = (-torch.expm1(-hold(x) * (dt / sub)) for x in (rate_p, rate_m))
        u = torch.rand((2,) + tuple(p_p.shape) + (N,), generator=gen, dtype=torch.float64)
        up, um = (u[0] < p_p[..., None]).double(), (u[1] < p_m[..., None]).double()   # (trials, time·sub, N)
        sp_fine, sm_fine = up.sum(-1), um.sum(-1)
        fano, base = [torch.ones_like(rate_p)] * 2, 0.0
        units = torch.cat([up, um], -1)
    # Counts per frame for the rate decoding.
    sp, sm = (x.reshape(trials, n, sub).sum(-1) for x in (sp_fine, sm_fine))
    h = dt / sub
    if cfg.spike_model == "lif":
        unsat = lambda e: e  # noqa: E731
    else:
        # A Poisson neuron's mean count per step is 1 − exp(−r·h) (at most one spike): a rate estimate e
        # (Hz, counts per neuron per second) inverts to r = −ln(1 − e·h)/h.
        unsat = lambda e: -torch.log1p(-(e * h).clamp(max=1.0 - 1e-9)) / h  # noqa: E731
    r_p, r_m = rate_p + base, rate_m + base
    if cfg.decode == "causal":
        tau_d = 0.5 * cfg.window_s
        # Exponential synaptic filter of the pooled counts (rate per neuron), then the lead τ_d·a.
        syn = lambda s: unsat(_lowpass(s / (N * dt), tau_d, dt))  # noqa: E731
        v_dec = (syn(sp) - syn(sm)) / gain
        if cfg.lead == "haltere":
            v_dec = v_dec + tau_d * torch.nan_to_num(a)
        # Decoding noise of that filter: var = Σ± F·r / (2 τ_d N) (Hz²), F the count's Fano factor:
        # 1 for Poisson; for a renewal train CV², plus the filter's ripple on a near-regular train
        # (a sawtooth of height 1/τ_d: variance 1/(12 τ_d²) = r/(2τ_d) · 1/(6 r τ_d)), at most 1.
        if cfg.spike_model == "lif":
            fano = [torch.clamp(f + 1.0 / (6.0 * r * tau_d), max=1.0) for f, r in zip(fano, (r_p, r_m))]
        std = torch.sqrt((fano[0] * r_p + fano[1] * r_m) / (2.0 * tau_d * N)) / gain
    else:
        w = max(1, int(round(cfg.window_s / dt)))
        kern = torch.ones(1, 1, w, dtype=sp.dtype) / (w * dt * N)
        # Centred boxcar rate estimate of each spike train (looks window_s/2 ahead), then push–pull decoding.
        smooth = lambda s: unsat(torch.nn.functional.conv1d(s[:, None], kern, padding=w // 2)[:, 0, :n])  # noqa: E731
        v_dec = (smooth(sp) - smooth(sm)) / gain
        std = torch.sqrt((fano[0] * r_p + fano[1] * r_m) / (w * dt * N)) / gain
    return dict(v_dec=v_dec, decode_std=std, spikes_plus=sp_fine, spikes_minus=sm_fine,
                spikes_units=units.to(torch.int32))


def spiking_output(t, v, a, config: ReadoutNeuronConfig | None = None) -> dict[str, np.ndarray]:
    """Carry a velocity estimate v (time,) m/s, sampled at ``t`` (time,) s, on push–pull spiking output neurons
    and decode it back.

    The output stage of :func:`readout_neuron` on its own (steps 5–6 of the module docstring),
    for any readout's v̂ (NaN: the neurons fall silent). v may also be (trials, time): the same
    or different estimates on independent trials (the neurons' noise differs, one generator
    seeded by ``config.seed``). a (time,) or (trials, time) m/s² gives the causal decoder its
    lead. Returns numpy arrays shaped like v: v_dec (m/s), decode_std (m/s, count noise),
    rate_plus / rate_minus (Hz); spikes_plus / spikes_minus (counts per generator step, the
    population's pairs pooled; time·m samples, :func:`spike_steps_per_frame`); spikes_units
    (time·m, 2·population): every output neuron's own counts, the population's + neurons
    then its − neurons (they sum to spikes_plus and spikes_minus).
    """
    cfg = config or ReadoutNeuronConfig(spiking=True)
    v_t = torch.as_tensor(np.array(v, dtype=np.float64))
    squeeze = v_t.dim() == 1
    v_t = v_t[None] if squeeze else v_t
    a_t = torch.as_tensor(np.array(a, dtype=np.float64)).expand_as(v_t)
    dt = float(np.median(np.diff(t)))
    out = _spikes(v_t, a_t, dt, cfg)
    vv = torch.nan_to_num(v_t)
    out.update(rate_plus=cfg.gain_hz_per_m_s * vv.clamp_min(0), rate_minus=cfg.gain_hz_per_m_s * (-vv).clamp_min(0))
    return {k: (x[0] if squeeze else x).numpy() for k, x in out.items()}


def readout_neuron(t, r, r2, a, config: ReadoutNeuronConfig | None = None) -> dict[str, np.ndarray]:
    """Run the readout neuron of ``config`` (None: the default ReadoutNeuronConfig) on field rates.

    t (time,) s; r, r2 (time, fields) or (trials, time, fields) in 1/s, 1/s²; a (time,)
    or (trials, time) m/s². Returns numpy arrays (trials dim dropped if absent):
    v_hat (m/s, NaN where not confident), observable, confidence, v_vis, g_shunt,
    rate_plus / rate_minus (Hz), and spikes_plus / spikes_minus when spiking: spike counts
    (trials, time·m) at the generator's step frame_dt/m (:func:`spike_steps_per_frame`),
    sample k·m + j lying in [t_k + j·frame_dt/m, t_k + (j+1)·frame_dt/m), the population's pairs
    pooled, and spikes_units (trials, time·m, 2·population): each output neuron's own counts.
    """
    cfg = config or ReadoutNeuronConfig()
    squeeze = np.ndim(r) == 2
    as_t = lambda x: torch.as_tensor(np.array(x, dtype=np.float64))
    r, r2, a = as_t(r), as_t(r2), as_t(a)
    if squeeze:
        r, r2, a = r[None], r2[None], a[None]
    dt = float(np.median(np.diff(t)))
    r_s, r2_s, r_dot = lc_pathways(torch.nan_to_num(r), torch.nan_to_num(r2), dt, cfg)
    a_s = _lowpass(_lowpass(a, cfg.tau_fast_s, dt), cfg.tau_sustained_s, dt)
    v_f, g_f = shunting_division(a_s, r_s, r2_s, r_dot, cfg)
    # The visual estimate refers to about τ_fast + τ_sustained ago (the pathways' delay);
    # a feedforward haltere term brings it to the present: v(t) ≈ v(t − δ) + δ·a.
    lead = (cfg.tau_fast_s + cfg.tau_sustained_s) * _lowpass(a, cfg.tau_fast_s, dt)
    trials, n = a.shape
    v_vis = torch.empty(trials, n, dtype=a.dtype)
    g_s = torch.empty_like(v_vis)
    v = torch.zeros(trials, dtype=a.dtype)
    conf = torch.zeros(trials, dtype=a.dtype)
    v_hat = torch.empty(trials, n, dtype=a.dtype)
    c_out = torch.empty_like(v_hat)
    decay_c = float(np.exp(-dt / cfg.tau_confidence_s))
    for k in range(n):  # the neuron's state evolves in time; trials and fields are batched
        v_vis[:, k], g_s[:, k] = pool_branches(v_f[:, k] + lead[:, k, None], g_f[:, k], v, cfg)
        kappa = cfg.kappa_max * g_s[:, k] / (g_s[:, k] + cfg.g_half)
        k_dt = kappa * dt
        # Exact update for constant inputs over the step: relax toward v_vis at rate κ while integrating a.
        e = torch.exp(-k_dt)
        drift = torch.where(k_dt > 1e-9, (1 - e) / kappa.clamp_min(1e-12), torch.full_like(e, dt))
        v = v * e + v_vis[:, k] * (1 - e) + a[:, k] * drift
        conf = decay_c * conf + (1 - decay_c) * kappa / cfg.kappa_max
        v_hat[:, k] = v
        c_out[:, k] = conf
    gain = cfg.gain_hz_per_m_s
    rate_p, rate_m = gain * v_hat.clamp_min(0), gain * (-v_hat).clamp_min(0)
    out = dict(v_vis=v_vis, g_shunt=g_s, confidence=c_out, rate_plus=rate_p, rate_minus=rate_m, v_field=v_f, r_dot=r_dot)
    v_dec = v_hat
    if cfg.spiking:
        enc = _spikes(v_hat, a, dt, cfg)
        v_dec = enc.pop("v_dec")
        out.update(enc)
    else:
        out["decode_std"] = torch.zeros_like(v_hat)
    obs = c_out >= cfg.confidence_min
    out.update(v_hat=torch.where(obs, v_dec, torch.nan), observable=obs)
    res = {k: x.numpy() for k, x in out.items()}
    return {k: x[0] for k, x in res.items()} if squeeze else res
