"""The LIF neuron in closed form: its f–I curve without noise and, with white noise, Siegert's firing
rate, the interspike interval's CV, and the current that gives a rate.
"""
from __future__ import annotations

from .._optional import is_tensor, torch
from .lif import LIFConfig


def lif_fi_curve(current, config: LIFConfig | None = None):
    """Analytic firing rate (Hz) of a noise-free LIF neuron under constant current (A).

    ``f = 1 / (t_ref + tau_m · ln((R I + V_rest - V_reset) / (R I - (V_th - V_rest))))``
    for ``R I > V_th - V_rest``, else 0. With V_reset = V_rest (the default) this is
    ``1 / (t_ref + tau_m · ln(R I / (R I - (V_th - V_rest))))``.
    Works on floats, numpy arrays and tensors (returns the same kind and shape). config: the neuron
    (:class:`LIFConfig`; None: the default).
    """
    c = config or LIFConfig()
    if is_tensor(current):
        lib, I = torch, current
    else:
        import numpy as np
        lib, I = np, np.asarray(current, dtype=float)
    drive = c.R * I                                     # V_inf - V_rest (V)
    gap = drive - (c.V_threshold - c.V_rest)            # V_inf - V_th (V)
    fires = gap > 0
    # keep log's argument valid off the firing branch (where() evaluates both sides)
    num = lib.where(fires, drive + c.V_rest - c.V_reset, 2.0)
    isi = c.t_ref + c.tau_m * lib.log(num / lib.where(fires, gap, 1.0))
    f = lib.where(fires, 1.0 / isi, 0.0)
    return float(f) if f.ndim == 0 and not is_tensor(current) else f


def _white_sigma(c: LIFConfig) -> float:
    """σ (V) of Brunel's (2000) τ dV/dt = −V + μ + σ√τ ξ for this config's white noise (0 without)."""
    return c.R * c.noise_std if (c.noisy and c.noise == "white") else 0.0


