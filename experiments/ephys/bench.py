"""A benchmark of virtual electrophysiology: a tuning sweep on a 5,000-ommatidia eye."""
from __future__ import annotations

import time as _time

import numpy as np

from lobula._optional import torch
from lobula.camera import PinholeCamera
from lobula.circuit import Circuit, CircuitConfig
from lobula.lattice import Lattice, LatticeConfig, dphi_for_count
from lobula.population import LCNeuronConfig, LCPopulationConfig, ReceptiveFieldConfig
from stimuli.lattice_stimuli import GratingSource

from .rig import torch_threads

__all__ = ["bench_tuning_sweep"]


def bench_tuning_sweep(n_ommatidia: int = 5000, n_tf: int = 20, n_contrasts: int = 5, trials: int = 10,
                       duration_s: float = 2.0, dt_s: float = 1e-3, neuron_model: str = "poisson",
                       field_size_deg: float = 5.0, threads: int | None = 1, device: str = "cpu",
                       chunk_steps: int = 8, compile: bool = False, max_steps: int | None = None,
                       verbose: bool = True) -> dict:
    """The benchmark: a tuning sweep of n_tf TFs × n_contrasts contrasts × trials, duration_s at dt_s,
    for an eye of ~n_ommatidia (D435i field of view at 320×240) with its LC population (5° Gaussian
    fields tiling the eye, 5 unit types each).

    The front end (photoreceptors, EMDs, LC pooling) is deterministic and runs once per
    stimulus condition (n_tf·n_contrasts conditions, all batched); the LC neurons run per
    trial (their noise differs). Only the steady-state spike counts/rates are kept (no
    time courses). threads: torch CPU threads during the run (1 is fastest on a shared
    2-core machine: per-step tensors are small); compile: fuse the pair pooling
    with torch.compile (its one-off compilation is timed separately, as ``compile_s``,
    by a short warm-up run; off by default: with the circuit running lobula.emd's correlator,
    compiling the pooling alone is 1.5× slower on a CPU); max_steps: time only that many steps and
    extrapolate. Returns a dict with seconds and neuron-steps per second:
    ``computed`` counts each stage as run (front end per condition, LC per trial),
    ``equivalent`` as if every trial ran the whole eye.
    """
    with torch_threads(threads):
        t0 = _time.perf_counter()
        camera = PinholeCamera(frame_rate_hz=1.0 / dt_s).scaled(0.5)
        lat = Lattice(camera, LatticeConfig(dphi_deg=dphi_for_count(camera, n_ommatidia)))
        pop = LCPopulationConfig(fields=ReceptiveFieldConfig(size_deg=field_size_deg),
                                 neurons=LCNeuronConfig(model=neuron_model))
        circuit = Circuit(lat, CircuitConfig(population=pop, dt_s=dt_s, chunk_steps=chunk_steps, compile=compile),
                          device=device)
        tf = np.geomspace(0.5, 32.0, n_tf)
        c = np.geomspace(0.05, 0.8, n_contrasts)
        TF, C = np.meshgrid(tf, c, indexing="ij")
        src = GratingSource(lat, kind="drum", temporal_freq_hz=TF.ravel(), contrast=C.ravel(), wavelength_deg=20.0,
                            frame_rate_hz=1.0 / dt_s, device=device)
        n_steps = int(round(duration_s / dt_s))
        run_steps = n_steps if max_steps is None else min(n_steps, int(max_steps))
        settle = int(round(0.5 / dt_s))
        var = "lc.spikes" if neuron_model in ("poisson", "lif") else "lc.rate"
        acc = {"sum": None}

        def keep(start, rec):  # steady-state sums only: no time courses are kept
            x = rec[var]                                                        # (Tc, B, K, U)
            lo = max(0, settle - start)
            if lo < x.shape[0]:
                s = x[lo:].sum(0)
                acc["sum"] = s if acc["sum"] is None else acc["sum"] + s

        setup = _time.perf_counter() - t0
        compile_s = 0.0
        if compile:  # compile on a warm-up chunk of the same shape, timed on its own
            tc = _time.perf_counter()
            circuit.run(src, chunk_steps, trials=trials, record=(var,), seed=0, baseline=1.0, callback=lambda *a: None)
            compile_s = _time.perf_counter() - tc
        t1, c1 = _time.perf_counter(), _time.process_time()
        circuit.run(src, run_steps, trials=trials, record=(var,), seed=0, baseline=1.0, callback=keep)
        if device != "cpu":
            torch.cuda.synchronize()
        run_s = _time.perf_counter() - t1
        run_cpu_s = _time.process_time() - c1
    B, U, n, P = TF.size, circuit.population.n_units, lat.n, lat.n_pairs
    scale = n_steps / run_steps
    total = run_s * scale
    computed = (B * (n + P) + B * trials * U) * n_steps
    equivalent = B * trials * (n + P + U) * n_steps
    res = {"n_ommatidia": n, "n_pairs": P, "n_lc_units": U, "n_fields": circuit.population.n_fields,
           "conditions": B, "trials": trials, "steps": n_steps, "dt_s": dt_s, "neuron_model": neuron_model,
           "device": device, "threads": threads, "compile": compile, "setup_s": setup, "compile_s": compile_s,
           "run_s": total, "run_cpu_s": run_cpu_s * scale,
           "extrapolated_from_steps": run_steps if run_steps < n_steps else None,
           "computed_neuron_steps_per_s": computed / total, "equivalent_neuron_steps_per_s": equivalent / total,
           "target_s": 60.0}
    if verbose:
        print(f"ephys tuning sweep: {n_tf} TF × {n_contrasts} contrasts × {trials} trials, {duration_s:g} s at "
              f"{dt_s * 1e3:g} ms; eye {n} ommatidia, {P} EMDs, {U} LC units ({neuron_model}) on {device}: "
              f"{total:.1f} s{' (extrapolated from %d steps)' % run_steps if run_steps < n_steps else ''} "
              f"({run_cpu_s * scale:.1f} s CPU) "
              f"+ {setup:.1f} s setup{' + %.1f s compilation' % compile_s if compile else ''}; "
              f"{computed / total:.3g} neuron-steps/s computed, "
              f"{equivalent / total:.3g} equivalent (target < 60 s)")
    return res


