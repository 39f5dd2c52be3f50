"""Virtual electrophysiology on the compound eye: record the velocity circuit's own LC fields.

``lobula ephys tf-tuning|rf-map --eye fly`` shows the lattice stimuli (drifting gratings,
moving spots; :mod:`stimuli.lattice_stimuli`, evaluated at the ommatidial axes with the
Gaussian acceptance applied analytically) to the two compound eyes of
:mod:`lobula.compound_eye` and records :class:`lobula.eye_circuit.EyeCircuit` — built
from :class:`experiments.eye_velocity.EyeVelocityConfig`'s circuit, the configuration
``lobula eye-velocity`` and ``lobula velocity EYE --front-end emd`` estimate velocity
with: the same eye (Δφ = Δρ = 5°, 1,574 ommatidia), rate (500 Hz), photoreceptors,
EMD τ, LC fields (30° Gaussian matched filters for translation) and pools. The units
recorded are the ones that compute velocity.

Records (``POPULATION.VARIABLE[subset]``):

- ``photoreceptor.v`` (time × ommatidium), ``emd.response`` (time × pair);
- ``lc.input``: each LC field's matched-filter input Σ_p w·c·m·R_p over its EMD pairs
  (before the contrast pool), at the eye's rate;
- ``lc.pool``: the field's divisive contrast pool Σ_p w·c²·m²·G_p (same four signals as
  the correlator), at the eye's rate;
- ``lc.r`` (ρ = v/D, 1/s), ``lc.grad`` (its gradient along θ), ``lc.r2`` (the convective
  r²-term the readout uses): the field's 2×2 fit, computed once per readout step (50 Hz)
  and held until the next (NaN before the first), as the readout sees them.

Known answers: the matched-filter input of a correlator array tunes to temporal frequency
with its optimum near 1/(2πτ) (times the photoreceptors' transfer), while the pooled ρ,
the correlator divided by a pool with the same temporal filtering, is proportional to
temporal frequency (R̄/Ḡ = ωτ·cot(Δϕ/2), :mod:`lobula.eye_circuit`): it reports speed,
not temporal frequency. RF maps: spot passages in ≥ 3 directions; a field's local radial
sensitivity is its designed weight times the template's magnitude sin θ, so the map
divided by sin θ recovers the designed Gaussian: its centroid on the sphere is compared
with the designed centre.

Stimuli have no self-rotation: the haltere input is zero (nothing is subtracted).
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field, replace

import numpy as np
import xarray as xr

from lobula._optional import torch
from lobula.compound_eye import CompoundEye, CompoundEyeConfig
from lobula.emd import emd_sine_response_discrete
from lobula.eye_circuit import EyeCircuit, EyeCircuitConfig
from lobula.photoreceptor import photoreceptor_frequency_response

from .rig import cf_describe, empty_slice, protocol, recording_attrs

__all__ = ["EyeEphysConfig", "EyeRig", "EYE_RECORDS", "eye_tf_tuning", "eye_rf_map", "eye_looming"]

#: what the eye rig records: (units, long_name)
EYE_VARIABLES = {
    "photoreceptor.v": ("1", "photoreceptor output less the neighbouring columns' mean (the LMCs' lateral inhibition)"),
    "emd.response": ("1", "EMD opponent (Hassenstein-Reichardt) response along a neighbour pair"),
    "lc.input": ("1", "LC matched-filter input: sum over the field's EMD pairs of w*c*m*R (before the pool)"),
    "lc.pool": ("1", "LC contrast pool: sum over the field's EMD pairs of w*c^2*m^2*G (the divisive normaliser)"),
    "lc.r": ("s-1", "LC field expansion rate v/D (per readout step, held)"),
    "lc.grad": ("s-1", "LC field gradient of the expansion rate along theta (per radian; per readout step, held)"),
    "lc.r2": ("s-2", "LC field r-squared term with the convective correction (per readout step, held)"),
}
EYE_RECORDS = tuple(EYE_VARIABLES)
_STEP = ("lc.input", "lc.pool")
_BLOCK = ("lc.r", "lc.grad", "lc.r2")
_MONITOR = re.compile(r"^\s*([a-z_]+\.[a-z_0-9]+)\s*(?:\[(.*)\])?\s*$")


def _velocity_circuit() -> EyeCircuitConfig:
    from experiments.eye_velocity import EyeVelocityConfig
    return EyeVelocityConfig().circuit


@dataclass
class EyeEphysConfig:
    """The compound-eye rig: the eye, the velocity pipeline's circuit, its rate (written into every recording).

    circuit: by default exactly :class:`experiments.eye_velocity.EyeVelocityConfig`'s.
    rate_hz: the eye's sample rate (500 Hz, as ``lobula scene --eye fly``).
    threads: torch CPU threads while a protocol runs.
    """

    eye: CompoundEyeConfig = field(default_factory=CompoundEyeConfig)
    circuit: EyeCircuitConfig = field(default_factory=_velocity_circuit)
    rate_hz: float = 500.0
    threads: int | None = 1

    def to_dict(self) -> dict:
        return dict(eye=self.eye.to_dict(), circuit=self.circuit.to_dict(), rate_hz=self.rate_hz,
                    threads=self.threads)

    def with_options(self, tau_s=None, dphi_deg=None, field_size_deg=None) -> "EyeEphysConfig":
        """The same rig with the EMD τ (s), Δφ (deg, Δρ follows) or LC field size (deg) replaced (None: unchanged)."""
        c = EyeCircuitConfig.from_dict(self.circuit.to_dict())
        if tau_s is not None:
            c.emd = replace(c.emd, tau_s=float(tau_s))
        if field_size_deg is not None:
            c.fields = replace(c.fields, size_deg=float(field_size_deg))
        eye = self.eye if dphi_deg is None else replace(self.eye, dphi_deg=float(dphi_deg))
        return replace(self, eye=eye, circuit=c)


class _Camera:
    def __init__(self, rate_hz):
        self.frame_rate_hz = rate_hz


class EyeLattice:
    """The compound eye seen by :mod:`stimuli.lattice_stimuli` (directions, Δφ, Δρ, angles, rate)."""

    def __init__(self, eye: CompoundEye, rate_hz: float):
        self.eye = eye
        self.directions = eye.directions
        self.n = eye.n
        self.dphi_deg = eye.config.dphi_deg
        self.drho_deg = eye.config.acceptance_deg
        self.azimuth_deg = np.degrees(eye.azimuth)
        self.elevation_deg = np.degrees(eye.elevation)
        self.camera = _Camera(rate_hz)


class EyeRig:
    """Two compound eyes and the velocity circuit, stepped at the eye's rate."""

    def __init__(self, config: EyeEphysConfig | None = None):
        self.config = cfg = config or EyeEphysConfig()
        self.eye = CompoundEye(cfg.eye)
        self.rate_hz = float(cfg.rate_hz)
        self.dt = 1.0 / self.rate_hz
        self.fields = self.new_circuit().fields
        self.lattice = EyeLattice(self.eye, self.rate_hz)

    def new_circuit(self) -> EyeCircuit:
        return EyeCircuit(self.eye, self.rate_hz, self.config.circuit)

    @property
    def n_outputs(self) -> int:
        return self.new_circuit().n_outputs

    def size(self, var: str) -> int:
        return {"photoreceptor.v": self.eye.n, "emd.response": self.eye.n_pairs}.get(
            var, self.fields.n_fields if var in _STEP else self.n_outputs)

    def monitors(self, record, default) -> dict:
        """``POP.VAR[subset]`` specs → {variable: indices or None}, checked (errors name the fix)."""
        want = {}
        for spec in (record or default):
            m = _MONITOR.match(spec)
            if not m or m.group(1) not in EYE_VARIABLES:
                hint = (" (the eye's LC fields feed the readout directly; spiking is the readout neuron's: "
                        "`lobula velocity EYE --front-end emd --readout neuron`)"
                        if m and m.group(1) in ("lc.rate", "lc.spikes", "lc.v", "lc.x", "lc.drive") else "")
                raise ValueError(f"cannot record {spec!r} on the compound eye{hint}; it records "
                                 f"{', '.join(EYE_RECORDS)} with subsets [i:j] or [i,j,k]")
            var, sub = m.group(1), (m.group(2) or "").strip()
            if var in want:
                raise ValueError(f"record each variable once; repeated: {var}")
            n = self.size(var)
            if not sub:
                want[var] = None
                continue
            try:
                idx = (list(range(n))[slice(*[int(p) if p.strip() else None for p in sub.split(":")])]
                       if ":" in sub else [int(p) for p in sub.split(",")])
            except (ValueError, TypeError):
                raise ValueError(f"{spec!r}: the subset must be i:j or i,j,k") from None
            if not idx and ":" in sub:
                raise ValueError(empty_slice(spec, var, sub, n))
            if not idx or min(idx) < -n or max(idx) >= n:
                raise ValueError(f"{spec!r}: indices must lie in [0, {n}) for {var}")
            want[var] = np.array([i % n for i in idx])
        return want

    def run(self, stimulus, n_steps: int, want: dict, baseline: float = 1.0, chunk: int = 200) -> dict:
        """Run B conditions through a fresh circuit (adapted to ``baseline``); records (B, T, X) numpy.

        stimulus: (B, T, n) tensor or a callable (start, stop) → (B, stop − start, n).
        """
        circ = self.new_circuit()
        src = stimulus if callable(stimulus) and not isinstance(stimulus, torch.Tensor) else \
            (lambda a, b: stimulus[:, a:b])
        first = src(0, 1)
        B = first.shape[0] if first.dim() == 3 else 1
        circ.run_steps(torch.full((B, 1, self.eye.n), float(baseline)))     # adapted to the mean luminance
        front = [k for k in want if k in ("photoreceptor.v", "emd.response", "lc.input")]
        parts: dict = {k: [] for k in front}
        sums = []
        for a in range(0, n_steps, chunk):  # time chunks: memory only
            x = src(a, min(n_steps, a + chunk))
            x = x if x.dim() == 3 else x[None]
            out = circ.run_steps(x.float(), None, front)
            sums.append(out["sums"].double())
            for k in front:
                parts[k].append(_sel(out[k], want[k]).numpy())
        s = torch.cat(sums, dim=-2).numpy()                                    # (B, T, 5F)
        F = self.fields.n_fields
        rec = {k: np.concatenate(v, axis=1) for k, v in parts.items()}
        if "lc.pool" in want:
            rec["lc.pool"] = _sel(s[..., 2 * F:3 * F], want["lc.pool"])
        if any(k in want for k in _BLOCK):
            blk = circ.block
            nb = n_steps // blk
            sol = circ.solve_blocks(s[:, :nb * blk].reshape(B, nb, blk, -1).sum(2),
                                    (np.arange(1, nb + 1) * blk - 1) * self.dt)
            # Each step holds the latest completed readout step (NaN before the first): causal.
            k = (np.arange(n_steps) + 1) // blk - 1
            for name, key in (("lc.r", "rho"), ("lc.grad", "grad"), ("lc.r2", "r2_eff")):
                if name in want:
                    v = sol[key][:, np.clip(k, 0, max(nb - 1, 0))] if nb else np.full((B, n_steps, self.n_outputs),
                                                                                       np.nan)
                    v = np.where((k >= 0)[None, :, None], v, np.nan)
                    rec[name] = _sel(v, want[name])
        return rec

    # -- labelled output
    def coords(self, var: str, idx) -> tuple[str, dict]:
        sel = (lambda a: np.asarray(a)) if idx is None else (lambda a: np.asarray(a)[idx])
        if var == "photoreceptor.v":
            return "ommatidium", {"ommatidium": sel(np.arange(self.eye.n)),
                                  "ommatidium_azimuth_deg": ("ommatidium", sel(self.lattice.azimuth_deg)),
                                  "ommatidium_elevation_deg": ("ommatidium", sel(self.lattice.elevation_deg))}
        if var == "emd.response":
            m = self.eye.pair_midpoint
            az = np.degrees(np.arctan2(m[:, 0], m[:, 2]))
            el = np.degrees(np.arctan2(m[:, 1], np.hypot(m[:, 0], m[:, 2])))
            return "pair", {"pair": sel(np.arange(self.eye.n_pairs)), "pair_azimuth_deg": ("pair", sel(az)),
                            "pair_elevation_deg": ("pair", sel(el))}
        f = self.fields
        n = self.size(var)
        cen = f.centres_deg[:n] if n == f.n_fields else f.centres_deg[f.eye == 0]
        eye = np.array(["right", "left"])[f.eye[:n]] if n == f.n_fields else np.full(n, "both")
        return "field", {"field": sel(np.arange(n)), "field_azimuth_deg": ("field", sel(cen[:, 0])),
                         "field_elevation_deg": ("field", sel(cen[:, 1])),
                         "field_size_deg": ("field", sel(np.full(n, f.size_deg))),
                         "field_eye": ("field", sel(eye), {"long_name": "eye of the LC field (both: mirror sum)"})}

    def dataset(self, rec: dict, want: dict, cond: dict, n_steps: int, attrs: dict) -> xr.Dataset:
        cdims = list(cond)
        cshape = [len(v) for v in cond.values()]
        coords = {"time": ("time", np.arange(n_steps) * self.dt), **{k: (k, np.asarray(v)) for k, v in cond.items()}}
        data, seen = {}, {}
        for var, idx in want.items():
            dim, c = self.coords(var, idx)
            if dim in seen and not np.array_equal(seen[dim], c[dim]):
                raise ValueError(f"record {dim} variables with one subset (got two different ones)")
            seen[dim] = c[dim]
            coords.update(c)
            units, long_name = EYE_VARIABLES[var]
            arr = rec[var].reshape(cshape + list(rec[var].shape[1:]))
            data[var.replace(".", "_")] = (cdims + ["time", dim], arr,
                                           {"units": units, "long_name": long_name, "monitor": var,
                                            "recorded": "all" if idx is None else json.dumps(idx.tolist())})
        ds = xr.Dataset(data, coords=coords)
        ds.attrs.update(attrs)
        return ds

    def attrs(self, protocol: str, params: dict) -> dict:
        full = {"eye_ephys": self.config.to_dict(), "protocol": protocol, "parameters": params,
                "eye": {"n_ommatidia": self.eye.n, "n_pairs": self.eye.n_pairs, "n_fields": self.fields.n_fields,
                        "summary": self.eye.summary()},
                "same_circuit_as": "experiments.eye_velocity.EyeVelocityConfig().circuit (lobula eye-velocity, "
                                   "lobula velocity EYE --front-end emd)"}
        return recording_attrs(protocol, full, params, eye="fly", dt_s=self.dt, trials=1, trials_requested=1,
                               trials_note="the compound eye's circuit is deterministic: one trial",
                               seed=0, neuron_model="none (LC field variables)",
                               emd_tau_s=self.config.circuit.emd.tau_s, dphi_deg=self.eye.config.dphi_deg)