def _siegert_nodes(current, c: LIFConfig, nodes: int):
    """Integration nodes u from y_r = (V_reset − μ)/σ to y_θ = (V_θ − μ)/σ, (m, nodes), for
    the flattened ``current``; and which entries can fire at all (y_θ < 26: beyond, ν < 1e-290)."""
    import numpy as np
    sigma = _white_sigma(c)
    mu = c.V_rest + c.R * np.ravel(np.asarray(current, dtype=float))
    y_r, y_th = (c.V_reset - mu) / sigma, (c.V_threshold - mu) / sigma
    # Dense near threshold, where the integrands vary on a scale of 1/(1 + 2|y_θ|) (they grow like
    # e^{u²}; far below it they decay like 1/|u| and 1/|u|³), sparse toward reset: half the nodes
    # evenly over the last 4 such scales, half cubically spaced over the rest.
    near = np.minimum(4.0 / (1.0 + 2.0 * np.abs(y_th)), y_th - y_r)
    s = np.linspace(0.0, 1.0, nodes // 2)
    far = (y_th - near)[:, None] - (y_th - near - y_r)[:, None] * (s ** 3)[::-1]
    x = np.concatenate([far[:, :-1], (y_th - near)[:, None] + near[:, None] * s], axis=1)
    ok = y_th < 26.0
    return np.where(ok[:, None], x, 0.0), ok


def _check_white(c: LIFConfig, what: str) -> None:
    if c.noisy and c.noise != "white":
        raise ValueError(f"{what} is the white-noise diffusion approximation; this LIFConfig has noise={c.noise!r}")


def lif_rate(current, config: LIFConfig | None = None, nodes: int = 600):
    """Stationary firing rate (Hz) of an LIF neuron under a constant ``current`` (A, float or
    array) plus its white noise — Siegert's first-passage formula (the diffusion approximation;
    Brunel 2000, J. Comput. Neurosci. 8:183, eq. 21):
    ``1/ν = t_ref + τ√π ∫_{y_r}^{y_θ} e^{u²}(1 + erf u) du`` with y = (V − μ)/σ, μ = V_rest + R·I
    and σ = R·noise_std (:class:`LIFConfig`'s white-noise convention). Without noise it is
    :func:`lif_fi_curve`; "ou" noise is not white and is refused. ``nodes``: trapezoid points.
    config: the neuron (None: the default LIFConfig). Returns ``current``'s shape.
    """
    import numpy as np
    from scipy.special import erfcx
    c = config or LIFConfig()
    _check_white(c, "lif_rate")
    I = np.asarray(current, dtype=float)
    if _white_sigma(c) == 0:
        return lif_fi_curve(I, c)
    x, ok = _siegert_nodes(I, c, nodes)
    # e^{u²}(1 + erf u) = erfcx(−u): stable for u < 0, where it decays like 1/(√π |u|).
    mass = np.trapezoid(erfcx(-x), x, axis=1)
    return np.where(ok, 1.0 / (c.t_ref + c.tau_m * np.sqrt(np.pi) * mass), 0.0).reshape(I.shape)


def lif_isi_cv(current, config: LIFConfig | None = None, nodes: int = 600):
    """Coefficient of variation of the interspike interval of an LIF neuron under a constant
    ``current`` (A, float or array) plus its white noise (Brunel 2000, Appendix A):
    ``CV² = 2π(ντ)² ∫_{y_r}^{y_θ} e^{x²} ∫_{−∞}^{x} e^{y²}(1 + erf y)² dy dx``, ν = :func:`lif_rate`.
    A renewal train's spike count over a long window has Fano factor CV². 0 without noise;
    1 where the neuron cannot fire. ``nodes``: trapezoid points of the outer integral. config: the
    neuron (None: the default LIFConfig). Returns the dimensionless CV, ``current``'s shape.
    """
    import numpy as np
    from scipy.special import erfcx
    c = config or LIFConfig()
    _check_white(c, "lif_isi_cv")
    I = np.asarray(current, dtype=float)
    if _white_sigma(c) == 0:
        return np.where(lif_fi_curve(I, c) > 0, 0.0, 1.0)
    if I.size > 16:   # the inner integral holds (entries, nodes, 200) values: bound its memory
        flat = I.ravel()
        return np.concatenate([lif_isi_cv(flat[i:i + 16], c, nodes) for i in range(0, flat.size, 16)]).reshape(I.shape)
    x, ok = _siegert_nodes(I, c, nodes)
    # Everything is scaled by e^{−Y}, Y = max(y_θ, 0)² (the integrands grow like e^{u²} up to y_θ),
    # and e^{x²} is taken inside the inner integral, so nothing over- or underflows:
    # CV² = 2π·outer_s / (t_ref/τ·e^{−Y} + √π·mass_s)².
    Y = np.maximum(x[:, -1:], 0.0) ** 2
    mass_s = np.trapezoid(erfcx(-x) * np.exp(-Y), x, axis=1)
    # Inner integral ∫_{−∞}^{x} erfcx(−y)² e^{x²−y²} dy: for x < 0 it decays within ~1/(2|x|) below
    # x, for x > 0 like e^{−y²} below 0; start where the integrand is < 1e-20 of its peak.
    lo = np.where(x < 0, x - 24.0 / (1.0 + 2.0 * np.abs(x)), -7.0)
    yy = x[:, :, None] - (x - lo)[:, :, None] * (np.linspace(0.0, 1.0, 200) ** 3)[::-1]
    h = (erfcx(-yy) * np.exp(-Y[:, :, None])) ** 2 * np.exp(x[:, :, None] ** 2 - yy ** 2)
    outer_s = np.trapezoid(np.trapezoid(h, yy, axis=2), x, axis=1)
    den = c.t_ref / c.tau_m * np.exp(-Y[:, 0]) + np.sqrt(np.pi) * mass_s
    cv = np.sqrt(np.maximum(2 * np.pi * outer_s / den ** 2, 0.0))
    return np.where(ok, cv, 1.0).reshape(I.shape)


def lif_current_for_rate(rate, config: LIFConfig | None = None, points: int = 800):
    """The constant current (A) at which this LIF fires at ``rate`` (Hz, array) on average —
    the inverse of :func:`lif_rate` (noise included), by interpolation on its curve.

    Rates must lie in [ν(I = 0), 1/t_ref); ValueError otherwise. Without noise ν(0) = 0 and
    rate 0 maps to the rheobase (the edge of firing). config: the neuron (None: the default
    LIFConfig); points: the currents the curve is evaluated at. Returns ``rate``'s shape.
    """
    import numpy as np
    c = config or LIFConfig()
    r = np.asarray(rate, dtype=float)
    gap = c.V_threshold - c.V_rest
    # Drives from rest to far above threshold, denser near it where the curve bends.
    drive = np.concatenate([np.linspace(0.0, gap, points // 4),
                            gap * (1 + np.geomspace(1e-4, 200.0, points - points // 4))])
    nu = lif_rate(drive / c.R, c)
    nu = np.maximum.accumulate(nu)
    top = 1.0 / c.t_ref if c.t_ref > 0 else np.inf
    if np.any(~np.isfinite(r)) or np.any(r < nu[0] - 1e-9) or np.any(r >= min(top, nu[-1])):
        raise ValueError(f"rates must lie in [{nu[0]:.3g}, {min(top, nu[-1]):.3g}) Hz for this LIFConfig, "
                         f"got {np.nanmin(r):.3g}–{np.nanmax(r):.3g}")
    # The last drive of every flat stretch: rate 0 without noise maps to the rheobase.
    keep = np.append(np.diff(nu) > 0, True)
    return np.interp(r, nu[keep], drive[keep]) / c.R
