"""What vision and the accelerometer measure of v: the readout's terms and its per-frame measurements.

Vision gives, per frame, each field's velocity v_f = a·r̄/(ṙ̄ − r²̄) (:func:`vision_measurement`),
the ratio κ = a/v that needs no accelerometer (:func:`ratio_measurement`, :func:`physical_kappa`),
a bound on |v| where nothing expands (:func:`rest_measurement`), the moments v passed through 0
(:func:`reversal_measurement`) and v's sign (:func:`expansion_sign`); the accelerometer says where
the camera is not starting or stopping (:func:`accelerometer_level`, :func:`accelerometer_steady`).
:func:`readout_terms` low-passes the fields' rates and the acceleration alike for the kalman readout.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from .config import ReadoutConfig
from .filters import (_integral, _lag, butterworth, difference_mean, gaussian_lowpass, staggered_difference,
                      vision_runs)

#: the fields' signed median r̄ within this many standard errors of 0: no expansion detected (see rest_measurement)
NO_EXPANSION_SE = 3.0
#: s: how long the fields' expansion must have held one clear sign before it counts as v's (expansion_sign)
SIGN_PERSIST_S = 0.5
#: s: the longest stretch without a clear expansion sign across which a reversal is read (see reversal_measurement)
REVERSAL_MAX_GAP_S = 1.0
#: m/s²: a forward acceleration below this gives the acceleration's direction nothing to go by
#: (:func:`acceleration_heading`): the accelerometer's noise and offset, filtered, reach about that
ACCEL_HEADING_FLOOR_M_S2 = 0.1


@dataclass
class MaterialRates:
    """Field rates taken along the image content (the material derivative), time-major (n, F).

    For each frame k: r̄, r²̄ averaged over the *same scene points* at both ends of a difference
    and ṙ̄ = Dr/Dt over those points, all in the camera's orientation at frame k
    (lobula.receptive_field.MaterialFields); NaN where no difference exists.

    Parameters
    ----------
    r : ndarray, (n, F)
        1/s: r̄.
    r2 : ndarray, (n, F)
        1/s²: r²̄.
    r_dot : ndarray, (n, F)
        1/s²: ṙ̄ = Dr/Dt.
    moment : ndarray, (n, F, 2), optional
        The fields' Σw(p − e)/Σw|p − e|² about the heading e the rates were read about (normalised
        coordinates⁻¹), which says how a moving heading enters ṙ̄ (:func:`field_axes`).
    """

    r: np.ndarray
    r2: np.ndarray
    r_dot: np.ndarray
    moment: np.ndarray | None = None


def acceleration_heading(accel: np.ndarray, dt: float, window_s: float, causal: bool,
                         orientation: np.ndarray | None = None) -> np.ndarray:
    """ê (n, 2): the direction the camera accelerates along, as a heading (d_x/d_z, d_y/d_z) in the camera frame,
    d the principal axis of the acceleration over each frame's window (trailing online, centred offline).

    A platform accelerates along its heading, so ê stands for the heading in ė = (A_xy − e·A_z)/V_z
    (:func:`field_axes`), leaving the drift, bounce and sway that move the heading: the heading the fields were
    read about may err (a pitched camera whose fit lags), and A_xy − e·A_z would read that error as motion.
    The axis is found in a frame that does not turn with the camera (``orientation``), so a camera that pans
    while its platform runs straight keeps one direction, turned into each frame's camera.

    Parameters
    ----------
    accel : ndarray, (n, 3)
        m/s²: the gravity-free acceleration, camera frame.
    dt : float
        s: the frame interval.
    window_s : float
        s.
    causal : bool
    orientation : ndarray, (n, 3, 3), optional
        Camera → a fixed frame at each frame (None: the camera does not turn).

    Returns
    -------
    ndarray, (n, 2)
        Where the window's acceleration is under ACCEL_HEADING_FLOOR_M_S2 (rms), or its axis lies within 45°
        of the image plane, the optical axis (0, 0).
    """
    from .coupling import _window_sums

    a = np.asarray(accel, float)
    rot = None if orientation is None else np.asarray(orientation, float)
    a_ref = a if rot is None else np.einsum("nij,nj->ni", rot, a)
    w = max(1, int(round(window_s / dt)))
    outer = (a_ref[:, :, None] * a_ref[:, None, :]).reshape(len(a), 9)
    m = np.stack([_window_sums(outer[:, j], w, causal) for j in range(9)], axis=1).reshape(len(a), 3, 3)
    count = _window_sums(np.ones(len(a)), w, causal)
    vals, vecs = np.linalg.eigh(m)
    d = vecs[:, :, -1]  # the principal axis, in the fixed frame
    d_cam = d if rot is None else np.einsum("nji,nj->ni", rot, d)
    d_cam = d_cam * np.sign(d_cam[:, 2:3] + (d_cam[:, 2:3] == 0))
    strong = (vals[:, -1] / count >= ACCEL_HEADING_FLOOR_M_S2 ** 2) & (d_cam[:, 2] > np.sqrt(0.5))
    return np.where(strong[:, None], d_cam[:, :2] / np.where(strong, d_cam[:, 2], 1.0)[:, None], 0.0)


def field_axes(moment: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """ñ_f (n, F, 3), camera frame: the axis along which each material field's κ measures the acceleration.

    The fields read both ends of ṙ̄'s difference about one heading, so a heading that moves enters
    ṙ̄ (:class:`lobula.receptive_field.MaterialFields`): each field's (ṙ̄ − r²̄)/r̄ is ⟨A, ñ_f⟩/V_z, with
    A the camera's 3-D acceleration (gravity-free, camera frame), ñ_f = (−m_x, −m_y, 1 + ⟨e, m⟩) from
    its moment m (about the heading the rates were read about) and e the heading the velocity has
    (its direction of acceleration, :func:`acceleration_heading`, stands for it). A field without a
    moment measures along the optical axis (0, 0, 1).

    Parameters
    ----------
    moment : ndarray, (n, F, 2)
        :attr:`MaterialRates.moment`, normalised coordinates⁻¹.
    heading : ndarray, (n, 2)
        The velocity's heading e, normalised coordinates.

    Returns
    -------
    ndarray, (n, F, 3)
    """
    m = np.nan_to_num(np.asarray(moment, float))
    e = np.nan_to_num(np.asarray(heading, float))
    return np.concatenate([-m, 1.0 + np.einsum("nc,nfc->nf", e, m)[..., None]], axis=2)


def field_velocity(r, r2, r_dot, a):
    """Per-field velocity v_f = a·r̄/(ṙ̄ − r²̄) and implied depth d_f = a/(ṙ̄ − r²̄).

    Parameters
    ----------
    r : ndarray, (n, F)
        1/s: r̄.
    r2 : ndarray, (n, F)
        1/s²: r²̄.
    r_dot : ndarray, (n, F)
        1/s²: ṙ̄.
    a : ndarray, (n,) or (n, F)
        m/s²: the forward acceleration, or each field's (:func:`field_axes`).

    Returns
    -------
    v_f : ndarray, (n, F)
        m/s (inf or NaN where ṙ̄ = r²̄).
    d_f : ndarray, (n, F)
        m.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = r_dot - r2
        depth = (a if np.ndim(a) == 2 else a[:, None]) / denom
        return r * depth, depth