def _sel(x, idx):
    if idx is None:
        return x
    if isinstance(x, torch.Tensor):
        return x.index_select(-1, torch.as_tensor(idx, dtype=torch.long))
    return x[..., idx]


# =========================================================================== protocols

def _radial(q: np.ndarray) -> np.ndarray:
    """Unit tangent vectors (..., 3) at directions q pointing away from the focus of expansion ẑ."""
    e = np.array([0.0, 0.0, 1.0])
    r = q * (q @ e)[..., None] - e
    n = np.linalg.norm(r, axis=-1, keepdims=True)
    return np.where(n > 1e-9, r / np.maximum(n, 1e-9), 0.0)


def _probe_pairs(rig: EyeRig) -> np.ndarray:
    """Per LC field, the EMD pair nearest its centre pointing radially away from ẑ (the rings' motion)."""
    eye = rig.eye
    align = np.einsum("pk,pk->p", eye.pair_direction, _radial(eye.pair_midpoint))
    good = np.flatnonzero(align > 0.8)
    d = rig.fields.directions @ eye.pair_midpoint[good].T                        # (F, G) cosines
    return np.unique(good[np.argmax(d, axis=1)])


def _eye_tf_tuning(cfg: EyeEphysConfig, *, temporal_frequencies_hz=None, contrasts=(0.5,),
                   wavelength_deg: float = 20.0, stimulus: str = "rings", direction_deg: float = 0.0,
                   duration_s: float = 2.0, settle_s: float = 0.5, record=None,
                   mean_luminance: float = 1.0) -> xr.Dataset:
    from stimuli.lattice_stimuli import GratingSource

    from .protocols import TF_GRID_HZ, steady_state_mean

    rig = EyeRig(cfg)
    tf = TF_GRID_HZ if temporal_frequencies_hz is None else np.atleast_1d(np.asarray(temporal_frequencies_hz, float))
    c = np.atleast_1d(np.asarray(contrasts, dtype=float))
    if stimulus not in ("rings", "grating"):
        raise ValueError(f"tf-tuning stimulus must be 'rings' or 'grating', got {stimulus!r}")
    if not (np.all(tf > 0) and np.all(np.isfinite(tf))):
        raise ValueError(f"temporal frequencies must be positive (Hz), got {tf.tolist()}")
    if np.any(tf >= rig.rate_hz / 2):
        raise ValueError(f"temporal frequencies must lie below the eye's Nyquist rate {rig.rate_hz / 2:g} Hz")
    if not np.all((c > 0) & (c <= 1)):
        raise ValueError(f"contrasts must lie in (0, 1], got {c.tolist()}")
    if not 0 <= settle_s < duration_s:
        raise ValueError(f"settle_s must lie in [0, duration_s = {duration_s}) s, got {settle_s}; "
                         f"use a longer --duration or a shorter --settle")
    probes = _probe_pairs(rig)
    want = rig.monitors(record, [f"emd.response[{','.join(map(str, probes))}]", "lc.input", "lc.r"])
    TF, C = np.meshgrid(tf, c, indexing="ij")
    n_steps = int(round(duration_s * rig.rate_hz))
    src = GratingSource(rig.lattice, kind="radial" if stimulus == "rings" else "drum", temporal_freq_hz=TF.ravel(),
                        contrast=C.ravel(), wavelength_deg=wavelength_deg, direction_deg=direction_deg,
                        centre_deg=(0.0, 0.0), mean_luminance=mean_luminance, frame_rate_hz=rig.rate_hz)
    rec = rig.run(src, n_steps, want, baseline=mean_luminance)
    params = dict(eye="fly", temporal_frequencies_hz=tf, contrasts=c, wavelength_deg=wavelength_deg,
                  stimulus=stimulus, direction_deg=direction_deg, duration_s=duration_s, settle_s=settle_s,
                  mean_luminance=mean_luminance, stimulus_info=src.info,
                  monitors=[k + ("" if v is None else f"[{','.join(map(str, v))}]") for k, v in want.items()])
    ds = rig.dataset(rec, want, {"temporal_frequency_hz": tf, "contrast": c}, n_steps,
                     rig.attrs("tf-tuning", params))
    t = ds.time.values
    for var in want:
        name = var.replace(".", "_")
        da = ds[name]
        mean = steady_state_mean(da.values, t, tf[:, None], settle_s)
        nd = da.dims[-1]
        ds[f"{name}_tuning"] = (("temporal_frequency_hz", "contrast", nd), mean, {
            "units": da.attrs["units"], "long_name": f"steady-state {da.attrs['long_name']} (mean over whole "
                                                     f"periods after {settle_s} s)"})
        ok = np.isfinite(mean).all(axis=0)
        peak = np.where(ok, tf[np.argmax(np.where(np.isfinite(mean), mean, -np.inf), axis=0)], np.nan)
        ds[f"{name}_peak_temporal_frequency_hz"] = (("contrast", nd), peak, {
            "units": "Hz", "long_name": f"temporal frequency of the largest steady-state {da.attrs['long_name']}"})
    tau = cfg.circuit.emd.tau_s
    pr = np.abs(photoreceptor_frequency_response(cfg.circuit.photoreceptor, rig.dt, tf)) ** 2
    dphase = 2.0 * math.pi * cfg.eye.dphi_deg / wavelength_deg
    pred = emd_sine_response_discrete(cfg.circuit.emd, rig.dt, tf, dphase) * pr
    ds["emd_prediction"] = ("temporal_frequency_hz", pred / pred.max(), {
        "units": "1", "long_name": "predicted EMD tuning, normalised to its maximum",
        "note": "exact discrete EMD tuning x |photoreceptor transfer|^2"})
    ds.attrs["optimum_hz"] = 1.0 / (2.0 * math.pi * tau)
    return cf_describe(ds)


