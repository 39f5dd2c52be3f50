"""Whether the image's expansion follows the accelerometer: the test that vision can fix the speed at all.

FLIVVER reads the speed from how the expansion changes as the camera accelerates: for a field at
depth d, ṙ − r² = a/d (the readout's terms, low-passed alike), so across frames the fields'
pooled ṙ̄ − r²̄ rises and falls with the forward acceleration a, with a positive slope 1/d. Where it
does not — the image is stabilised against the body, the scene moves, the flow is noise — κ = a/v is
noise, and a filter that takes it at its stated error settles on whatever v makes that noise smallest
(v ≈ 0 for a noisy κ, errors in variables), with a confident, wrong σ.

:func:`coupling_test` measures it: the correlation ρ of ṙ̄ − r²̄ (the fields' median) with the
low-passed acceleration over a window, as Fisher's z with the window's effective number of
independent samples (the low-pass leaves about 2·cutoff of them per second),
z = atanh(ρ)·√(n_eff − 3). Each frame's window then says one of three things:

* **coupled** — z reached ``coupling_z`` (one-sided: a negative slope is not a depth). Early in a window
  (an online run's first seconds, a short record) fewer samples need a stronger correlation for that.
* **refuted** — a whole window over which the acceleration varied (its low-passed std at least
  ``power_m_s2``) while z stayed below ``refute_z`` (0: no positive correlation at all): the expansion had a
  change to follow and did not. An accelerometer error that the filter models but vision does not see (the
  gravity error turning with the camera) weakens the correlation without reversing it.
* neither — a steady pace (nothing to follow, so nothing to refute), or a weak correlation.

Before a window is whole (an online run's first seconds, a record shorter than the window) the test has
fewer samples. With at most 3 effective ones (1.5 s at the default 1 Hz) it cannot tell, and the
posterior's std decides alone (a 1.2 s clip is still read) unless the acceleration has varied (by
``power_m_s2``, as a refutation needs) and the correlation so far is negative: an expansion falling as the
camera speeds up is a κ of the wrong sign, which would pin v near 0 with a σ the posterior alone cannot doubt
(a real walk's stabilised image through the EMD front end). Beyond that a frame
is answered provisionally where the correlation so far is as strong as a whole window needs,
atanh(ρ)·√(n_full − 3) ≥ ``coupling_z`` (``provisional``), which locks nothing.

:func:`vision_locked` turns that into where vision has fixed the speed: from a coupled frame (or one
the rest bound holds at v = 0) on, until a refuted one. In between v̂ is reported while σ stays within
bounds; where no measurement of vision enters the filter, the integrated accelerometer alone carries it,
its σ growing as the accelerometer's errors allow. Where vision is refuted the filter takes no κ and no
reversal from it, and the readout reports no speed, whatever its posterior says, and tells the user why.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CouplingTest", "coupling_test", "expansion_coupling", "window_full", "vision_locked", "LockState"]


def _window_sums(x: np.ndarray, w: int, causal: bool) -> np.ndarray:
    """Sums of x (n,) over windows of w frames: trailing (frames k − w + 1 … k, fewer at the start) or centred."""
    c = np.concatenate([[0.0], np.cumsum(x)])
    n = len(x)
    k = np.arange(n)
    if causal:
        lo, hi = np.maximum(k - w + 1, 0), k + 1
    else:
        lo, hi = np.maximum(k - w // 2, 0), np.minimum(k + w - w // 2, n)
    return c[hi] - c[lo]


def _window_correlation(g, a, dt: float, window_s: float, cutoff_hz: float, causal: bool):
    """ρ (n,) of g with a over each frame's window (0 where either is constant or fewer than 4 effective
    samples), the window's effective samples n_eff (n,), a's std over it (n,) in a's units, and the sign of the
    correlation however few the samples (n,): ±1, 0 where either is constant or the window holds under 3 frames."""
    g = np.asarray(g, float)
    a = np.asarray(a, float)
    ok = np.isfinite(g) & np.isfinite(a)
    g0, a0, m = np.where(ok, g, 0.0), np.where(ok, a, 0.0), ok.astype(float)
    w = max(2, int(round(window_s / dt)))
    n = _window_sums(m, w, causal)
    sg, sa = _window_sums(g0, w, causal), _window_sums(a0, w, causal)
    sgg, saa, sga = (_window_sums(g0 * g0, w, causal), _window_sums(a0 * a0, w, causal),
                     _window_sums(g0 * a0, w, causal))
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = sga - sg * sa / n
        var_g, var_a = sgg - sg ** 2 / n, saa - sa ** 2 / n
        rho = cov / np.sqrt(var_g * var_a)
        sd_a = np.sqrt(np.maximum(var_a, 0.0) / n)
    n_eff = n * dt * 2.0 * cutoff_hz
    defined = np.isfinite(rho) & (var_g > 0) & (var_a > 0) & (n >= 3)
    sign = np.where(defined, np.sign(rho), 0.0)
    rho = np.clip(np.where(defined & (n_eff > 3.0), rho, 0.0), -0.999999, 0.999999)
    return rho, n_eff, np.where(n > 0, sd_a, 0.0), sign


def expansion_coupling(g, a, dt: float, window_s: float, cutoff_hz: float, causal: bool) -> np.ndarray:
    """Fisher's z of the correlation between the pooled ṙ̄ − r²̄ and the acceleration, frame by frame.

    Parameters
    ----------
    g : ndarray, (n,)
        1/s²: the fields' median ṙ̄ − r²̄ (NaN where no field is valid).
    a : ndarray, (n,)
        m/s²: the low-passed forward acceleration, paired with ``g`` in time.
    dt : float
        s: the frame interval.
    window_s : float
        s: the window the correlation is taken over.
    cutoff_hz : float
        Hz: the low-pass both signals went through; sets the effective samples per second (2·cutoff).
    causal : bool
        True: the window ends at each frame (frames so far at the start); False: centred on it.

    Returns
    -------
    ndarray, (n,)
        z (dimensionless), positive where the expansion rises with the acceleration; 0 where the window
        holds fewer than four effective samples or either signal is constant.
    """
    rho, n_eff, _, _ = _window_correlation(g, a, dt, window_s, cutoff_hz, causal)
    return np.arctanh(rho) * np.sqrt(np.maximum(n_eff - 3.0, 0.0))


@dataclass
class CouplingTest:
    """What each frame's window says of vision's coupling to the accelerometer (:func:`coupling_test`).

    Parameters
    ----------
    z : ndarray, (n,)
        Fisher's z of the correlation over the window (:func:`expansion_coupling`).
    coupled : ndarray of bool, (n,)
        The expansion followed the acceleration: vision informs v here.
    refuted : ndarray of bool, (n,)
        A whole window over which the acceleration varied and the expansion did not follow it.
    accel_std : ndarray, (n,)
        m/s²: the low-passed acceleration's std over the window (the test's power).
    full : ndarray of bool, (n,)
        The window holds a whole ``window_s`` of record (:func:`window_full`).
    provisional : ndarray of bool, (n,)
        A window not yet whole that cannot tell (at most 3 effective samples, and not correlated negatively
        while the acceleration varied) or already correlates as a whole one must: the posterior may answer
        there, though vision is not locked.
    """

    z: np.ndarray
    coupled: np.ndarray
    refuted: np.ndarray
    accel_std: np.ndarray
    full: np.ndarray
    provisional: np.ndarray


def coupling_test(g, a, dt: float, window_s: float, cutoff_hz: float, causal: bool, threshold: float,
                  refute_z: float, power_m_s2: float) -> CouplingTest:
    """Each frame's verdict on whether the expansion follows the acceleration (see the module's docstring).

    Parameters
    ----------
    g, a, dt, window_s, cutoff_hz, causal
        As :func:`expansion_coupling` takes them.
    threshold : float
        The z that says coupled; 0 or less: every frame is coupled and none refuted (the test is off).
    refute_z : float
        A whole window with z below this, while the acceleration varied, refutes vision.
    power_m_s2 : float
        m/s²: the least std of the low-passed acceleration over a window for it to refute.

    Returns
    -------
    CouplingTest
    """
    rho, n_eff, sd_a, sign = _window_correlation(g, a, dt, window_s, cutoff_hz, causal)
    z = np.arctanh(rho) * np.sqrt(np.maximum(n_eff - 3.0, 0.0))
    n = len(rho)
    full = window_full(n, dt, window_s, causal)
    if threshold <= 0:
        return CouplingTest(z, np.ones(n, bool), np.zeros(n, bool), sd_a, full, np.ones(n, bool))
    coupled = z >= threshold
    refuted = full & (z < refute_z) & (sd_a >= power_m_s2)
    n_full = max(2, int(round(window_s / dt))) * dt * 2.0 * cutoff_hz
    as_whole = np.arctanh(rho) * np.sqrt(max(n_full - 3.0, 0.0)) >= threshold
    against = (sign < 0) & (sd_a >= power_m_s2)
    provisional = ~full & (((n_eff <= 3.0) & ~against) | as_whole)
    return CouplingTest(z, coupled, refuted, sd_a, full, provisional)


def window_full(n: int, dt: float, window_s: float, causal: bool) -> np.ndarray:
    """Frames (n,) whose coupling window holds a whole ``window_s`` (s) of record (online, not the first seconds;
    offline, a record at least that long)."""
    w = max(2, int(round(window_s / dt)))
    if causal:
        return np.arange(n) + 1 >= w
    return np.full(n, n >= w)


def vision_locked(test: CouplingTest, still, passed_zero, causal: bool) -> np.ndarray:
    """Where vision has fixed the speed: from a coupled frame, one the rest bound holds at v = 0 or whose expansion
    has fallen to a stop (:func:`lobula.readout.stop_measurement`), or a reversal of
    the expansion's sign (v passed 0) that a whole window has since let stand, until a refuted frame.

    A reversal needs no κ, but a flow that is noise also changes sign; it locks only once a whole window
    around it has had the chance to refute the image and has not.

    Parameters
    ----------
    test : CouplingTest
    still, passed_zero : ndarray of bool, (n,)
        Frames the rest bound holds v at 0 or a stop is read at, and frames a reversal was seen at.
    causal : bool
        True: from the frames so far. False: the whole record; the smoother carries what a frame fixes over
        every frame not parted from it by a refuted one.

    Returns
    -------
    ndarray of bool, (n,)
    """
    refuted = np.asarray(test.refuted, bool)
    passed_zero = np.asarray(passed_zero, bool) & ~refuted
    n = len(refuted)
    k = np.arange(n)
    if n == 0:
        return np.zeros(0, bool)
    hit = (np.asarray(test.coupled, bool) | np.asarray(still, bool)) & ~refuted
    if causal:
        last_refuted = np.maximum.accumulate(np.where(refuted, k, -1))
        pending = np.maximum.accumulate(np.where(passed_zero, k, -1)) > last_refuted
        hit |= pending & test.full & ~refuted
        return (np.maximum.accumulate(np.where(hit, k, -1)) > last_refuted) & ~refuted
    hit |= passed_zero & test.full
    stretch = np.cumsum(refuted)  # stretches between refuted frames
    has_hit = np.bincount(stretch, weights=hit.astype(float), minlength=int(stretch[-1]) + 1) > 0
    return has_hit[stretch] & ~refuted


@dataclass
class LockState:
    """:func:`vision_locked`'s causal rule a frame at a time, for an estimator that sees frames as they come.

    Parameters
    ----------
    locked : bool
        Vision has fixed the speed.
    passed_zero : bool
        A reversal was seen that no refuted frame has since undone, waiting for a whole window.
    """

    locked: bool = False
    passed_zero: bool = False

    def step(self, coupled: bool, still: bool, passed_zero: bool, full: bool, refuted: bool) -> bool:
        """Take one frame's verdicts (as :func:`vision_locked` takes them) and return whether vision is locked."""
        self.passed_zero = (self.passed_zero or passed_zero) and not refuted
        hit = coupled or still or (self.passed_zero and full)
        self.locked = (self.locked or hit) and not refuted
        return self.locked
