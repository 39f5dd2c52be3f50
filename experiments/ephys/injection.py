"""The ``current-injection`` protocol: current steps into the LC units, their f–I curve against theory.

The eye looks at a uniform field (the visual input at rest: the circuit runs on it, and the LC
units' drive is what it returns, 0 for a model at rest), and a current step is added to each LC
unit's input: for LIF units a current (A) on top of the synaptic current the drive makes
(``lif_bias_A + lif_gain_A·s(drive)``, :class:`lobula.lc_config.LCNeuronConfig`); for rate and
Poisson units, whose input is a dimensionless drive, a drive step. Each amplitude is shown on every
trial; trial k's membrane or spike noise comes from its own stream, seeded by
:func:`experiments.ephys.rig.trial_seed` (seed, k).

Analysis, over the step after :data:`SETTLE_S`: each unit's steady-state rate (the inverse of its
mean interspike interval, (n − 1)/(t_last − t_first); 0 without a spike; for rate units their mean
rate), its mean and spread over trials and units, the ISI CV, and the rheobase (the smallest
amplitude tested that evokes ≥ :data:`RHEOBASE_HZ`). Theory beside it: :func:`lobula.neurons.lif_fi_curve`
without noise, Siegert's :func:`lobula.neurons.lif_rate` and :func:`lobula.neurons.lif_isi_cv` with
white membrane noise (none exists for Ornstein–Uhlenbeck noise), the Naka–Rushton steady state for
rate and Poisson units.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import xarray as xr

from lobula._optional import torch
from lobula.neurons import LIFConfig, lif_fi_curve, lif_isi_cv, lif_rate, lif_step, naka_rushton
from lobula.population import NEURON_RECORDS

from .protocols import _specs
from .rig import EphysConfig, Rig, cf_describe, monitors_for, protocol, record_dataset, \
    rig_attrs, trial_seed

__all__ = ["current_injection", "run_from_options", "plot_current_injection", "injection_summary", "synaptic_current",
           "interspike_intervals", "DEFAULT_AMPLITUDES_A", "DEFAULT_AMPLITUDES_DRIVE", "SETTLE_S", "RHEOBASE_HZ",
           "PRE_S", "POST_S"]

#: default LIF step amplitudes (A): 0 to 3 nA in 0.25 nA steps (the LC units' rheobase is 0.5 nA above
#: their 1 nA bias)
DEFAULT_AMPLITUDES_A = tuple(np.round(np.arange(13) * 0.25e-9, 15))
#: default rate/Poisson step amplitudes (drive, dimensionless): 0 to 3 in steps of 0.25
DEFAULT_AMPLITUDES_DRIVE = tuple(np.arange(13) * 0.25)
#: time (s) at rest before and after the step
PRE_S = POST_S = 0.2
#: time (s) after step onset left out of the steady-state analysis (the membrane's τ_m = 10 ms, 5×)
SETTLE_S = 0.05
#: the rate (Hz) a step must evoke to count as above rheobase
RHEOBASE_HZ = 1.0
#: --membrane-noise choices
NOISE_KINDS = ("none", "white", "ou")


def synaptic_current(neurons_config, drive):
    """The current (A) a drive makes in an LIF LC unit: ``bias + gain·s(drive)``, s the synaptic saturation
    of :class:`lobula.lc_config.LCNeuronConfig` (the form :meth:`lobula.population.LCNeurons.step` uses).
    drive: tensor, dimensionless, any shape; returns its shape."""
    c = neurons_config
    ex, inh = c.lif_excitation_max, c.lif_inhibition_max
    s = torch.where(drive > 0, ex * torch.tanh(drive / ex), inh * torch.tanh(drive / inh))
    return c.lif_bias_A + c.lif_gain_A * s


def interspike_intervals(counts: np.ndarray, dt: float) -> list[np.ndarray]:
    """Interspike intervals (s) of spike-count trains ``counts`` (..., T) in steps of ``dt`` s, one array per
    train (row-major over the leading dims). A step with c spikes holds c spikes at its start (c − 1
    intervals of 0)."""
    flat = np.asarray(counts).reshape(-1, np.shape(counts)[-1])
    out = []
    for row in flat:  # spike trains are ragged: one small array each
        t = np.repeat(np.arange(row.size), np.asarray(row, dtype=np.int64)) * dt
        out.append(np.diff(t))
    return out


def _steady_rate(counts: np.ndarray, dt: float) -> np.ndarray:
    """Steady-state rate (Hz) of spike-count trains (..., T): (n − 1)/(t_last − t_first) for n ≥ 2 spikes
    (the inverse mean ISI: exact for a periodic train whatever the window's phase), n/window for one,
    0 for none. Returns the leading shape."""
    c = np.asarray(counts, dtype=float)
    T = c.shape[-1]
    n = c.sum(-1)
    has = c > 0
    first = np.where(has.any(-1), np.argmax(has, -1), 0)
    last = np.where(has.any(-1), T - 1 - np.argmax(has[..., ::-1], -1), 0)
    span = (last - first) * dt
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(n >= 2, (n - 1) / np.where(span > 0, span, np.inf), n / (T * dt))
    return np.where((n >= 2) & (span == 0), n / (T * dt), r)


def _theory(cfg: EphysConfig, lif: LIFConfig, model: str, current: np.ndarray):
    """Theoretical rate (Hz), ISI CV and a label, for total inputs ``current`` (A for LIF, drive otherwise)."""
    if model != "lif":
        r = cfg.circuit.population.neurons.rate
        rate = naka_rushton(torch.as_tensor(current, dtype=torch.float64), r.r_max, r.c50, r.n).numpy()
        cv = np.where(rate > 0, 1.0, np.nan) if model == "poisson" else np.full_like(rate, np.nan)
        return rate, cv, ("Naka-Rushton steady state r_max x^n/(x^n + c50^n)"
                          + ("; Poisson ISI CV 1" if model == "poisson" else ""))
    if lif.noisy and lif.noise == "ou":
        return (np.asarray(lif_fi_curve(current, replace(lif, noise="none")), dtype=float), np.full(current.shape, np.nan),
                "noise-free LIF f-I curve 1/(t_ref + tau_m ln(...)) (no closed form with OU noise)")
    rate = np.asarray(lif_rate(current, lif), dtype=float)
    cv = np.asarray(lif_isi_cv(current, lif), dtype=float)
    return rate, cv, ("Siegert rate and ISI CV (white membrane noise)" if lif.noisy
                      else "noise-free LIF f-I curve 1/(t_ref + tau_m ln(...))")


def _current_injection(config: EphysConfig, *, amplitudes=None, duration_s: float = 1.0,
                       membrane_noise: str | None = None, noise_std_A: float | None = None,
                       record=None) -> xr.Dataset:
    """Current steps into the LC units with the eye at rest; their f–I curve, rheobase and ISI CV.

    Parameters
    ----------
    config : EphysConfig
        The rig: its LC neuron model (``with_neurons``), trials and seed.
    amplitudes : sequence of float, optional
        Step amplitudes: current (A) for LIF units (default :data:`DEFAULT_AMPLITUDES_A`), drive
        (dimensionless) for rate and Poisson units (default :data:`DEFAULT_AMPLITUDES_DRIVE`).
    duration_s : float
        The step's duration (s), between :data:`PRE_S` and :data:`POST_S` at rest.
    membrane_noise : {"none", "white", "ou"}, optional
        LIF only: the membrane noise (default: the rig's LIF, OU). noise_std_A: its SD (A) (default: the
        rig's, 0.2 nA). White noise follows :class:`lobula.neurons.LIFConfig`'s convention.
    record : list of str, optional
        Monitors among the neuron model's variables (default: all of them, for the expansion units);
        the f–I analysis needs the spikes (LIF, Poisson) or the rate (rate units) recorded.

    Returns
    -------
    xarray.Dataset
        The monitors with dims (amplitude, trial, time, neuron), time since step onset (s); ``fi_rate``
        (amplitude, trial, neuron) Hz, ``fi_rate_mean``/``fi_rate_sd``/``fi_rate_sem`` (amplitude) over
        trials and units, ``fi_rate_theory`` (amplitude), ``isi_cv`` and ``isi_cv_theory`` (amplitude),
        ``rheobase`` and ``rheobase_theory`` (scalars, the amplitude's units), ``input_at_rest``.
    """
    cfg = config
    nc = cfg.circuit.population.neurons
    model = nc.model
    if membrane_noise is not None or noise_std_A is not None:
        if model != "lif":
            raise ValueError(f"--membrane-noise and --noise-std set the LIF membrane's noise; the {model} units have "
                             f"none (use --neuron-model lif)")
        kind = membrane_noise or nc.lif.noise
        if kind not in NOISE_KINDS:
            raise ValueError(f"membrane noise must be one of {NOISE_KINDS}, got {kind!r}")
        std = nc.lif.noise_std if noise_std_A is None else float(noise_std_A)
        if not (std >= 0 and math.isfinite(std)):
            raise ValueError(f"the membrane noise SD must be a non-negative number of amperes, got {noise_std_A}")
        if kind == "none":
            std = 0.0
        elif std == 0:
            raise ValueError(f"--membrane-noise {kind} with --noise-std 0 is no noise; give --noise-std > 0 "
                             f"or --membrane-noise none")
        cfg = replace(cfg, circuit=replace(cfg.circuit, population=replace(
            cfg.circuit.population, neurons=replace(nc, lif=replace(nc.lif, noise=kind, noise_std=std)))))
        nc = cfg.circuit.population.neurons
    unit = "A" if model == "lif" else "1"
    amps = np.asarray(DEFAULT_AMPLITUDES_A if (amplitudes is None and model == "lif") else
                      DEFAULT_AMPLITUDES_DRIVE if amplitudes is None else amplitudes, dtype=float)
    if amps.ndim != 1 or amps.size == 0 or not np.all(np.isfinite(amps)):
        raise ValueError(f"the step amplitudes must be one or more finite numbers, got {amplitudes!r}")
    if np.any(np.diff(amps) <= 0):
        raise ValueError("give the step amplitudes in increasing order, each once (the f-I curve's axis)")
    if model == "lif" and np.max(np.abs(amps)) > 1e-6:
        raise ValueError(f"LIF step amplitudes are in amperes (nA on the command line); {np.max(np.abs(amps)):g} A "
                         f"is over a microampere: give them in A (e.g. 1e-9) to current_injection")
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise ValueError(f"the step duration must be a positive number of seconds, got {duration_s}")
    if duration_s <= SETTLE_S + 0.05:
        raise ValueError(f"the step must last over {SETTLE_S + 0.05:g} s (the analysis leaves out its first "
                         f"{SETTLE_S:g} s); use --duration ≥ 0.2")
    rig = Rig(cfg)
    dt = rig.dt
    monitors = monitors_for(rig, record, [f"{v}[expansion]" for v in rig.default_records()])
    bad = [m.variable for m in monitors if m.variable not in NEURON_RECORDS]
    if bad:
        raise ValueError(f"current-injection records the LC units' neuron variables ({', '.join(rig.circuit.neurons.records)}), "
                         f"not {', '.join(bad)}: the eye is at rest")
    fi_var = "lc.rate" if model == "rate" else "lc.spikes"
    if fi_var not in [m.variable for m in monitors]:
        raise ValueError(f"the f-I analysis reads {fi_var}: add it to --record (e.g. --record "
                         f"{' '.join(m.variable + ('' if m.neurons is None else '[...]') for m in monitors)} {fi_var})")
    n0, n1 = int(round(PRE_S / dt)), int(round(duration_s / dt))
    n_steps = n0 + n1 + int(round(POST_S / dt))
    # A uniform field of luminance 1 for the whole run: the eye at rest.
    front = rig.circuit.run(torch.full((1, n_steps, rig.lattice.n), 1.0, device=cfg.device), n_steps,
                            trials=1, record={"lc.drive": None}, seed=cfg.seed)["lc.drive"]       # (1, T, U)
    step = torch.zeros(n_steps, dtype=front.dtype, device=front.device)
    step[n0:n0 + n1] = 1.0
    amp_t = torch.as_tensor(amps, dtype=front.dtype, device=front.device)
    neurons = rig.circuit.neurons
    if model == "lif":   # current (A): the synaptic current at rest plus the step
        inputs = synaptic_current(nc, front)[0][:, None] + step[:, None, None] * amp_t[None, :, None]       # (T, A, U)
        rest_input = float(synaptic_current(nc, front).mean())
    else:                # drive: the drive at rest plus the step
        inputs = front[0][:, None] + step[:, None, None] * amp_t[None, :, None]
        rest_input = float(front.mean())
    inputs = inputs.unsqueeze(2)                                                              # (T, A, 1, U)
    A, U = len(amps), rig.population.n_units
    want = [m.variable for m in monitors]
    per_trial = {k: [] for k in want}
    for trial in range(rig.stored_trials):   # trial k on its own stream, as the rig's neurons
        gen = torch.Generator(device=front.device)
        gen.manual_seed(trial_seed(cfg.seed, trial))
        state = neurons.init_state((A, 1, U), front.device, front.dtype, gen)
        bufs = {k: front.new_empty((n_steps, A, 1, U)) for k in want}
        for t in range(n_steps):  # the neuron's time loop, vectorised over amplitudes and units
            if model == "lif":
                state = lif_step(state, inputs[t], dt, nc.lif, gen)
            else:
                state = neurons.step(state, inputs[t], dt, gen)
            for k in want:
                bufs[k][t] = neurons.read(state, k)
        for k in want:
            per_trial[k].append(bufs[k].movedim(0, 2))                                            # (A, 1, T, U)
    recs = {}
    for m in monitors:
        x = torch.cat(per_trial[m.variable], dim=1)
        recs[m.variable] = x if m.neurons is None else x.index_select(-1, torch.as_tensor(m.neurons))
    params = dict(amplitudes=amps, amplitude_units=unit, duration_s=duration_s, pre_s=PRE_S, post_s=POST_S,
                  settle_s=SETTLE_S, membrane_noise=nc.lif.noise if model == "lif" else None,
                  noise_std_A=nc.lif.noise_std if model == "lif" else None, monitors=_specs(monitors))
    ds = record_dataset(rig, recs, monitors, {"amplitude": amps}, n_steps, rig_attrs(rig, "current-injection", params),
                        time_offset_s=PRE_S)
    ds["amplitude"].attrs.update(units=unit, long_name="injected step amplitude: " + (
        "current" if model == "lif" else "drive (lc.drive's units)"))
    _analyse(ds, cfg, model, fi_var.replace(".", "_"), rest_input, unit, duration_s, dt)
    return cf_describe(ds)


def _analyse(ds: xr.Dataset, cfg: EphysConfig, model: str, var: str, rest_input: float, unit: str,
             duration_s: float, dt: float) -> None:
    """The f–I curve, ISI CV and rheobase of the recorded units, and their theory, into ``ds``."""
    lif = cfg.circuit.population.neurons.lif
    t = ds.time.values
    win = (t >= SETTLE_S - 1e-9) & (t < duration_s - 1e-9)
    x = ds[var].isel(time=np.flatnonzero(win)).transpose("amplitude", "trial", "neuron", "time").values
    amps = ds.amplitude.values
    if model == "rate":
        rate = x.mean(-1)
        cv = np.full(len(amps), np.nan)
    else:
        rate = _steady_rate(x, dt)
        isis = interspike_intervals(x, dt)
        per_amp = len(isis) // len(amps)
        cv = np.array([_cv(np.concatenate(isis[i * per_amp:(i + 1) * per_amp])) for i in range(len(amps))])
    dims = ("amplitude", "trial", "neuron")
    ds["fi_rate"] = (dims, rate, {"units": "Hz", "long_name": "steady-state firing rate during the step" + (
        " (the inverse mean interspike interval; 0 without spikes)" if model != "rate" else " (mean rate)")})
    flat = rate.reshape(len(amps), -1)
    n = flat.shape[1]
    ds["fi_rate_mean"] = ("amplitude", flat.mean(1), {"units": "Hz", "long_name": "f-I curve: mean steady-state "
                                                                                "rate over trials and units"})
    ds["fi_rate_sd"] = ("amplitude", flat.std(1, ddof=1) if n > 1 else np.zeros(len(amps)), {
        "units": "Hz", "long_name": "standard deviation of the steady-state rate over trials and units"})
    ds["fi_rate_sem"] = ("amplitude", ds.fi_rate_sd.values / math.sqrt(n), {
        "units": "Hz", "long_name": "standard error of the f-I curve's mean"})
    theory, cv_theory, label = _theory(cfg, lif, model, rest_input + amps)
    ds["fi_rate_theory"] = ("amplitude", theory, {"units": "Hz", "long_name": "theoretical steady-state rate: " + label})
    if model != "rate":
        ds["isi_cv"] = ("amplitude", cv, {"units": "1", "long_name": "coefficient of variation of the interspike "
                                                                     "intervals during the step, all trials and units "
                                                                     "pooled (NaN with fewer than 2 intervals)"})
        ds["isi_cv_theory"] = ("amplitude", cv_theory, {"units": "1", "long_name": "theoretical ISI CV: " + label
                                                        + " (NaN where there is none)"})
    above = np.flatnonzero(flat.mean(1) >= RHEOBASE_HZ)
    ds["rheobase"] = ((), float(amps[above[0]]) if above.size else np.nan, {
        "units": unit, "long_name": f"smallest step amplitude tested whose mean rate is at least {RHEOBASE_HZ:g} Hz "
                                    "(NaN: none)"})
    if model == "lif":
        rheo = lif.rheobase - rest_input
    else:
        rheo = -rest_input   # Naka-Rushton: any positive drive fires
    ds["rheobase_theory"] = ((), rheo, {"units": unit, "long_name": "noise-free rheobase: the step amplitude at "
                                                                   "which the unit starts to fire" + (
                                                                       " ((V_th - V_rest)/R minus the current at rest)"
                                                                       if model == "lif" else "")})
    ds["input_at_rest"] = ((), rest_input, {"units": unit, "long_name": "the unit's input with the eye at rest (the "
                                                                       "synaptic current for LIF, the drive otherwise)"})
    ds.attrs["theory"] = label


def _cv(isi: np.ndarray) -> float:
    return float(isi.std(ddof=1) / isi.mean()) if isi.size >= 2 and isi.mean() > 0 else float("nan")


current_injection = protocol(_current_injection, EphysConfig)


def run_from_options(opts: dict):
    """``lobula ephys current-injection`` from the given options (amplitudes and noise SD in nA for LIF units)."""
    from .command import rig_config

    cfg = rig_config("current-injection", opts)
    lif = cfg.circuit.population.neurons.model == "lif"
    kw = {}
    if "amplitudes" in opts:
        kw["amplitudes"] = np.asarray(opts["amplitudes"], dtype=float) * (1e-9 if lif else 1.0)
    if "duration" in opts:
        kw["duration_s"] = opts["duration"]
    if "membrane_noise" in opts:
        kw["membrane_noise"] = opts["membrane_noise"]
    if "noise_std" in opts:
        kw["noise_std_A"] = opts["noise_std"] * 1e-9
    return current_injection(cfg, record=opts.get("record"), **kw)


# =========================================================================== summary and figure

def injection_summary(ds: xr.Dataset) -> list[str]:
    """Lines describing a stored ``current-injection`` recording: rheobase, f–I against theory, ISI CV."""
    unit = ds.amplitude.attrs.get("units", "")
    scale, shown = (1e9, "nA") if unit == "A" else (1.0, "drive")
    lines = [f"rheobase: {float(ds.rheobase) * scale:.3g} {shown} measured (first step ≥ {RHEOBASE_HZ:g} Hz), "
             f"{float(ds.rheobase_theory) * scale:.3g} {shown} noise-free theory"]
    err = []
    for a, m, th in zip(ds.amplitude.values, ds.fi_rate_mean.values, ds.fi_rate_theory.values):
        err.append(f"{a * scale:g}: {m:.1f} ({th:.1f})")
    lines.append(f"f-I curve, {shown}: mean rate Hz (theory, {ds.attrs.get('theory', '')}): " + "; ".join(err))
    if "isi_cv" in ds:
        lines.append("ISI CV per step: " + ", ".join(f"{a * scale:g} {shown}: {c:.2f}"
                                                      for a, c in zip(ds.amplitude.values, ds.isi_cv.values)
                                                      if np.isfinite(c)))
    return lines


def _shown_amplitudes(ds: xr.Dataset) -> list[int]:
    """Up to three amplitudes to draw traces of: below, near and well above rheobase."""
    rate = ds.fi_rate_mean.values
    fires = np.flatnonzero(rate >= RHEOBASE_HZ)
    if fires.size == 0:
        return [len(rate) - 1]
    first = int(fires[0])
    picks = [first, first + (fires.size - 1) // 3, len(rate) - 1]
    return sorted(set(picks))


def plot_current_injection(ds: xr.Dataset, path) -> list:
    """Voltage (LIF) or rate traces and a raster at up to three amplitudes, the f–I curve with theory (SEM
    bars and SD band), the ISI CV and an ISI histogram per amplitude shown. PNG and PDF."""
    from .figures import _colours, _plt, save_png_and_pdf

    plt = _plt()
    unit = ds.amplitude.attrs.get("units", "")
    scale, shown = (1e9, "nA") if unit == "A" else (1.0, "drive")
    picks = _shown_amplitudes(ds)
    cols = _colours(3)
    fig = plt.figure(figsize=(11, 8.2), layout="constrained")
    gs = fig.add_gridspec(2, 3)
    a_tr, a_ra = fig.add_subplot(gs[0, :2]), fig.add_subplot(gs[1, :2])
    a_fi, a_isi = fig.add_subplot(gs[0, 2]), fig.add_subplot(gs[1, 2])
    t = ds.time.values
    dur = json.loads(ds.attrs["parameters"])["duration_s"]
    trace = "lc_v" if "lc_v" in ds else "lc_rate" if "lc_rate" in ds else None
    for j, i in enumerate(picks):
        amp = float(ds.amplitude[i]) * scale
        if trace is not None:
            y = ds[trace].isel(amplitude=i, trial=0, neuron=0).values
            y = y * 1e3 if trace == "lc_v" else y
            a_tr.plot(t, y, color=cols[j], lw=0.9, label=f"{amp:g} {shown}")
        if "lc_spikes" in ds:
            s = ds.lc_spikes.isel(amplitude=i).transpose("trial", "neuron", "time").values
            rows = s.reshape(-1, s.shape[-1])[:8]   # at most 8 trains per amplitude: the raster stays legible
            for r, row in enumerate(rows):
                ts = t[row > 0]
                y0 = j * 9 + r
                a_ra.vlines(ts, y0 + 0.1, y0 + 0.9, color=cols[j], lw=0.6)
            a_ra.text(t[-1], j * 9 + 4, f" {amp:g} {shown}", va="center", fontsize=8, color=cols[j])
    for a in (a_tr, a_ra):
        a.axvspan(0.0, dur, color="0.92", lw=0, zorder=0)
        a.set_xlim(t[0], t[-1])
    # The traces' first 0.3 s of the step: at a hundred spikes per second the whole step is a solid block.
    a_tr.set_xlim(t[0], min(0.3, dur))
    a_ra.set_ylim(-0.5, 9 * len(picks))
    if trace == "lc_v":
        a_tr.axhline(json.loads(ds.lc_v.attrs["neuron_parameters"])["lif"]["V_threshold"] * 1e3, color="0.5",
                     ls=":", lw=0.8, label="threshold")
    a_tr.set_ylabel("membrane potential (mV)" if trace == "lc_v" else "rate (Hz)")
    a_tr.set_title(f"trial 0, unit {int(ds.neuron[0])}: {'membrane potential' if trace == 'lc_v' else 'rate'} "
                   f"at step onset (step shaded)", fontsize=9)
    a_tr.legend(fontsize=7, frameon=False, loc="upper left")
    a_ra.set_xlabel("time since step onset (s)")
    a_ra.set_ylabel("trial × unit (8 trains per step)")
    a_ra.set_yticks([])
    a_ra.set_title("spike raster" if "lc_spikes" in ds else "no spikes recorded (rate units)", fontsize=9)
    amps = ds.amplitude.values * scale
    a_fi.fill_between(amps, ds.fi_rate_mean - ds.fi_rate_sd, ds.fi_rate_mean + ds.fi_rate_sd, color="C0",
                      alpha=0.2, lw=0, label="± SD over trials and units")
    a_fi.errorbar(amps, ds.fi_rate_mean, yerr=ds.fi_rate_sem, color="C0", marker="o", ms=3, capsize=2, lw=1.2,
                  label="simulated (mean ± SEM)")
    a_fi.plot(amps, ds.fi_rate_theory, color="k", ls="--", lw=1, label="theory")
    if np.isfinite(float(ds.rheobase_theory)):
        a_fi.axvline(float(ds.rheobase_theory) * scale, color="0.5", ls=":", lw=0.8, label="noise-free rheobase")
    a_fi.set_xlabel(f"step amplitude ({shown})")
    a_fi.set_ylabel("steady-state rate (Hz)")
    a_fi.set_title(f"f-I curve\ntheory: {ds.attrs.get('theory', '')}", fontsize=8)
    a_fi.legend(fontsize=7, frameon=False, loc="upper left")
    if "lc_spikes" in ds:
        dt = float(ds.lc_spikes.attrs["dt_s"])
        win = np.flatnonzero((ds.time.values >= SETTLE_S) & (ds.time.values < dur))
        isis = [np.concatenate(interspike_intervals(ds.lc_spikes.isel(amplitude=i, time=win).transpose(
            "trial", "neuron", "time").values, dt) or [np.zeros(0)]) * 1e3 for i in picks]
        pooled = np.concatenate(isis)
        top = float(np.percentile(pooled, 99)) if pooled.size else 1.0
        edges = np.arange(0.0, max(top, 2.0) + dt * 1e3, dt * 1e3) - 0.5 * dt * 1e3   # one bin per model step
        for j, (i, isi) in enumerate(zip(picks, isis)):
            if isi.size:
                a_isi.hist(isi, bins=edges, histtype="step", color=cols[j], lw=1.2,
                           label=f"{amps[i]:g} {shown} (CV {float(ds.isi_cv[i]):.2f})")
        a_isi.set_xlabel("interspike interval (ms)")
        a_isi.set_ylabel("intervals (all trials and units)")
        a_isi.set_title("ISI histogram during the step", fontsize=9)
        a_isi.legend(fontsize=7, frameon=False)
    else:
        a_isi.text(0.5, 0.5, "rate units fire no spikes", ha="center", transform=a_isi.transAxes)
        a_isi.set_axis_off()
    cfg = json.loads(ds.attrs["config"])
    fig.suptitle(f"Current injection into LC units ({ds.attrs.get('neuron_model')}; {ds.sizes['trial']} trial(s) × "
                 f"{ds.sizes['neuron']} unit(s)), the eye at rest; seed {cfg['ephys']['seed']}", fontsize=10)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)