def _eye_rf_locations(rig: EyeRig, fields: np.ndarray, extent: float, spacing: float, dphi: float) -> tuple:
    """Mapping locations (n, 2) (azimuth, elevation; degree) about the probed fields that the eye sees, and
    their directions (n, 3)."""
    from stimuli.lattice_stimuli import direction_from_angles

    f = rig.fields
    # Mapping grid: squares about each probed field, kept where the field's own eye sees.
    pts = []
    for k in fields:
        g = np.arange(-extent, extent + 1e-9, spacing)
        A, E = np.meshgrid(f.centres_deg[k, 0] + g, f.centres_deg[k, 1] + g, indexing="xy")
        pts.append(np.stack([A.ravel(), E.ravel()], 1))
    locs = np.unique(np.round(np.concatenate(pts) / spacing * 1e6) / 1e6 * spacing, axis=0)
    q = direction_from_angles(locs[:, 0], locs[:, 1])
    near = (q @ rig.eye.directions.T).max(axis=1) >= math.cos(math.radians(0.75 * dphi))
    locs, q = locs[near], q[near]
    if len(locs) == 0:
        raise ValueError("no mapping location lies on the eye; use a larger --extent or other --fields")
    return locs, q


def _eye_rf_weights(q: np.ndarray, locs: np.ndarray, dirs: np.ndarray, resp: np.ndarray, dphi: float) -> tuple:
    """Radial sensitivity, local preferred direction (degree) and the weight map (sensitivity over the
    template's sin θ), each (location, field), from the responses (location, direction, field); and each
    grid cell's relative solid angle (location,)."""
    from stimuli.lattice_stimuli import tangent_basis

    D = len(dirs)
    east, south = tangent_basis(q)
    rad = _radial(q)
    rad_ang = np.arctan2((rad * south).sum(1), (rad * east).sum(1))
    z = (resp * np.exp(1j * np.radians(dirs))[None, :, None]).sum(axis=1) * 2.0 / D       # (L, F)
    sens = np.real(z * np.exp(-1j * rad_ang)[:, None])
    pref = np.degrees(np.angle(z))
    # The template's magnitude sin θ (θ from the focus of expansion ẑ) divided out: the designed weights.
    sin_t = np.sqrt(np.clip(1.0 - q[:, 2] ** 2, 0.0, 1.0))
    ok = sin_t > math.sin(math.radians(dphi))
    weight = np.where(ok[:, None], sens / np.maximum(sin_t, 1e-9)[:, None], 0.0)
    area = np.cos(np.radians(locs[:, 1]))                    # solid angle of an az/el grid cell ∝ cos el
    return sens, pref, weight, area


