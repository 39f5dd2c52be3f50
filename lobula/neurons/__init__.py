"""Neuron dynamics: rate neurons, leaky integrate-and-fire neurons, Poisson spiking.

Every population is a batch of ``(trials, neurons)`` torch tensors (any shape works,
the update is elementwise); the device and float dtype follow the input. Nothing
loops over trials or neurons in Python; the whole-run helpers loop over time steps.

Units are SI throughout: seconds, volts, amperes, ohms, and rates in Hz (spikes/s).

Time convention (for all three models): the input of step ``k`` is held constant over
``[k·dt, (k+1)·dt)`` (zero-order hold, as a frame-by-frame pipeline delivers it), and
the state a step returns is the state at ``(k+1)·dt``. Within that assumption the rate
neuron and the subthreshold LIF membrane are integrated exactly (exponential
integration, not Euler), and LIF spike times are the exact threshold crossings inside
the step, so the step size sets the time resolution of the *input*, not the accuracy
of the integration.

Streaming API, the same for every model (``model`` = :class:`RateNeuron`,
:class:`LIFNeuron` or :class:`PoissonNeuron`)::

    state = model.init_state(trials, neurons, device=..., dtype=...)   # or None
    for frame in ...:
        state = model.step(state, input_k, dt, generator=g)            # new state
    rec = model.run(inputs, dt, seed=0)      # inputs (trials, time, neurons)
    rec["r"]  # (time, trials, neurons): time-major

Random numbers come only from an explicit ``torch.Generator`` (see
:func:`make_generator`), so the same seed gives identical arrays on the same device
(CPU and CUDA generators produce different streams).

The package, one module per model: :mod:`lobula.neurons.rate` (:class:`RateNeuron`),
:mod:`lobula.neurons.lif` (:class:`LIFNeuron`), :mod:`lobula.neurons.lif_theory` (the LIF in
closed form: :func:`lif_fi_curve`, :func:`lif_rate`, :func:`lif_isi_cv`,
:func:`lif_current_for_rate`), :mod:`lobula.neurons.poisson` (:class:`PoissonNeuron`) and
:mod:`lobula.neurons.streaming` (:func:`make_generator` and the time loop the models share);
every public name is importable from ``lobula.neurons`` itself.
"""
from __future__ import annotations

from .lif import LIFConfig, LIFNeuron, LIFState, lif_step
from .lif_theory import lif_current_for_rate, lif_fi_curve, lif_isi_cv, lif_rate
from .poisson import PoissonConfig, PoissonNeuron, PoissonState, poisson_spikes
from .rate import RateNeuron, RateNeuronConfig, RateState, naka_rushton, rate_step
from .streaming import make_generator

__all__ = [
    "RateNeuronConfig", "RateState", "RateNeuron", "naka_rushton", "rate_step",
    "LIFConfig", "LIFState", "LIFNeuron", "lif_step", "lif_fi_curve", "lif_rate", "lif_isi_cv",
    "lif_current_for_rate",
    "PoissonConfig", "PoissonState", "PoissonNeuron", "poisson_spikes",
    "make_generator",
]