def nanmedian_rows(x: np.ndarray) -> np.ndarray:
    """The median of each row, NaN left out: ``np.nanmedian(x, axis=1)`` to the bit, without its warnings.

    numpy computes a small array's row medians through masked arrays, 6x slower than sorting the rows
    once (NaN sorts last) and averaging the two middle values of the finite ones, as it does.

    Parameters
    ----------
    x : ndarray, (n, F)
        Any units U.

    Returns
    -------
    ndarray, (n,)
        U, NaN where a row has no value that is not NaN.
    """
    x = np.asarray(x, float)
    if x.shape[1] == 0:
        return np.full(len(x), np.nan)
    s = np.sort(x, axis=1)
    n = np.count_nonzero(~np.isnan(x), axis=1)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[:, None], 1)[:, 0]
    hi = np.take_along_axis(s, np.maximum(n // 2, 0)[:, None], 1)[:, 0]
    with np.errstate(invalid="ignore"):  # −inf and +inf in the middle: NaN, as numpy's
        return np.where(n > 0, (lo + hi) / 2, np.nan)


def median_and_error(values: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median over fields, NaN left out, and its standard error 1.253·1.4826·MAD/√n.

    1.253 is the median's efficiency for Gaussian samples, 1.4826 turns the MAD into σ.

    Parameters
    ----------
    values : ndarray, (n_frames, F)
        Any units U; NaN where a field has none.
    n : ndarray, (n_frames,)
        The fields counted per frame.

    Returns
    -------
    med : ndarray, (n_frames,)
        U, NaN where a frame has no value.
    se : ndarray, (n_frames,)
        U.
    """
    med = nanmedian_rows(values)
    with np.errstate(invalid="ignore"):  # an infinite value less an infinite median
        mad = nanmedian_rows(np.abs(values - med[:, None]))
    return med, 1.253 * 1.4826 * mad / np.sqrt(np.maximum(n, 1))


def vision_measurement(r, r2, r_dot, a, cfg: ReadoutConfig):
    """One velocity measurement per frame from the fields, with its standard deviation.

    Fields are kept when their implied depth lies in [depth_min, depth_max] (d > 0 is
    geometry, not a tuning); a frame is informative when |a| ≥ accel_min and at least
    min_valid_fraction of fields are kept. The std is the median's standard error
    (1.253·1.4826·MAD/√n), floored.

    Parameters
    ----------
    r, r2, r_dot : ndarray, (n, F)
        1/s, 1/s², 1/s²: r̄, r²̄, ṙ̄.
    a : ndarray, (n,) or (n, F)
        m/s²: the forward acceleration, or each field's.
    cfg : ReadoutConfig

    Returns
    -------
    z : ndarray, (n,)
        m/s: the median of the kept fields' v_f, NaN where uninformative.
    std : ndarray, (n,)
        m/s, NaN where uninformative.
    v_f : ndarray, (n, F)
        m/s, NaN for rejected fields.
    """
    v_f, depth = field_velocity(r, r2, r_dot, a)
    ok = np.isfinite(v_f) & (depth >= cfg.depth_min_m) & (depth <= cfg.depth_max_m)
    ok &= np.abs(a if np.ndim(a) == 2 else a[:, None]) >= cfg.accel_min_m_s2
    v_f = np.where(ok, v_f, np.nan)
    n_ok = ok.sum(1)
    z, se = median_and_error(v_f, n_ok)
    std = np.maximum(se, cfg.meas_floor_m_s)
    enough = n_ok >= max(3, cfg.min_valid_fraction * r.shape[1])
    return np.where(enough, z, np.nan), np.where(enough, std, np.nan), v_f


def ratio_measurement(r, r2, r_dot, cfg: ReadoutConfig, keep=None, fields: bool = False):
    """Vision's a/v per frame, κ = median over fields of (ṙ̄ − r²̄)/r̄, and its standard error.

    No accelerometer enters: ṙ − r² = a/d and r = v/d, so their ratio is a/v for every
    field whatever its depth. Fields whose |r̄| is under a fifth of the frame's median
    |r̄| (nothing expanding there to measure) are left out, and so are fields outside
    ``keep`` (e.g. those whose implied depth is not physical); a frame needs at least
    min_valid_fraction of the fields.

    Parameters
    ----------
    r, r2, r_dot : ndarray, (n, F)
        1/s, 1/s², 1/s²: r̄, r²̄, ṙ̄.
    cfg : ReadoutConfig
    keep : ndarray of bool, (n, F), optional
        The fields that may count.
    fields : bool
        Also return the fields' ratios.

    Returns
    -------
    kappa : ndarray, (n,)
        1/s: κ, NaN where uninformative.
    std : ndarray, (n,)
        1/s, NaN where uninformative.
    k : ndarray, (n, F)
        1/s: each field's ratio, NaN for the fields left out (with ``fields`` only).
    """
    with warnings.catch_warnings(), np.errstate(divide="ignore", invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        ra = np.abs(r)
        ok = np.isfinite(r) & np.isfinite(r2) & np.isfinite(r_dot) & (ra >= 0.2 * nanmedian_rows(ra)[:, None])
        if keep is not None:
            ok &= keep
        k = np.where(ok, (r_dot - r2) / r, np.nan)
    n_ok = ok.sum(1)
    kap, std = median_and_error(k, n_ok)
    enough = (n_ok >= max(3, cfg.min_valid_fraction * r.shape[1])) & np.isfinite(kap)
    out = np.where(enough, kap, np.nan), np.where(enough, std, np.nan)
    return out + (k,) if fields else out


def signed_expansion(r: np.ndarray):
    """The fields' signed median expansion r̄ per frame, its standard error and the fields counted.

    What the rest bound and the reversals judge "expansion detected" on (|r̄| > NO_EXPANSION_SE·SE).

    Parameters
    ----------
    r : ndarray, (n, F)
        1/s, NaN where a field has none.

    Returns
    -------
    r_med : ndarray, (n,)
        1/s.
    se : ndarray, (n,)
        1/s.
    n : ndarray of int, (n,)
        The fields counted.
    """
    n = np.isfinite(r).sum(1)
    r_med, se = median_and_error(r, n)
    return r_med, se, n


def clear_expansion(r: np.ndarray, min_fields: int):
    """The fields' signed median r̄ and where it stands clear of zero.

    Clear: beyond NO_EXPANSION_SE standard errors, with at least max(3, ``min_fields``) fields —
    "expansion detected", as the reversals and the expansion's sign judge it.

    Parameters
    ----------
    r : ndarray, (n, F)
        1/s, NaN where a field has none.
    min_fields : int
        The fields a frame needs for its median to count.

    Returns
    -------
    r_med : ndarray, (n,)
        1/s.
    clear : ndarray of bool, (n,)
    """
    r_med, se, n = signed_expansion(r)
    return r_med, np.isfinite(r_med) & (n >= max(3, min_fields)) & (np.abs(r_med) > NO_EXPANSION_SE * se)


def expansion_sign(t: np.ndarray, r: np.ndarray, min_fields: int, persist_s: float = SIGN_PERSIST_S) -> np.ndarray:
    """The sign of v that the fields' expansion shows (causal).

    Every field's r̄ = v/d has the sign of v whatever its depth d > 0; the persistence keeps a
    moment's front-end fault (an expansion read with the wrong sign for 0.3 s, tests/test_readout.py) out.

    Parameters
    ----------
    t : ndarray, (n,)
        s.
    r : ndarray, (n, F)
        1/s, NaN where a field has none.
    min_fields : int
        The fields a frame needs for its median to count.
    persist_s : float
        s: how long the sign must have held.

    Returns
    -------
    ndarray, (n,)
        ±1 where the fields' signed median r̄ has lain beyond NO_EXPANSION_SE standard errors of 0, with
        that sign and at least ``min_fields`` fields, at every frame of the last ``persist_s`` seconds;
        NaN elsewhere.
    """
    r_med, clear = clear_expansion(r, min_fields)
    sgn = np.where(clear, np.sign(r_med), 0.0)
    t = np.asarray(t, float)
    start = np.searchsorted(t, t - persist_s, side="left")
    out = np.full(len(t), np.nan)
    for s in (-1.0, 1.0):
        # frames with this clear sign, counted: the window [start, k] must hold nothing else
        c = np.concatenate([[0], np.cumsum(sgn == s)])
        whole = (c[np.arange(1, len(t) + 1)] - c[start]) == (np.arange(len(t)) - start + 1)
        out[whole & (t - t[0] >= persist_s)] = s
    return out


def scene_depth(r, v_f, informative, coupled, dt: float, window_s: float, causal: bool, seen: float = np.nan):
    """m: the depth the rest bound takes, learned from the footage while vision measured it.

    Where translation makes the fields' r̄_f = v/d_f, their signed median is r̄_m = v/D with D the
    median of the fields' depths (1/x keeps the median's place), so |v| = |r̄_m|·D. Each frame on
    which vision has fixed the speed (``coupled``) and measures (``informative``) gives every field's
    depth d_f = v_f/r̄_f = a/(ṙ̄ − r²̄) (no v needed); a field that implies no physical depth (the
    sky, a far town, noise) counts as infinitely far, so a scene mostly beyond what the
    acceleration reveals has D = ∞ and no bound. D is each frame's median over fields, then the
    median over the last ``window_s`` (a frame whose ṙ̄ − r²̄ crosses zero says nothing), then the
    largest so far (online) or over the record (offline): the farthest the scene has been seen to be.
    Before any such frame there is no depth and no bound: "no flow" in a scene of unknown depth
    bounds nothing (a drone hovering 20 m up drifting at 0.3 m/s shows less flow than a still camera's
    noise).

    Parameters
    ----------
    r : ndarray, (n, F)
        1/s: the fields' r̄, NaN where a field has none.
    v_f : ndarray, (n, F)
        m/s: the fields' velocities a·r̄/(ṙ̄ − r²̄), NaN where rejected (:func:`vision_measurement`).
    informative, coupled : ndarray of bool, (n,)
        Frames with a vision measurement, and frames where it follows the accelerometer
        (:mod:`lobula.readout.coupling`).
    dt, window_s : float
        s: the frame interval and the window of the per-frame medians' median.
    causal : bool
        Online: the largest depth up to each frame (trailing windows); offline: over the record.
    seen : float
        m: the largest depth learned before the first frame (online, a stream's earlier rows; NaN: none).

    Returns
    -------
    ndarray, (n,)
        m: NaN where no depth has been learned, inf where the scene was too far to bound.
    """
    n = len(r)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = v_f / r
    d = np.where(np.isfinite(r), np.where(np.isfinite(d) & (d > 0), d, np.inf), np.nan)
    use = np.asarray(informative, bool) & np.asarray(coupled, bool) & (np.isfinite(r).sum(1) >= 3)
    per_frame = np.full(n, np.nan)
    if use.any():
        per_frame[use] = nanmedian_rows(d[use])
    w = max(1, int(round(window_s / dt)))
    padded = np.concatenate([np.full(w - 1, np.nan), per_frame])
    windowed = nanmedian_rows(np.lib.stride_tricks.sliding_window_view(padded, w))
    if causal:
        return np.fmax.accumulate(np.concatenate([[seen], windowed]))[1:]
    return np.full(n, np.fmax(np.nanmax(windowed) if np.any(~np.isnan(windowed)) else np.nan, seen))


def rest_measurement(r, cfg: ReadoutConfig, depth_m=None, expansion=None):
    """v = r·d with 0 < d ≤ the scene's depth: no detectable expansion bounds |v|.

    Translation makes every field's r̄ = v/d of one sign (v's), while flow noise and residual
    rotation scatter the fields' r̄ about zero (rotation's divergence is odd across the image).
    So the fields' *signed* median r̄_m, known to within its standard error SE
    (1.253·1.4826·MAD/√n), tells: where |r̄_m| ≤ 3·SE no expansion is detected (3·SE, not 2·SE:
    r̄ also carries small non-translational biases — an epipole that wanders while nothing
    moves, a derotation with a biased gyro — which on the real still EuRoC sequence 2·SE calls
    motion on a third of the frames), and the speed
    is bounded by |v| ≤ D·(|r̄_m| + 2·SE) at 95%, that bound being the measurement's 2σ, with D
    the fields' median depth (:func:`scene_depth`).
    (The median of |r̄| would count the noise as motion: a still camera's DIS flow noise alone
    is ~0.02 1/s per field, which at 5 m is 0.1 m/s.) Where expansion is detected the camera
    moves, and a bound resting on a depth would only pull v̂ toward 0: not used.

    Parameters
    ----------
    r : ndarray, (n, F)
        1/s, NaN where a field has none.
    cfg : ReadoutConfig
    depth_m : float or ndarray, (n,), optional
        m: D, NaN or inf where unknown or unbounded (no bound); None: ``cfg.rest_depth_max_m``.
    expansion : tuple of ndarray, optional
        :func:`signed_expansion` of ``r``, where the caller has it already (None: computed here).

    Returns
    -------
    z : ndarray, (n,)
        m/s: 0 where the bound is used, NaN elsewhere.
    std : ndarray, (n,)
        m/s, NaN where the bound is not used.
    """
    if depth_m is None:
        if cfg.rest_depth_max_m is None:
            raise ValueError("rest_measurement needs the scene's depth: depth_m, or ReadoutConfig.rest_depth_max_m")
        depth_m = cfg.rest_depth_max_m
    r_med, se, n = signed_expansion(r) if expansion is None else expansion
    with np.errstate(invalid="ignore"):
        std = np.maximum(0.5 * np.asarray(depth_m, float) * (np.abs(r_med) + 2.0 * se), cfg.meas_floor_m_s)
    # It is a bound, not a noisy sample: repeating a loose bound frame after frame must
    # not add up to confidence, so it only counts where it alone would be decisive.
    use = (np.isfinite(r_med) & np.isfinite(std) & (n >= max(3, cfg.min_valid_fraction * r.shape[1]))
           & (np.abs(r_med) <= NO_EXPANSION_SE * se) & (std <= 0.5 * cfg.max_std_m_s))
    return np.where(use, 0.0, np.nan), np.where(use, std, np.nan)


def reversal_measurement(t, r, a, min_fields: int = 3, stamp_error_s: float = 0.0,
                         persist_s: float = SIGN_PERSIST_S):
    """Where v passed through 0: the frames at which the fields' expansion is seen to change sign.

    Every field's r̄ = v/d has v's sign (d > 0), so where the fields' signed median r̄ stands clear
    of zero (|r̄| > 3·SE, as :func:`rest_measurement` judges "expansion detected") at frame i and
    again at a later frame j with the other sign, and nowhere clearly in between, v was 0 at some
    t* in [t_i, t_j] — whatever the depths (a far backdrop only makes r̄ small, never of the
    wrong sign). Each sign must hold for ``persist_s`` on its side of the change, its run of clear
    frames (frames in between may be unclear) spanning that long: a flow that is noise, a front-end
    fault or a walker's bob also flips r̄'s sign, for a moment, and the columns of a front end that
    has just started have shown no sign before their first frame. t* is interpolated linearly in r̄
    between i and j, and is uncertain by the gap's uniform spread (t_j − t_i)/√12 and by how far the
    rates' stamps may be off (``stamp_error_s``, 1σ, in quadrature), which turns into a velocity
    error of |a|·that: the acceleration's own offset is still unknown here, so
    :func:`kalman_velocity` takes |a| as its posterior has it. Gaps longer than REVERSAL_MAX_GAP_S
    are skipped (v may have crossed more than once). Each reversal is known at the first frame k
    at least ``persist_s`` after j (online: once the new sign has held); the four arrays returned
    are NaN except at those frames k.

    Parameters
    ----------
    t : ndarray, (n,)
        s.
    r : ndarray, (n, F)
        1/s: the fields' expansion rates at fixed pixels (the newest, not low-passed).
    a : ndarray, (n,)
        m/s²: the forward acceleration as read (offset and all).
    min_fields : int
        The fields a frame needs for its median to count.
    stamp_error_s : float
        s (1σ): how far the rates' stamps may be off.
    persist_s : float
        s: how long each sign must hold on its side of the change.

    Returns
    -------
    shift : ndarray, (n,)
        m/s: the integrated reading from t* to t_k (the measurement of v(t_k − delay) + ∫a, as the
        filter's rows take it).
    time_std : ndarray, (n,)
        s: t*'s std.
    delay : ndarray, (n,)
        s: t_k − t*.
    accel : ndarray, (n,)
        m/s²: the mean reading over [t_i, t_j].
    """
    t = np.asarray(t, float)
    n = len(t)
    r_med, clear = clear_expansion(r, min_fields)
    idx = np.flatnonzero(clear)
    flip = np.flatnonzero(np.sign(r_med[idx[1:]]) != np.sign(r_med[idx[:-1]]))
    i, j = idx[flip], idx[flip + 1]
    # Each sign's run of clear frames spans persist_s: the old one began that long before i (at the
    # previous change, or the first clear frame), the new one lasts that long after j (to the next change,
    # or to k, where the reversal is known).
    k = np.searchsorted(t, t[j] + persist_s, side="left")
    began = np.concatenate([t[idx[:1]], t[j[:-1]]])
    ends = np.concatenate([t[i[1:]], [np.inf]])
    keep = ((t[j] - t[i] <= REVERSAL_MAX_GAP_S) & (k < n)
            & (t[i] - began >= persist_s) & (ends - t[j] >= persist_s))
    i, j, k = i[keep], j[keep], k[keep]
    t_star = t[i] + (t[j] - t[i]) * np.abs(r_med[i]) / (np.abs(r_med[i]) + np.abs(r_med[j]))
    cum = _integral(a, t)
    out = tuple(np.full(n, np.nan) for _ in range(4))
    out[0][k] = cum[k] - np.interp(t_star, t, cum)
    out[1][k] = np.hypot((t[j] - t[i]) / np.sqrt(12.0), stamp_error_s)
    out[2][k] = t[k] - t_star
    a_sum = np.concatenate([[0.0], np.cumsum(a)])
    out[3][k] = (a_sum[j + 1] - a_sum[i]) / (j - i + 1)  # the mean reading over frames i..j
    return out


#: the largest ratio v(t)/v(t − Δ) (its 2σ upper end) at which the fields' expansion reads a stop
#: (:func:`stop_measurement`)
STOP_RATIO_MAX = 0.1
#: s: how far back :func:`stop_measurement` looks for the expansion a stop is read against
STOP_LOOKBACK_S = 3.0
#: the most the fields' depth may have grown (a factor less one, exp(∫|r̄|) − 1) between the two frames a
#: stop is read from
STOP_DEPTH_CHANGE_MAX = 1.0


def stop_measurement(t, r, a, min_fields: int = 3, persist_s: float = SIGN_PERSIST_S,
                     ratio_max: float = STOP_RATIO_MAX, lookback_s: float = STOP_LOOKBACK_S, expansion=None):
    """Where the camera has nearly stopped: v(t) = ρ·v(t − Δ), read from how far the expansion has fallen.

    Every field's r̄ = v/d, so where the same scene is seen at two moments the fields' signed median
    r̄_m falls with v: r̄_m(t)/r̄_m(t − Δ) = v(t)/v(t − Δ) · d(t − Δ)/d(t), whatever the depth. Between
    the two, tracked points draw nearer by ∫v, which changes d by at most a factor exp(∫|r̄_m|). Where
    that is under 1 + STOP_DEPTH_CHANGE_MAX and r̄_m has fallen below ``ratio_max`` of what it was (its
    2σ upper end, the depth change included), the ratio ρ = r̄_m(t)/r̄_m(t − Δ) measures v(t)/v(t − Δ)
    with no depth and no κ. It is what tells a stop from a constant deceleration: braking to a stop,
    κ = −1/(time to stop) fits any offset of the accelerometer, while v falling to a few percent of
    what it was pins the offset the accelerometer integrates through the stop. The reference t − Δ is
    the frame of clear expansion (|r̄_m| > NO_EXPANSION_SE·SE) within ``lookback_s`` before t that
    bounds ρ tightest, and the fall must have held for ``persist_s`` (a frame or two of flow that reads
    nothing is a front-end fault, not a stop). A scene that changes between the two at speed (a camera
    leaving a corridor for open ground) lowers r̄_m as well and would be read as a stop: a known limit.

    Parameters
    ----------
    t : ndarray, (n,)
        s, uniformly spaced.
    r : ndarray, (n, F)
        1/s: the fields' expansion rates (as the rest bound judges them).
    a : ndarray, (n,)
        m/s²: the forward acceleration as read (offset and all).
    min_fields : int
        The fields a frame needs for its median to count.
    persist_s : float
        s: how long the fall must have held.
    ratio_max : float
        The largest 2σ upper end of ρ taken as a stop.
    lookback_s : float
        s: the farthest back the reference frame may lie.
    expansion : tuple of ndarray, optional
        :func:`signed_expansion` of ``r``, where the caller has it already (None: computed here).

    Returns
    -------
    shift : ndarray, (n,)
        m/s: the reading integrated over [t − Δ, t] (v(t − Δ) = the filter's row for Δ − shift).
    ratio : ndarray, (n,)
        ρ, the measured v(t)/v(t − Δ).
    ratio_std : ndarray, (n,)
        ρ's std: the two medians' standard errors and the depth change.
    delay : ndarray, (n,)
        s: Δ.
    All NaN but where a stop is read.
    """
    t = np.asarray(t, float)
    n = len(t)
    out = tuple(np.full(n, np.nan) for _ in range(4))
    if n < 2:
        return out
    dt = float(np.median(np.diff(t)))
    r_med, se, count = signed_expansion(r) if expansion is None else expansion
    clear = np.isfinite(r_med) & (count >= max(3, min_fields)) & (np.abs(r_med) > NO_EXPANSION_SE * se)
    cum_r = _integral(np.abs(np.nan_to_num(r_med)), t)
    # The reference of frame k, among frames k − w … k − 1 of clear expansion: the one that bounds ρ tightest,
    # (|r̄_m| − 2·SE)·exp(∫|r̄_m|) largest at the reference (the later, the less the depth may have changed).
    with np.errstate(divide="ignore", invalid="ignore"):
        score = np.where(clear & (np.abs(r_med) > 2.0 * se), np.log(np.abs(r_med) - 2.0 * se) + cum_r, -np.inf)
    w = max(1, int(round(lookback_s / dt)))
    window = np.lib.stride_tricks.sliding_window_view(np.concatenate([np.full(w, -np.inf), score]), w)[:n]
    j = np.arange(n) - w + np.argmax(window, axis=1)
    has_ref = np.isfinite(window.max(axis=1))
    j = np.where(has_ref, j, np.arange(n))
    growth = np.exp(cum_r - cum_r[j]) - 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        ref = np.abs(r_med[j])
        rho = r_med / r_med[j]
        rho_hi = (np.abs(r_med) + 2.0 * se) / (ref - 2.0 * se[j]) * (1.0 + growth)
        rho_std = np.hypot(se, np.abs(rho) * se[j]) / ref + np.abs(rho) * growth
        fallen = (has_ref & np.isfinite(r_med) & (count >= max(3, min_fields)) & (ref > 2.0 * se[j])
                  & (rho_hi <= ratio_max) & (growth <= STOP_DEPTH_CHANGE_MAX))
    p = max(1, int(round(persist_s / dt)))
    run = np.concatenate([[0], np.cumsum(fallen)])
    held = fallen & (np.arange(n) >= p) & (run[np.arange(1, n + 1)] - run[np.maximum(np.arange(n) + 1 - p, 0)] == p)
    k = np.flatnonzero(held)
    cum = _integral(a, t)
    out[0][k] = cum[k] - cum[j[k]]
    out[1][k] = rho[k]
    out[2][k] = rho_std[k]
    out[3][k] = t[k] - t[j[k]]
    return out


def accelerometer_level(a: np.ndarray, dt: float, change_max: float, causal: bool = False):
    """The forward accelerometer reading averaged over 5 frames, and how far it may stray while nothing happens.

    A vibrating platform (a real drone's running rotors) shakes the reading far beyond the
    sensor's own noise: the bar is raised to 5× the rms of what the 5-frame average leaves out
    of white noise of the reading's own level (≈ 11σ of the average, ~2.7× the range white noise
    spans in a 1 s window), over the last 5 s online, the 5 s around the frame offline. (EuRoC
    V1_01's still start ends in a −0.1 → −0.29 m/s² step over 0.8 s — rotors spinning up or the
    take-off beginning; the copy has no ground truth to tell; at 3× that bar loses the rest bound
    and v̂ drifts to an RMS of 0.011 m/s.) That level is read from the second differences
    (E[(Δ²a)²] = 6σ² for white noise), which a smooth trajectory barely enters; what the average
    itself leaves out also holds the flight's own jerk, which on a corridor at 2 m/s would raise
    the bar to 0.5 m/s² and let a rest bound through while the camera accelerates at 0.3 m/s²
    (causal RMSE 0.047 m/s that way, 0.033 from the second differences; the real EuRoC start
    the same either way).

    Second differences see white noise at the frame rate, not a slow wobble: a hovering platform's
    3 Hz, 0.1 m/s² wobble leaves the bar at change_max, so the wobble reads as motion and the rest
    bound is not used through it. That is the cautious side. Counting such a wobble as vibration
    (what a half-second quadratic leaves) gives the rest bound back on 20 % of the replay of the
    real FLIVVER run, but with the EMD front end's weak expansion at coarse resolution a wrongly
    applied bound is confidently wrong (Δφ = 3°: 0.105 m/s against 0.045), while losing it costs
    little (τ = 5 ms at full contrast: 0.032 m/s against 0.026; DIS the same, 0.0052).

    Parameters
    ----------
    a : ndarray, (n,)
        m/s²: the forward reading.
    dt : float
        s: the frame interval.
    change_max : float
        m/s²: the least bar.
    causal : bool
        Trailing averages (online) rather than centred ones.

    Returns
    -------
    level : ndarray, (n,)
        m/s²: the 5-frame average.
    tol : ndarray, (n,)
        m/s²: ``change_max``, or 5× the reading's own vibration where that is more.
    """
    from scipy.ndimage import uniform_filter1d

    a = np.asarray(a, float)
    sm = uniform_filter1d(a, 5, mode="nearest", origin=2 if causal else 0)  # trailing when causal
    k = max(3, int(round(5.0 / dt)))
    d2 = np.diff(a, 2) if len(a) >= 3 else np.zeros(1)
    # Online the first two frames have no curvature to show yet (0); offline they take their neighbour's.
    d2 = np.concatenate([np.zeros(2), d2] if causal else [d2[:1], d2, d2[-1:]])[:len(a)]
    # 0.8σ²: the variance white noise leaves after its 5-frame average is taken away.
    hf = 0.8 * uniform_filter1d(d2 ** 2 / 6.0, k, mode="nearest", origin=(k - 1) // 2 if causal else 0)
    return sm, np.maximum(change_max, 5.0 * np.sqrt(np.maximum(hf, 0.0)))


def accelerometer_steady(a: np.ndarray, dt: float, change_max: float, window_s: float = 1.0,
                         causal: bool = False) -> np.ndarray:
    """Where the forward acceleration stayed within a bar of a straight line over a window.

    Each reading is first averaged over 5 frames; the bar is ``change_max`` or 5× the reading's
    own vibration where that is more (:func:`accelerometer_level`).

    A still camera's accelerometer reads its offset, gravity's residue — a constant, or a ramp while
    an uncorrected gyro bias turns gravity into the forward axis (a real still EuRoC sequence: 0.17
    m/s² per second). A reading that bends away from a line says the camera starts or stops
    accelerating: not at rest, whatever the image shows. The converse does not hold (constant
    velocity reads the same as rest): that the image must tell. No offset or ramp enters the test
    (the online filter also asks the reading less its learned offset: :func:`kalman_velocity`).

    Parameters
    ----------
    a : ndarray, (n,)
        m/s²: the forward reading.
    dt : float
        s: the frame interval.
    change_max : float
        m/s²: the least bar.
    window_s : float
        s: the window's length.
    causal : bool
        The window ending at each frame (online); else the one centred on it.

    Returns
    -------
    ndarray of bool, (n,)
    """
    from numpy.lib.stride_tricks import sliding_window_view

    n = len(a)
    w_full = max(3, int(round(window_s / dt)))
    w = min(w_full, n)
    sm, change_max = accelerometer_level(a, dt, change_max, causal)
    # Window j covers frames j .. j + w − 1; causal frame k takes the window ending at k, offline the
    # one centred on it (both clipped at the record's ends).
    win = sliding_window_view(sm, w)                                       # (n − w + 1, w)
    x = np.arange(w) - 0.5 * (w - 1)
    slope = win @ x / max(x @ x, 1.0)  # one reading (x·x = 0) has no slope
    res = win - win.mean(1, keepdims=True) - slope[:, None] * x
    bend = res.max(1) - res.min(1)                                         # (n − w + 1,)
    j = np.arange(n) - (w - 1 if causal else w // 2)
    steady = bend[np.clip(j, 0, len(bend) - 1)] <= change_max
    if causal:
        # Before a whole window has passed, the frames so far (at least 3: two always lie on a line).
        for k in range(min(w_full - 1, n)):
            if k < 2:
                steady[k] = False
                continue
            xs = np.arange(k + 1) - 0.5 * k
            y = sm[:k + 1]
            res = y - y.mean() - (y @ xs / (xs @ xs)) * xs
            steady[k] = res.max() - res.min() <= change_max[k]
    return steady


def readout_lag(cfg: ReadoutConfig, dt: float) -> int:
    """Frames by which the kalman readout's terms are late (:func:`readout_terms`).

    Parameters
    ----------
    cfg : ReadoutConfig
    dt : float
        s: the frame interval.

    Returns
    -------
    int
        0 offline; online the centred low-pass's half-width plus half the stagger of ṙ̄'s
        difference (11 at 30 frames/s by default).
    """
    if cfg.filter == "zero-phase":
        return 0
    stagger = cfg.difference_frames
    return gaussian_lowpass(np.zeros(3), cfg.cutoff_hz, dt, truncate=cfg.online_window_sigma)[1] + stagger // 2


def physical_kappa(terms, v_f, cfg: ReadoutConfig, offset_prior: float):
    """κ and its standard error (:func:`ratio_measurement`), a field left out where its implied depth is not physical.

    A field's depth is judged (v_f NaN, :func:`vision_measurement`) only where |a| is beyond what
    the accelerometer's offset could make of nothing: an offset (the online gravity reference's,
    up to the start's acceleration) would otherwise make every field look unphysical exactly when
    κ ≈ 0 is what pins it down. Elsewhere κ ≈ 0 ties the offset down.

    Parameters
    ----------
    terms : tuple of ndarray
        The readout's (r̄, r²̄, ṙ̄, a): (n, F) 1/s, 1/s², 1/s² and (n,) m/s² (:func:`readout_terms`).
    v_f : ndarray, (n, F)
        m/s: the fields' velocities, NaN where rejected.
    cfg : ReadoutConfig
    offset_prior : float
        m/s²: the prior std of the accelerometer's offset.

    Returns
    -------
    kappa : ndarray, (n,)
        1/s, NaN where uninformative.
    std : ndarray, (n,)
        1/s.
    k : ndarray, (n, F)
        1/s: each field's ratio, NaN for the fields left out.
    """
    judge = np.abs(terms[3]) >= cfg.accel_min_m_s2 + 2.0 * offset_prior
    return ratio_measurement(*terms[:3], cfg, keep=np.isfinite(v_f) | ~judge[:, None], fields=True)


def readout_terms(t, r, r2, a, cfg: ReadoutConfig, material: MaterialRates | None = None, dt: float | None = None):
    """The kalman readout's low-passed inputs: (r̄, r²̄, ṙ̄, a) and how late they are.

    Offline (``cfg.filter`` "zero-phase") a zero-phase Butterworth, no latency; online the same
    centred (linear-phase) computation, known ``lag`` frames later, every term delayed alike so
    the ratios the readout takes stay unbiased.

    Parameters
    ----------
    t : ndarray, (n,)
        s, uniformly spaced.
    r, r2 : ndarray, (n, F)
        1/s and 1/s²: the fields' rates at fixed pixels.
    a : ndarray, (n,)
        m/s².
    cfg : ReadoutConfig
    material : MaterialRates, optional
        The rates along the content; then r̄, r²̄ and ṙ̄ are its own.
    dt : float, optional
        s: the frame interval (None: the median of t's differences).

    Returns
    -------
    terms : tuple of ndarray
        The four terms (n, F), (n, F), (n, F), (n,) as of ``lag`` frames ago.
    lag : int
        Frames, including half the stagger of ṙ̄'s difference.
    lp : callable
        The low-pass used, on (n, ...) arrays.
    rf : ndarray, (n, F)
        1/s: the low-passed fixed-pixel r̄ as of now (not lagged).
    """
    dt = float(np.median(np.diff(t))) if dt is None else float(dt)
    stagger = cfg.difference_frames
    lag = readout_lag(cfg, dt)
    if cfg.filter == "zero-phase":
        wn = cfg.cutoff_hz / (0.5 / dt)
        lp = lambda x: butterworth(x, wn, cfg.order, True)
        lp_rates = lp
    else:
        lp = lambda x, restart=False: gaussian_lowpass(x, cfg.cutoff_hz, dt, truncate=cfg.online_window_sigma,
                                                       causal=True, restart=restart)[0]
        # Online the fields' rates are smoothed run by run (filters.vision_runs): across a fast turn
        # they see other surfaces, and a held gap would carry the surfaces before it into the terms
        # after. (Offline a gap is interpolated, and the zero-phase Butterworth would ring at the
        # edges of runs shorter than its impulse response.)
        lp_rates = lambda x: lp(x, True)
    # ṙ̄ is a difference over the stagger: the acceleration beside it is averaged over the same span.
    a = difference_mean(a, stagger)
    af = lp(a)
    if material is not None and cfg.filter != "zero-phase":
        # Run by run, every term is windowed alike: a run is where ρ and ṙ are both measured (ṙ's difference
        # starts half a stagger into ρ's run), and the acceleration is smoothed over each run alone with the
        # same edge pads. A ratio of terms smoothed over different windows is biased at a run's edge, where the pads
        # weigh the edge sample most (a deceleration inside a saccade would reach lp(a) but not ṙ̄).
        seen = np.isfinite(material.r).any(1) & np.isfinite(material.r_dot).any(1)
        material = replace(material, **{k: np.where(seen[:, None], getattr(material, k), np.nan)
                                        for k in ("r", "r2", "r_dot")})
        for run in vision_runs(material.r):
            af[run] = lp(np.asarray(a[run], float))
    rf = lp_rates(r)
    if material is None:
        r2f = lp_rates(r2) if cfg.r2_term == "field" else rf ** 2
        terms = (rf, r2f, staggered_difference(rf, stagger, dt, centred=True), af)
    else:
        m = material
        rm = lp_rates(m.r)
        r2m = rm ** 2 if cfg.r2_term == "mean_squared" else lp_rates(m.r2)
        terms = (rm, r2m, lp_rates(m.r_dot), af)
    return tuple(_lag(x, lag) for x in terms), lag, lp, rf