def _eye_rf_moments(rig: EyeRig, fields: np.ndarray, q: np.ndarray, weight: np.ndarray, area: np.ndarray) -> tuple:
    """Mapped centre (F, 2) (degree), its error from the designed centre (F,) and size (F,) (degree, FWHM)
    of each probed field's weight map; NaN for the fields not probed."""
    f = rig.fields
    F = f.n_fields
    cen = np.full((F, 2), np.nan)
    err = np.full(F, np.nan)
    sz = np.full(F, np.nan)
    for k in fields:  # a handful of probed fields; each a vectorised moment computation
        w = np.clip(weight[:, k], 0.0, None) * area
        # Keep the field's own lobe: locations within 1.5 FWHM of the strongest, as the design cuts its weights.
        top = q[np.argmax(w)]
        w = np.where(np.degrees(np.arccos(np.clip(q @ top, -1, 1))) <= 1.5 * f.size_deg, w, 0.0)
        if w.sum() <= 0:
            continue
        m = (w[:, None] * q).sum(0)
        m /= np.linalg.norm(m)
        cen[k] = np.degrees([math.atan2(m[0], m[2]), math.atan2(m[1], math.hypot(m[0], m[2]))])
        err[k] = math.degrees(math.acos(min(1.0, float(m @ f.directions[k]))))
        ang = np.arccos(np.clip(q @ m, -1.0, 1.0))
        var = float((w * ang ** 2).sum() / w.sum()) / 2.0                     # per-axis variance (rad²)
        sz[k] = math.degrees(2.0 * math.sqrt(2.0 * math.log(2.0) * var))
    return cen, err, sz


