""":class:`EyeCircuit`, the streaming circuit on the compound eye: photoreceptors, lateral inhibition,
EMDs, the LC fields' matched filters, the haltere's rotation subtraction at its learned gain, and
each readout step's 2×2 solve for ρ, g and r2_eff.
"""
from __future__ import annotations

import math

import numpy as np

from .._optional import torch
from ..compound_eye import CompoundEye
from ..emd import EMDArray
from ..photoreceptor import Photoreceptors, lattice_filter, lowpass_scan, spatial_filter
from ..three_arm import ThreeArmArray, ThreeArmConfig
from .config import EyeCircuitConfig
from .fields import _angle, eye_fields
from .scene_gain import natural_scene_gain


class EyeCircuit:
    """Streaming circuit: ``process(luminance (T, n), gyro (T, 3))`` → completed readout steps.

    Keeps photoreceptor, EMD, gyro-filter and partial-block state between calls.
    ``finish()`` returns the last, partial block (if any). Each result is a dict of
    numpy arrays over readout steps: ``t`` (K,) stamped times, ``rho`` (K, F') 1/s,
    ``grad`` (K, F') 1/s per rad, ``r2_eff`` (K, F') 1/s², ``rot`` (K, F') 1/s (the rotation
    the haltere subtracted, as ρ at the learned gain; 0 without haltere subtraction),
    ``haltere_gain`` (K, F') the gain it was subtracted at (1 + α; 1 fixed; NaN without), with
    F' = F fields, or the mirror groups (F/2) under wide-field rotation cancelling, and ``saccade`` (K,)
    bool: the step saw a body saccade or the hold after it (:attr:`EyeCircuitConfig.saccade_gate_deg_s`).

    eye: the :class:`lobula.compound_eye.CompoundEye`; rate_hz: the rate (Hz) the luminance and gyro
    arrive at; config: the :class:`EyeCircuitConfig` (None: the default).
    """

    #: haltere gain regression: running-mean time constant and memory (readout steps), prior std of α
    HP_STEPS, MEMORY_STEPS, ALPHA_PRIOR_STD = 50, 500, 0.5

    def __init__(self, eye: CompoundEye, rate_hz: float, config: EyeCircuitConfig | None = None):
        self.config = cfg = config or EyeCircuitConfig()
        self.eye = eye
        self.dt = 1.0 / float(rate_hz)
        self.block = max(1, int(round(rate_hz / cfg.readout_rate_hz)))
        self.fields = fields = eye_fields(eye, cfg.fields)
        self.photoreceptors = Photoreceptors(cfg.photoreceptor, self.dt)
        self.emds = EMDArray(eye.pairs_a, eye.pairs_b, cfg.emd, self.dt)
        # The three-arm detector (an option) replaces the correlator along the same pairs, at the same delay.
        self.arms = (ThreeArmArray.from_eye(eye, ThreeArmConfig(tau_s=cfg.emd.tau_s, weight=cfg.three_arm_weight),
                                            self.dt) if cfg.detector == "three-arm" else None)
        # The per-pair decoding low-passes R and G once more with the EMD's τ (see _pair_speeds): a
        # first-order lag of τ more on the decoded speed (stamping without it put vision ~τ behind the
        # accelerometer: on the dev worlds, seeds 7, 8, 100, the causal RMSE fell 0.005–0.04 m/s with it).
        n_lp = 2 if cfg.normaliser == "pair" else 1
        self.latency_s = (cfg.latency_s if cfg.latency_s is not None
                          else cfg.photoreceptor.tau_s + n_lp * cfg.emd.tau_s + 0.5 * self.block * self.dt)
        tau = cfg.emd.tau_s
        c = 2.0 * tau / eye.pair_separation                                     # (P,)
        zhat = np.array([0.0, 0.0, 1.0])
        m = -(eye.pair_direction @ zhat)                                        # template (P,)
        theta_p = _angle(eye.pair_midpoint, zhat)
        delta = theta_p[None, :] - fields.theta[:, None]                        # (F, P)
        W = fields.weights
        k = np.cross(eye.pair_direction, eye.pair_midpoint)                     # rotational template (P, 3)
        # Numerator filters (on R) and denominator filters (on G), stacked for one matmul each.
        num = np.concatenate([(W * c * m), (W * c * m * delta)], 0)            # (2F, P)
        cgm = W * c * c * m
        den = [cgm * m, cgm * m * delta, cgm * m * delta ** 2]
        rot = [cgm * k[:, j] for j in range(3)] + [cgm * delta * k[:, j] for j in range(3)]
        if cfg.normaliser == "pair":
            # Each pair's speed is decoded first (R/(c·G)), then pooled with speed-independent weights.
            num = np.concatenate([W * m, W * m * delta], 0)
            wm = W * m
            den = [wm * m, wm * m * delta, wm * m * delta ** 2]
            rot = [wm * k[:, j] for j in range(3)] + [wm * delta * k[:, j] for j in range(3)]
        self._c = torch.as_tensor(c, dtype=torch.float32)
        # The LC's synaptic drive from its EMDs, Σ_p w·c·m·R_p (recorded as lc.input, whatever the pool).
        self._lc_input = torch.as_tensor((W * c * m).T, dtype=torch.float32)    # (P, F)
        self._num = torch.as_tensor(num.T, dtype=torch.float32)                  # (P, 2F)
        self._den = torch.as_tensor(np.concatenate(den + rot, 0).T, dtype=torch.float32)  # (P, 9F)
        self._pair_state = None
        self._pool = lattice_filter(eye, cfg.column_pool, cfg.surround)
        self._a = torch.as_tensor(eye.pairs_a)
        self._b = torch.as_tensor(eye.pairs_b)
        self._gyro_state: torch.Tensor | None = None
        self._gyro_pair: torch.Tensor | None = None
        self._lp_state: torch.Tensor | None = None
        self._carry: list = []           # partial block of per-step sums
        self._t0 = 0.0
        self._n_steps = 0
        self._floor = None
        self._rot_state = None
        self._last_saccade = -math.inf   # s (circuit clock): the latest sample above the saccade gate
        self.gain_prior = (cfg.rotation_gain_prior if cfg.rotation_gain_prior is not None else
                           natural_scene_gain(eye.config.dphi_deg, eye.config.acceptance_deg, cfg.surround,
                                              cfg.column_pool))
        self.timings = dict(photoreceptor=0.0, emd=0.0, fields=0.0)

    @property
    def n_outputs(self) -> int:
        """F': the number of output columns (fields, or mirror groups under wide-field cancelling)."""
        F = self.fields.n_fields
        return F // 2 if self.config.rotation in ("wide-field", "both") and F > 1 and \
            (self.fields.mirror != np.arange(F)).all() else F

    def _gyro_filtered(self, gyro: torch.Tensor) -> torch.Tensor:
        """ω through the photoreceptor and EMD low-passes (continuing state), (..., T, 3)."""
        cfg = self.config
        if self._gyro_state is None:
            self._gyro_state = torch.stack([gyro[..., 0, :], gyro[..., 0, :]])
        a1 = math.exp(-self.dt / cfg.photoreceptor.tau_s) if cfg.photoreceptor.tau_s > 0 else 0.0
        a2 = math.exp(-self.dt / cfg.emd.tau_s)
        g1 = lowpass_scan(gyro, a1, self._gyro_state[0])
        g2 = lowpass_scan(g1, a2, self._gyro_state[1])
        self._gyro_state = torch.stack([g1[..., -1, :], g2[..., -1, :]])
        if cfg.normaliser == "pair":   # the pairs' speeds pass one more low-pass (see _pair_speeds)
            if self._gyro_pair is None:
                self._gyro_pair = g2[..., 0, :]
            g2 = lowpass_scan(g2, a2, self._gyro_pair)
            self._gyro_pair = g2[..., -1, :]
        return g2

    #: time constant (s) of the running mean of each pair's contrast energy that sets its semi-saturation floor
    PAIR_FLOOR_TAU_S = 2.0

    def _pair_speeds(self, R: torch.Tensor, dy: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
        """Per-pair decoded image speed times its contrast weight, and the weights: (..., T, 2F + 9F) sums.

        Each EMD's output is divided by its own delayed-contrast pool before any pooling,
        s_p = LP(R_p) / (c_p·(LP(G_p)⁺ + ε_p)) (rad/s along u_p; LP the EMD's own τ, which
        averages the correlator's ripple; ε_p = ``fields.floor`` × the pair's contrast energy
        (x_B − x_A)² averaged over ``PAIR_FLOOR_TAU_S``, a semi-saturation constant), and the
        LC field then fits ρ_f, g_f to the s_p weighted by the contrast energy H_p = LP((x_B − x_A)²),
        which does not depend on the speed. Why: pooled first (default "delayed"), a pair's weight in
        the fit is its pool G_p ∝ C²/(1 + (ωτ)²), smaller the faster its image moves, so the fit leans
        on the far, slow parts of a field and ρ̂ grows slower than ρ (measured on dev worlds, log–log
        slope β of ρ̂ against the exact v/D: 0.6 in a corridor); the readout's (ρ̇ − r²)/ρ of ρ^β is
        β·a/v. Local contrast normalisation before the direction-selective stage is what the fly's
        motion pathway does (Drews et al. 2020, Curr Biol 30:209; Matulis et al. 2020, Curr Biol
        30:222): each T4/T5 input is normalised by its own recent contrast.
        """
        a = math.exp(-self.dt / self.config.emd.tau_s)
        af = math.exp(-self.dt / self.PAIR_FLOOR_TAU_S)
        H = dy * dy
        st = self._pair_state or {}
        lR = lowpass_scan(R, a, st.get("R"))
        lG = lowpass_scan(G, a, st.get("G"))
        lH = lowpass_scan(H, a, st.get("H"))
        slow = lowpass_scan(H, af, st.get("slow"))
        self._pair_state = dict(R=lR[..., -1, :].clone(), G=lG[..., -1, :].clone(), H=lH[..., -1, :].clone(),
                                slow=slow[..., -1, :].clone())
        speed = lR / (self._c * (lG.clamp(min=0.0) + self.config.fields.floor * slow + 1e-12))
        return torch.cat([(speed * lH) @ self._num, lH @ self._den], dim=-1)

    def _sums(self, lum: torch.Tensor, gyro: torch.Tensor | None, keep: dict | None = None,
              with_rotation: bool = False) -> torch.Tensor:
        """Per-step pooled sums (..., T, 5F): b1, b2 (2F), A11, A12, A22 (3F), haltere-corrected.

        with_rotation: when the haltere correction ran, also return the two subtracted
        predictions (the rotational response of b1, b2 at unit gain), as (..., T, 7F).

        lum (..., T, n); gyro (..., T, 3) or None (no rotation signal: nothing subtracted).
        keep: a dict that receives the stages' signals "photoreceptor.v" (..., T, n) and
        "emd.response" (..., T, P) when it has those keys (for recording).
        """
        import time as _time
        t0 = _time.perf_counter()
        y = self.photoreceptors.run(lum)
        y = spatial_filter(self._pool, y)
        t1 = _time.perf_counter()
        R = self.emds.run(y) if self.arms is None else self.arms.run(y)        # (..., T, P)
        t2 = _time.perf_counter()
        if keep is not None:
            if "photoreceptor.v" in keep:
                keep["photoreceptor.v"] = y
            if "emd.response" in keep:
                keep["emd.response"] = R
            if "lc.input" in keep:
                keep["lc.input"] = R @ self._lc_input
        dy = y[..., self._b] - y[..., self._a]
        if self.config.normaliser in ("delayed", "pair"):
            # The contrast difference times its own delayed (low-passed) copy: the EMD's four signals.
            lp = lowpass_scan(dy, math.exp(-self.dt / self.config.emd.tau_s), self._lp_state)
            self._lp_state = lp[..., -1, :].clone()
            G = lp * dy
        else:
            G = dy * dy
        out = (self._pair_speeds(R, dy, G) if self.config.normaliser == "pair"
               else torch.cat([R @ self._num, G @ self._den], dim=-1))
        self.timings["photoreceptor"] += t1 - t0
        self.timings["emd"] += t2 - t1
        self.timings["fields"] += _time.perf_counter() - t2
        F = self.fields.n_fields
        if self.config.rotation in ("haltere", "both") and gyro is not None:
            w = self._gyro_filtered(gyro)                                       # (..., T, 3)
            rot = out[..., 5 * F:].reshape(out.shape[:-1] + (2, 3, F))
            corr = torch.einsum("...tj,...tkjf->...tkf", w, rot)                # (..., T, 2, F)
            corr = corr.reshape(out.shape[:-1] + (2 * F,))
            out[..., :2 * F] -= corr
            if with_rotation:
                # The subtracted prediction travels with the sums: the solve learns its gain (see _solve).
                return torch.cat([out[..., :5 * F], corr], dim=-1)
        return out[..., :5 * F]

    def run_steps(self, luminance, gyro=None, record=()) -> dict:
        """The circuit at the eye's rate, batched over leading dims (stimulus conditions).

        luminance (..., T, n); gyro (..., T, 3) rad/s or None (a stimulus without
        self-rotation). Continues the circuit's state like :meth:`process`. Returns torch
        tensors: ``sums`` (..., T, 5F), the per-step pooled signals (b1, b2, then the pools
        A11, A12, A22), plus "photoreceptor.v", "emd.response" and "lc.input" (the fields'
        matched-filter input Σ_p w·c·m·R_p, (..., T, F): b1 itself for the "delayed" and
        "gradient" pools) when named in ``record``.
        """
        lum = torch.as_tensor(luminance, dtype=torch.float32)
        if lum.dim() < 2 or lum.shape[-1] != self.eye.n:
            raise ValueError(f"luminance must be (..., time, {self.eye.n}) for this eye, got {tuple(lum.shape)}")
        gyr = None if gyro is None else torch.as_tensor(gyro, dtype=torch.float32)
        if gyr is not None and gyr.shape != lum.shape[:-1] + (3,):
            raise ValueError(f"gyro must be (..., time, 3) matching the luminance, got {tuple(gyr.shape)}")
        keep = {k: None for k in record if k in ("photoreceptor.v", "emd.response", "lc.input")}
        sums = self._sums(lum, gyr, keep)
        return dict(sums=sums, **{k: v for k, v in keep.items() if v is not None})

    def solve_blocks(self, block_sums: np.ndarray, t_end: np.ndarray, saccade: np.ndarray | None = None) -> dict:
        """ρ, g and r2_eff (the dict of :class:`EyeCircuit`'s results) from ``block_sums`` (..., K, 5F) of blocks
        ending at ``t_end`` (K,) s (the readout's 2×2 solve; continues the floor). saccade: (K,) bool, the blocks
        the saccade gate flags (None: none, as for a stimulus without a haltere signal)."""
        return self._solve(np.asarray(block_sums, dtype=float), np.asarray(t_end, dtype=float),
                           None if saccade is None else np.asarray(saccade, dtype=bool))

    def saccade_samples(self, gyro: np.ndarray) -> np.ndarray:
        """Which of the next samples the saccade gate flags, (T,) bool; continues the circuit's clock.

        gyro (T, 3) rad/s, the haltere's angular velocity at the eye's rate, for the samples that follow
        those already processed. A sample is flagged while |ω| exceeds ``saccade_gate_deg_s`` and for
        :meth:`EyeCircuitConfig.saccade_hold_s` after the last sample that did (causal: the hold runs
        across calls). All False without a gate.
        """
        cfg = self.config
        g = np.asarray(gyro, dtype=float)
        if cfg.saccade_gate_deg_s is None or not len(g):
            return np.zeros(len(g), dtype=bool)
        t = (self._n_steps + np.arange(len(g))) * self.dt
        fast = np.linalg.norm(g, axis=-1) > math.radians(cfg.saccade_gate_deg_s)
        last = np.maximum(np.maximum.accumulate(np.where(fast, t, -math.inf)), self._last_saccade)
        self._last_saccade = float(last[-1])
        return (t - last) <= cfg.saccade_hold_s() + 1e-9

    def process(self, luminance, gyro) -> dict:
        """Feed (T, n) luminance (any units) and ``gyro`` (T, 3) angular velocity (rad/s, camera frame) at the
        eye's rate; returns the readout steps completed (the dict of :class:`EyeCircuit`'s results)."""
        lum = torch.as_tensor(np.array(luminance, dtype=np.float32))
        gyr = torch.as_tensor(np.array(gyro, dtype=np.float32))
        if lum.dim() != 2 or lum.shape[1] != self.eye.n:
            raise ValueError(f"luminance must be (time, {self.eye.n}) for this eye, got {tuple(lum.shape)}")
        if gyr.shape != (lum.shape[0], 3):
            raise ValueError(f"gyro must be (time, 3) matching the luminance, got {tuple(gyr.shape)}")
        s = self._sums(lum, gyr, with_rotation=self.config.rotation_gain == "adaptive").double()
        # The saccade gate's flag travels with the sums as one more column: a block is flagged if any sample is.
        flag = torch.as_tensor(self.saccade_samples(gyr.numpy()), dtype=s.dtype)
        s = torch.cat([s, flag[:, None]], dim=1)
        if self._carry:
            s = torch.cat([self._carry.pop(), s])
        start = self._n_steps - (len(s) - lum.shape[0])
        self._n_steps += lum.shape[0]
        nb = len(s) // self.block
        if len(s) > nb * self.block:
            self._carry.append(s[nb * self.block:])
        if nb == 0:
            return self._solve(np.zeros((0, s.shape[1] - 1)), np.zeros(0))
        blocks = s[:nb * self.block].reshape(nb, self.block, -1).sum(1).numpy()
        t_end = (start + self.block * np.arange(1, nb + 1) - 1) * self.dt
        return self._solve(blocks[:, :-1], t_end, blocks[:, -1] > 0)

    def finish(self) -> dict:
        """The final partial block, if any, as :meth:`process` returns steps (K = 0 or 1)."""
        if not self._carry:
            return self._solve(np.zeros((0, 5 * self.fields.n_fields)), np.zeros(0))
        s = self._carry.pop()
        t_end = np.array([(self._n_steps - 1) * self.dt])
        flag = np.array([bool(s[:, -1].sum() > 0)])
        return self._solve(s[:, :-1].sum(0, keepdim=True).numpy() * (self.block / len(s)), t_end, flag)

    def _rotation_gain(self, rho: np.ndarray, q: np.ndarray, gate: np.ndarray | None = None) -> np.ndarray:
        """Causal per-field estimate of α = γ − 1, the field's gain γ less the haltere's unit gain, (K, F').

        The decoded image motion is γ·(true motion) with γ = (Δϕ/2)·cot(Δϕ/2) averaged
        over the field's texture (< 1, and the same for rotation and translation: one set
        of EMDs sees both). The haltere predicts the rotational response at gain 1, so
        ρ̂ = γρ + α·q after the subtraction, q the subtracted rotation's ρ. Rotation is
        independent of translation, so α is the regression of ρ̂ on q — over past readout
        steps only, both with their running means (time constant ``HP_STEPS``, learning starts
        once they have run that long; a constant turn is not told from translation) removed, with
        forgetting (``MEMORY_STEPS``) and a prior α = α₀ ± ``ALPHA_PRIOR_STD`` (α₀ = ``gain_prior`` − 1,
        the config's ``rotation_gain_prior`` or :func:`natural_scene_gain`) against ρ̂'s own running
        variance s² as the noise: the posterior mean (Σ δρ·δq + α₀·s²/σ₀²) / (Σ δq² + s²/σ₀²), α₀ until
        the field has learned (no rotation seen: the prior's gain). α is held in [−1, 0.5] (γ between 0
        and 1.5) and the estimate at step k uses steps before k only. Steps flagged in ``gate`` (K,) bool (a
        saccade and its hold) teach it nothing: at a saccade's rates the EMDs are far past their
        temporal-frequency optimum and report the turn at another gain than in the intersaccadic flight
        that α serves.
        """
        K, Fo = rho.shape[-2], rho.shape[-1]
        st = self._rot_state
        if st is None:
            z = np.zeros(rho.shape[:-2] + (Fo,))
            st = dict(mr=np.nan_to_num(rho[..., 0, :]), mq=q[..., 0, :].copy(), sxy=z.copy(), sxx=z.copy(),
                      vr=z.copy(), n=0)
        hp, mem = 1.0 / self.HP_STEPS, 1.0 / self.MEMORY_STEPS
        a0, w0 = self.gain_prior - 1.0, 1.0 / self.ALPHA_PRIOR_STD ** 2
        alpha = np.empty_like(rho)
        for k in range(K):  # a loop over readout steps, vectorised over fields
            den = st["sxx"] + st["vr"] * w0
            with np.errstate(invalid="ignore", divide="ignore"):
                a = np.where(den > 0, (st["sxy"] + a0 * st["vr"] * w0) / den, a0)
            alpha[..., k, :] = np.clip(np.nan_to_num(a, nan=a0), -1.0, 0.5)
            if gate is not None and gate[k]:
                continue   # saccadic suppression: α and its running means hold (see the docstring)
            r, qk = rho[..., k, :], q[..., k, :]
            ok = np.isfinite(r)
            dr, dq = np.where(ok, r - st["mr"], 0.0), np.where(ok, qk - st["mq"], 0.0)
            st["mr"] = np.where(ok, st["mr"] + hp * dr, st["mr"])
            st["mq"] = st["mq"] + hp * (qk - st["mq"])
            st["n"] += 1
            if st["n"] > self.HP_STEPS:   # the running means have settled: learn
                st["sxy"] = (1 - mem) * st["sxy"] + dr * dq
                st["sxx"] = (1 - mem) * st["sxx"] + dq * dq
                st["vr"] = (1 - mem) * st["vr"] + mem * dr * dr
        self._rot_state = st
        return alpha

    def _solve(self, sums: np.ndarray, t_end: np.ndarray, gate: np.ndarray | None = None) -> dict:
        """Per-block 2×2 weighted least squares for (ρ_f, g_f) and r2_eff; ``gate`` (K,) bool: the blocks the
        saccade gate flags, from which the floor and the haltere gain do not learn (None: none)."""
        gate = np.zeros(sums.shape[-2], dtype=bool) if gate is None else gate
        F = self.fields.n_fields
        parts = [sums[..., i * F:(i + 1) * F] for i in range(sums.shape[-1] // F)]
        theta = self.fields.theta
        if self.n_outputs != F:   # wide-field: sum mirror fields (right f with left mirror[f])
            right = np.flatnonzero(self.fields.eye == 0)
            left = self.fields.mirror[right]
            parts = [x[..., right] + x[..., left] for x in parts]
            theta = theta[right]
        b1, b2, A11, A12, A22 = parts[:5]
        cfg = self.config.fields
        q = np.zeros_like(b1)
        # The gain each field subtracts the haltere's prediction at: 1 + α learned, 1 when fixed, NaN without.
        gain = np.full_like(b1, 1.0 if self.config.rotation in ("haltere", "both") else np.nan)
        if A11.shape[-2]:
            # Semi-saturation floor: a running mean (over past blocks only) of each field's pool.
            floors = np.empty_like(A11)
            level = A11[..., 0, :] if self._floor is None else self._floor
            for k in range(A11.shape[-2]):  # a loop over readout steps, vectorised over fields
                if not gate[k]:   # a saccade's pools are the turn's, not the flight's: the floor holds
                    level = 0.99 * level + 0.01 * A11[..., k, :]
                floors[..., k, :] = level
            self._floor = level
            A11 = A11 + cfg.floor * floors
        A22 = A22 * (1.0 + cfg.gradient_ridge)
        det = A11 * A22 - A12 * A12
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.where(det > 0, (A22 * b1 - A12 * b2) / det, np.nan)
            grad = np.where(det > 0, (A11 * b2 - A12 * b1) / det, np.nan)
            if len(parts) == 7 and A11.shape[-2]:
                # ρ and g of the rotation the haltere subtracted, at unit gain.
                c1, c2 = parts[5:]
                q = np.where(det > 0, (A22 * c1 - A12 * c2) / det, 0.0)
                qg = np.where(det > 0, (A11 * c2 - A12 * c1) / det, 0.0)
                alpha = self._rotation_gain(rho, q, gate)
                rho, grad = rho - alpha * q, grad - alpha * qg
                q, gain = (1.0 + alpha) * q, 1.0 + alpha
            rho, grad = rho * self.config.calibration, grad * self.config.calibration
        mode = self.config.r2_term
        r2_eff = (rho ** 2 * np.cos(theta) - rho * np.sin(theta) * grad if mode == "convective"
                  else rho ** 2 * np.cos(theta) if mode == "point" else np.zeros_like(rho))
        return dict(t=t_end - self.latency_s, rho=rho, grad=grad, r2_eff=r2_eff, rot=q * self.config.calibration,
                    haltere_gain=gain, saccade=gate.copy())