def _eye_rf_map(cfg: EyeEphysConfig, *, fields=None, directions: int = 4, spacing_deg: float | None = None,
                extent_deg: float | None = None, spot_size_deg: float | None = None, path_deg: float | None = None,
                speed_deg_s: float | None = None, contrast: float = 1.0, tail_s: float = 0.12, batch: int = 128,
                record=None) -> xr.Dataset:
    from stimuli.lattice_stimuli import moving_spot

    rig = EyeRig(cfg)
    f = rig.fields
    F = f.n_fields
    fields = np.arange(F) if fields is None else np.unique(np.atleast_1d(np.asarray(fields, dtype=int)))
    if len(fields) == 0 or fields.min() < 0 or fields.max() >= F:
        raise ValueError(f"fields must be indices in [0, {F}) (the eye has {F} LC fields), got {fields.tolist()}")
    want = rig.monitors(record, ["lc.input"])
    if len(want) != 1 or next(iter(want)) != "lc.input" or next(iter(want.values())) is not None:
        raise ValueError("rf-map on the compound eye maps lc.input (the fields' matched-filter input; no subset: "
                         "choose fields with --fields)")
    dphi = cfg.eye.dphi_deg
    spacing = dphi if spacing_deg is None else float(spacing_deg)
    extent = 1.6 * f.size_deg if extent_deg is None else float(extent_deg)
    size = dphi if spot_size_deg is None else float(spot_size_deg)
    path = 2.0 * dphi if path_deg is None else float(path_deg)
    speed = 50.0 * dphi if speed_deg_s is None else float(speed_deg_s)
    if not (isinstance(directions, (int, np.integer)) and directions >= 3):
        raise ValueError(f"rf-map needs at least 3 spot directions, got {directions!r}")
    for name, val in (("spacing_deg", spacing), ("extent_deg", extent), ("spot_size_deg", size),
                      ("path_deg", path), ("speed_deg_s", speed), ("contrast", contrast)):
        if not (val > 0 and math.isfinite(val)):
            raise ValueError(f"rf-map {name} must be a positive number, got {val}")
    dirs = np.arange(directions) * 360.0 / directions
    locs, q = _eye_rf_locations(rig, fields, extent, spacing, dphi)
    L, D = len(locs), len(dirs)
    pass_s = path / speed
    n_steps = int(round((pass_s + tail_s) * rig.rate_hz))
    ev_loc, ev_dir = np.repeat(np.arange(L), D), np.tile(dirs, L)
    resp = np.empty((L * D, F))
    for a in range(0, L * D, batch):  # batches of spot passages, each a condition from rest
        b = min(L * D, a + batch)
        stim, _ = moving_spot(rig.lattice, n_steps, centre_deg=locs[ev_loc[a:b]], direction_deg=ev_dir[a:b],
                              speed_deg_s=speed, path_deg=path, t_mid_s=pass_s / 2.0, size_deg=size,
                              contrast=contrast, frame_rate_hz=rig.rate_hz)
        out = rig.run(stim, n_steps, {"lc.input": None}, baseline=1.0)
        resp[a:b] = out["lc.input"].sum(axis=1) * rig.dt
    resp = resp.reshape(L, D, F)
    sens, pref, weight, area = _eye_rf_weights(q, locs, dirs, resp, dphi)
    cen, err, sz = _eye_rf_moments(rig, fields, q, weight, area)
    params = dict(eye="fly", fields=fields, directions=dirs, spacing_deg=spacing, extent_deg=extent,
                  spot_size_deg=size, path_deg=path, speed_deg_s=speed, contrast=contrast, tail_s=tail_s,
                  recorded="lc.input")
    _, fc = rig.coords("lc.input", fields)
    ds = xr.Dataset({
        "rf_response": (("location", "direction_deg", "field"), resp[:, :, fields],
                        {"units": "s", "long_name": "time integral of the LC matched-filter input per spot passage",
                         "monitor": "lc.input"}),
        "rf_sensitivity": (("location", "field"), sens[:, fields], {
            "units": "s", "long_name": "local motion sensitivity along the radial (expansion) direction"}),
        "rf_weight": (("location", "field"), weight[:, fields], {
            "units": "s", "long_name": "radial sensitivity divided by the template magnitude sin(theta)"}),
        "rf_preferred_direction_deg": (("location", "field"), pref[:, fields], {
            "units": "degree", "long_name": "local preferred direction (0 east, 90 down)"}),
        "rf_centre_azimuth_deg": ("field", cen[fields, 0], {"units": "degree",
                                                            "long_name": "mapped RF centre azimuth"}),
        "rf_centre_elevation_deg": ("field", cen[fields, 1], {"units": "degree",
                                                              "long_name": "mapped RF centre elevation (positive down)"}),
        "rf_centre_error_deg": ("field", err[fields], {"units": "degree", "long_name":
                                                       "angle between the mapped and the designed RF centre"}),
        "rf_size_deg": ("field", sz[fields], {"units": "degree", "long_name": "mapped RF size (FWHM of the weight "
                                              "map's second moment; the probe's own spread not removed)"}),
    }, coords={"location": np.arange(L), "location_azimuth_deg": ("location", locs[:, 0]),
               "location_elevation_deg": ("location", locs[:, 1]), "direction_deg": dirs, **fc})
    ds.attrs.update(rig.attrs("rf-map", params))
    ds.attrs["dphi_deg"] = dphi
    return cf_describe(ds)


def _eye_looming(cfg: EyeEphysConfig, *, l_over_v_s=(0.01, 0.02, 0.04, 0.08), duration_s: float = 1.0,
                 t_collision_s: float | None = None, max_size_deg: float = 60.0, contrast: float = 1.0,
                 record=None) -> xr.Dataset:
    from stimuli.lattice_stimuli import looming_disc

    rig = EyeRig(cfg)
    lv = np.atleast_1d(np.asarray(l_over_v_s, dtype=float))
    if not np.all(lv > 0):
        raise ValueError(f"l/|v| values must be positive (s), got {lv.tolist()}")
    n_steps = int(round(duration_s * rig.rate_hz))
    tc = 0.8 * duration_s if t_collision_s is None else float(t_collision_s)
    if not 0 < tc <= duration_s:
        raise ValueError(f"the collision time must lie in (0, duration = {duration_s}] s, got {tc}")
    if not 0 < max_size_deg <= 180:
        raise ValueError(f"the disc's size cap must lie in (0, 180] degrees, got {max_size_deg}")
    want = rig.monitors(record, ["lc.input", "lc.r"])
    kw = dict(t_collision_s=tc, centre_deg=(0.0, 0.0), contrast=contrast, max_size_deg=max_size_deg,
              frame_rate_hz=rig.rate_hz)
    app, info = looming_disc(rig.lattice, n_steps, l_over_v_s=lv, **kw)
    rec_, info_r = looming_disc(rig.lattice, n_steps, l_over_v_s=lv, receding=True, **kw)
    stim = torch.stack([app.reshape(len(lv), n_steps, -1), rec_.reshape(len(lv), n_steps, -1)], 1)
    rec = rig.run(stim.reshape(2 * len(lv), n_steps, -1), n_steps, want, baseline=1.0)
    params = dict(eye="fly", l_over_v_s=lv, duration_s=duration_s, t_collision_s=tc, centre_deg=(0.0, 0.0),
                  max_size_deg=max_size_deg, contrast=contrast)
    ds = rig.dataset(rec, want, {"l_over_v_s": lv, "motion": np.array(["approach", "recede"])}, n_steps,
                     rig.attrs("looming", params))
    ds = ds.assign_coords(time=ds.time - tc)
    ds["time"].attrs.update(long_name="time relative to collision", units="s")
    sizes = np.stack([np.atleast_2d(info["angular_size_deg"]), np.atleast_2d(info_r["angular_size_deg"])], 1)
    ds["angular_size_deg"] = (("l_over_v_s", "motion", "time"), sizes, {
        "units": "degree", "long_name": f"disc angular size (capped at {max_size_deg:g} degrees)"})
    if "field" in ds.dims:
        # The fields the disc reaches: centre within its largest radius plus the field's half-width.
        f = rig.fields
        # The recorded fields (a subset keeps their indices) among the circuit's outputs (mirror sums: right eye).
        cen = np.radians(f.centres_deg if rig.n_outputs == f.n_fields else f.centres_deg[f.eye == 0])[ds.field.values]
        off = np.degrees(np.arccos(np.clip(np.cos(cen[:, 0]) * np.cos(cen[:, 1]), -1.0, 1.0)))
        ds = ds.assign_coords(field_sees_disc=("field", off <= 0.5 * (max_size_deg + f.size_deg), {"units": "1",
            "long_name": "the disc reaches the field (centre within half the disc's largest size plus half the "
                         "field's FWHM of straight ahead)"}))
    t = ds.time.values
    for var in ("lc_input", "lc_r"):
        if var not in ds:
            continue
        # Approach expands the image (ρ > 0 on the translation template), receding contracts it: each
        # motion's peak is its own sign's extreme.
        x = ds[var]
        sign = xr.DataArray([1.0, -1.0], dims="motion", coords={"motion": ds.motion})
        y = (x * sign).fillna(-np.inf)
        what = x.attrs["long_name"]
        ds[f"{var}_peak"] = (x.max("time").where(sign > 0, x.min("time"))).assign_attrs(
            units=x.attrs["units"], long_name=f"peak {what} (approach: largest; recede: most negative)")
        ds[f"{var}_time_of_peak_s"] = (t[y.argmax("time").values] * xr.ones_like(x.isel(time=0))).assign_attrs(
            units="s", long_name=f"time of that peak of the {what}, relative to collision")
    ds.attrs["t_collision_s"] = tc
    return cf_describe(ds)


eye_tf_tuning = protocol(_eye_tf_tuning, EyeEphysConfig,
                         "Temporal-frequency tuning of the compound eye's velocity circuit (see the module docstring).")
eye_rf_map = protocol(_eye_rf_map, EyeEphysConfig,
                      "Receptive-field maps of the compound eye's LC fields (see the module docstring).")
eye_looming = protocol(_eye_looming, EyeEphysConfig,
                       "A dark disc approaching (or receding) straight ahead of the compound eye.")




#: options of `lobula ephys` that the compound eye's rig does not take, with the reason
_NOT_ON_EYE = {
    "trials": "the eye's circuit is deterministic (one trial)",
    "seed": "the eye's circuit has no noise to seed",
    "neuron_model": "the eye's LC fields feed the readout directly (no LC neuron model); the spiking output is the "
                    "readout neuron's (`lobula velocity EYE --front-end emd --readout neuron`)",
    "device": "the eye rig runs on the CPU",
}


def run_eye_protocol(protocol: str, opts: dict, stimulus: dict) -> xr.Dataset:
    """``lobula ephys PROTOCOL --eye fly``: the command's options mapped onto the compound eye's rig.

    stimulus: the protocol's stimulus keywords (:func:`experiments.ephys.command.stimulus_kwargs`).
    """
    for k, why in _NOT_ON_EYE.items():
        if k in opts:
            raise ValueError(f"--{k.replace('_', '-')} does not apply with --eye fly: {why}; drop it")
    run = {"tf-tuning": eye_tf_tuning, "rf-map": eye_rf_map, "looming": eye_looming}.get(protocol)
    if run is not None:
        cfg = EyeEphysConfig().with_options(tau_s=opts.get("tau"), dphi_deg=opts.get("dphi"),
                                            field_size_deg=opts.get("field_size"))
        return run(cfg, record=opts.get("record"), **stimulus)
    raise ValueError(f"--eye fly applies to tf-tuning, rf-map and looming, not {protocol}")
