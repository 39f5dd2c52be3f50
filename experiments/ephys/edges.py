"""The lobula plate in the rig (T4/T5 layers, HS/VS cells) and the ``edges`` protocol.

Recording: :func:`plate_records` turns the circuit's photoreceptor output into the monitored
lobula-plate variables (``t4.response``, ``t5.response``: time × ommatidium × preferred
direction; ``hs.v``, ``vs.v``: mV, one per cell); :func:`cell_coords` labels the HS and VS
cells. :class:`experiments.ephys.rig.Rig` calls both, only when a monitor asks.

Protocol: :func:`edges` moves ON and OFF edges (or bars) across the eye in the four
directions of :data:`lobula.motion_pathways.DIRECTIONS` and measures the polarity and
direction selectivity of T4 and T5 and the HS/VS responses; :func:`plot_edges` draws it.
"""
from __future__ import annotations

import json
import math

import numpy as np
import xarray as xr

from lobula._optional import torch
from lobula.motion_pathways import DIRECTIONS, lamina_on_off, t4_t5
from lobula.tangential_cells import hs_vs, tangential_fields
from stimuli.gratings import drum_coordinates
from stimuli.lattice_stimuli import moving_edge

from .protocols import _specs
from .rig import (LAYER_RECORDS, PATHWAY_RECORDS, EphysConfig, Monitor, Rig, cf_describe, monitors_for, protocol,
                  record_dataset, rig_attrs)

__all__ = ["plate_records", "lamina_input", "select", "cell_coords", "edges", "plot_edges", "edges_summary",
           "POLARITIES", "OPPOSITE"]

#: edge polarities: ON (dark → bright; a bright bar) and OFF (bright → dark; a dark bar)
POLARITIES = ("on", "off")
#: each direction's opposite (the null direction of its T4/T5 layer)
OPPOSITE = {"front_to_back": "back_to_front", "back_to_front": "front_to_back", "upward": "downward",
            "downward": "upward"}


# =========================================================================== recording

def lamina_input(rig: Rig, y):
    """The photoreceptor signal before its LMC-like high-pass, from the circuit's output ``y`` (B, T, n).

    The circuit's photoreceptor ends in a first-order high-pass ``y = s − m``,
    ``m[t] = a·m[t−1] + (1 − a)·s[t]``, a = exp(−dt/τ_hp), which inverts exactly:
    ``s[t] − m[−1] = y[t] + ((1 − a)/a)·Σ_{k≤t} y[k]``. The constant m[−1] (the adapted
    level) is dropped: the lamina's high-pass removes it. So L1/L2 apply their own high-pass
    (:class:`lobula.motion_pathways.OnOffConfig`'s τ_hp), not a second one on top of the
    photoreceptor's: two in a row undershoot after every edge, and each ON edge would drive
    the OFF pathway. Same units as y (B, T, n).
    """
    pc = rig.config.circuit.photoreceptor
    if pc.tau_hp_s is None:
        return y
    if pc.tau_gain_s is not None:
        raise ValueError("the lobula plate needs the photoreceptor signal before its high-pass, which contrast gain "
                         "control (tau_gain_s) makes unrecoverable; record T4/T5/HS/VS with tau_gain_s None")
    a = math.exp(-rig.dt / pc.tau_hp_s)
    return (y.double() + (1.0 - a) / a * torch.cumsum(y.double(), dim=-2)).to(y.dtype)


def plate_records(rig: Rig, y, monitors) -> dict:
    """The lobula plate's monitored variables from the photoreceptor output ``y`` (B, T, n).

    :func:`lobula.motion_pathways.lamina_on_off` on the photoreceptor signal before its own
    high-pass (:func:`lamina_input`), then :func:`~lobula.motion_pathways.t4_t5` and, when HS or
    VS is monitored, :func:`~lobula.tangential_cells.hs_vs`, all at the rig's step dt, with the
    rig's :class:`~lobula.motion_pathways.OnOffConfig` and
    :class:`~lobula.tangential_cells.TangentialConfig`.

    Returns {variable: tensor}: t4/t5 (B, T, X, L) (the monitor's ommatidia and layers), hs.v
    (B, T, n_hs) and vs.v (B, T, n_vs) in mV (the monitor's cells).
    """
    cfg, dt = rig.config, rig.dt
    ch = lamina_on_off(lamina_input(rig, y), dt, cfg.on_off)
    layers = t4_t5(ch.on, ch.off, rig.lattice, cfg.on_off, dt)
    want = {m.variable: m for m in monitors}
    full = {"t4.response": layers.t4, "t5.response": layers.t5}
    if "hs.v" in want or "vs.v" in want:
        cells = hs_vs(layers.t4, layers.t5, rig.lattice, cfg.tangential, dt)
        full.update({"hs.v": cells.hs, "vs.v": cells.vs})
    return {k: select(full[k], m) for k, m in want.items()}


def _take(x, idx, axis: int):
    return x if idx is None else x.index_select(axis, torch.as_tensor(idx, dtype=torch.long, device=x.device))


def select(x, monitor: Monitor):
    """A lobula-plate tensor reduced to a monitor's subset: its ommatidia (axis −2 of T4/T5 (B, T, n, 4))
    or cells (axis −1 of HS/VS (B, T, c)), and its T4/T5 layers (axis −1)."""
    if monitor.variable in LAYER_RECORDS:
        return _take(_take(x, monitor.neurons, -2), monitor.layers, -1)
    return _take(x, monitor.neurons, -1)


def cell_coords(rig: Rig, dim: str) -> dict:
    """Coordinates of every HS (``dim`` "hs_cell") or VS ("vs_cell") cell: index, name and the mean
    elevation (HS) or azimuth (VS) of its receptive field (degree); {name: values or (dim, values, attrs)}."""
    w_hs, w_vs = tangential_fields(rig.lattice, rig.config.tangential)
    lat = rig.lattice
    if dim == "hs_cell":
        names = ["HSN", "HSE", "HSS"] if len(w_hs) == 3 else [f"HS{i}" for i in range(len(w_hs))]
        return {"hs_cell": np.arange(len(w_hs)),
                "hs_cell_name": ("hs_cell", np.array(names), {"long_name": "HS cell name, dorsal to ventral"}),
                "hs_cell_elevation_deg": ("hs_cell", w_hs @ lat.elevation_deg / w_hs.sum(1), {
                    "units": "degree", "long_name": "HS receptive-field mean elevation (positive down)"})}
    return {"vs_cell": np.arange(len(w_vs)),
            "vs_cell_name": ("vs_cell", np.array([f"VS{i + 1}" for i in range(len(w_vs))]),
                             {"long_name": "VS cell name, in order of increasing azimuth"}),
            "vs_cell_azimuth_deg": ("vs_cell", w_vs @ lat.azimuth_deg / w_vs.sum(1), {
                "units": "degree", "long_name": "VS receptive-field mean azimuth"})}


#: units and long names of the coordinates made here
_DESCRIBE = {
    "polarity": (None, "edge polarity: on (dark to bright, or a bright bar), off (bright to dark, or a dark bar)"),
    "direction": (None, "direction of motion, named for the fly's body (front_to_back: progressive)"),
    "direction_image_deg": ("degree", "direction of motion in the image (0 right, 90 down)"),
}


# =========================================================================== protocol

def _image_angles(eye: str) -> np.ndarray:
    """Image angle (degree; 0 right, 90 down) of each of :data:`DIRECTIONS` for a right or left eye."""
    ftb = 0.0 if eye == "right" else 180.0
    return np.array([ftb, (ftb + 180.0) % 360.0, 270.0, 90.0])


def _stimulus(rig: Rig, angles, polarity: str, n_steps: int, speed: float, contrast: float, bar_deg, lum0: float):
    """Luminance (D, T, n) of ON/OFF edges or bars moving in the image directions ``angles`` (D,), and the
    leading edge's start (D,) (degree of drum longitude, just outside the eye)."""
    kw = dict(direction_deg=angles, speed_deg_s=speed, frame_rate_hz=1.0 / rig.dt, device=rig.config.device)
    # An ON edge of contrast 1 about a mean of 0.5 is the fraction of each acceptance the edge has passed.
    lead, info = moving_edge(rig.lattice, n_steps, polarity="on", contrast=1.0, mean_luminance=0.5, **kw)
    sign = 1.0 if polarity == "on" else -1.0
    if bar_deg is None:
        return lum0 * (1.0 + sign * contrast * (2.0 * lead - 1.0)), np.asarray(info["start_deg"])
    trail, _ = moving_edge(rig.lattice, n_steps, polarity="on", contrast=1.0, mean_luminance=0.5,
                           start_deg=np.asarray(info["start_deg"]) - bar_deg, **kw)
    return lum0 * (1.0 + sign * contrast * (lead - trail)), np.asarray(info["start_deg"])


def _centre_columns(rig: Rig) -> list[int]:
    """The ommatidium nearest the eye's centre and its neighbours (within 1.5 Δφ)."""
    lat = rig.lattice
    az, el = lat.azimuth_deg, lat.elevation_deg
    c = int(np.argmin(np.hypot(az - np.median(az), el - np.median(el))))
    return np.flatnonzero(np.hypot(az - az[c], el - el[c]) <= 1.5 * lat.dphi_deg).tolist()


def _edges(config: EphysConfig, *, speed_deg_s: float = 50.0, contrast: float = 0.5, bar_width_deg=None,
           duration_s: float | None = None, tail_s: float = 0.3, mean_luminance: float = 1.0, record=None,
           tau_s: float | None = None) -> xr.Dataset:
    """ON and OFF edges (or bars) moving front-to-back, back-to-front, upward and downward.

    Conditions: dims ``polarity`` (on, off) × ``direction`` (:data:`lobula.motion_pathways.DIRECTIONS`,
    image angles by the eye's side, ``OnOffConfig.eye``). An edge of Michelson ``contrast`` between
    L₀(1 ∓ C) and L₀(1 ± C) sweeps across the eye at ``speed_deg_s`` (degree/s), starting just outside
    it; ``bar_width_deg`` makes it a bar of that width (degree), bright (on) or dark (off) on L₀. The
    eye starts adapted to the first frame. duration_s: default until the edge (the bar's trailing
    edge) has left the eye in every direction, plus ``tail_s``. tau_s: the correlators' delay τ (s)
    (EMD, T4 and T5). record: monitors (default: T4 and T5 of the eye's central column and its
    neighbours, HS and VS).

    The analysis uses the whole T4/T5 layers whatever is recorded: ``t4_mean_response`` and
    ``t5_mean_response`` (polarity, direction, preferred_direction), the mean over time and
    ommatidia; ``t4_dsi`` (from ON stimuli) and ``t5_dsi`` (from OFF), per preferred direction d,
    DSI = (R_pref − R_null)/(R_pref + R_null) with R the layer's mean response to motion along d
    (pref) and against it (null); ``hs_v_peak``/``hs_v_trough``/``hs_v_mean`` (and VS): the
    largest, smallest and mean potential (mV) per cell and condition; ``edge_enters_s`` and
    ``edge_leaves_s`` (direction).
    """
    from dataclasses import replace

    cfg = config or EphysConfig()
    if tau_s is not None:
        cfg = replace(cfg.with_tau(tau_s), on_off=replace(cfg.on_off, tau_delay_t4_s=float(tau_s),
                                                          tau_delay_t5_s=float(tau_s)))
    for name, val in (("speed_deg_s", speed_deg_s), ("mean_luminance", mean_luminance)):
        if not (val > 0 and math.isfinite(val)):
            raise ValueError(f"edges {name} must be a positive number, got {val}")
    if not (tail_s >= 0 and math.isfinite(tail_s)):
        raise ValueError(f"edges tail_s must be a non-negative number of seconds, got {tail_s}")
    if not 0 < contrast <= 1:
        raise ValueError(f"edges contrast must lie in (0, 1], got {contrast}")
    if bar_width_deg is not None and not (bar_width_deg > 0 and math.isfinite(bar_width_deg)):
        raise ValueError(f"the bar width must be a positive number of degrees, got {bar_width_deg}")
    rig = Rig(cfg)
    lat = rig.lattice
    angles = _image_angles(cfg.on_off.eye)
    psi = np.degrees(drum_coordinates(lat.directions, angles)[0])                    # (D, n) drum longitude
    _, start = _stimulus(rig, angles, "on", 1, speed_deg_s, contrast, bar_width_deg, mean_luminance)
    width = 0.0 if bar_width_deg is None else float(bar_width_deg)
    enters = (psi.min(1) - start) / speed_deg_s
    leaves = (psi.max(1) + width - start) / speed_deg_s
    if duration_s is None:
        duration_s = float(leaves.max()) + tail_s
    n_steps = int(round(duration_s / rig.dt))
    if n_steps < 2:
        raise ValueError(f"the edges' duration must span at least two steps of {rig.dt} s, got {duration_s} s")
    cols = ",".join(map(str, _centre_columns(rig)))
    monitors = monitors_for(rig, record, [f"t4.response[{cols}]", f"t5.response[{cols}]", "hs.v", "vs.v"])
    # The analysis needs whole layers and every cell: run them whole, keep the monitors' subsets.
    plate = {v: Monitor(v) for v in PATHWAY_RECORDS}
    run_mons = [plate.pop(m.variable, m) for m in monitors] + list(plate.values())
    stim = torch.cat([_stimulus(rig, angles, p, n_steps, speed_deg_s, contrast, bar_width_deg, mean_luminance)[0]
                      for p in POLARITIES])                                           # (P·D, T, n)
    recs = rig.run(stim, n_steps, run_mons)
    full = {v: recs[v] for v in PATHWAY_RECORDS}
    for m in monitors:
        if m.variable in PATHWAY_RECORDS:
            recs[m.variable] = select(recs[m.variable], m)
    params = dict(speed_deg_s=speed_deg_s, contrast=contrast, bar_width_deg=bar_width_deg, duration_s=duration_s,
                  tail_s=tail_s, mean_luminance=mean_luminance, direction_image_deg=angles,
                  monitors=_specs(monitors))
    ds = record_dataset(rig, recs, monitors, {"polarity": np.array(POLARITIES), "direction": np.array(DIRECTIONS)},
                        n_steps, rig_attrs(rig, "edges", params))
    _analyse(ds, rig, full, enters, leaves, angles, bar_width_deg)
    for name, (units, long_name) in _DESCRIBE.items():
        if name in ds.variables:
            ds[name].attrs.update({"long_name": long_name, **({"units": units} if units else {})})
    return cf_describe(ds)


def _analyse(ds: xr.Dataset, rig: Rig, full: dict, enters, leaves, angles, bar_width_deg) -> None:
    """Mean T4/T5 responses, their DSIs, HS/VS peaks and the edge's passage, into ``ds``: for the layers
    and cells the monitors recorded (all when a variable is not recorded), over whole layers."""
    P, D = len(POLARITIES), len(DIRECTIONS)
    what = "bars" if bar_width_deg is not None else "edges"
    ds.coords["direction_image_deg"] = ("direction", angles)
    if "preferred_direction" not in ds.coords:
        ds.coords["preferred_direction"] = np.array(DIRECTIONS)
    layers = [DIRECTIONS.index(str(n)) for n in ds.preferred_direction.values]
    for cell, pol in (("t4", "on"), ("t5", "off")):
        m = full[f"{cell}.response"].double().mean((1, 2)).reshape(P, D, D).cpu().numpy()
        ds[f"{cell}_mean_response"] = (("polarity", "direction", "preferred_direction"), m[:, :, layers], {
            "units": "1", "long_name": f"{cell.upper()} response averaged over time and every ommatidium of "
                                       f"each layer"})
        k = POLARITIES.index(pol)
        pref = np.array([m[k, d, d] for d in layers])
        null = np.array([m[k, DIRECTIONS.index(OPPOSITE[DIRECTIONS[d]]), d] for d in layers])
        with np.errstate(invalid="ignore", divide="ignore"):
            dsi = np.where(pref + null > 0, (pref - null) / (pref + null), np.nan)
        ds[f"{cell}_dsi"] = ("preferred_direction", dsi, {
            "units": "1", "long_name": f"{cell.upper()} direction-selectivity index (R_pref - R_null)/(R_pref + "
                                       f"R_null) of each layer, {pol.upper()} {what}",
            "note": "R: the layer's mean response (t*_mean_response) to motion along its preferred direction "
                    "(pref) and the opposite one (null)"})
    for cell in ("hs", "vs"):
        dim = f"{cell}_cell"
        if dim not in ds.coords:
            ds.coords.update(cell_coords(rig, dim))
        v = full[f"{cell}.v"].double().cpu().numpy()[..., ds[dim].values]            # (P·D, T, c)
        v = v.reshape((P, D) + v.shape[1:])
        for stat, fn, words in (("peak", np.max, "largest"), ("trough", np.min, "smallest"),
                                ("mean", np.mean, "mean")):
            ds[f"{cell}_v_{stat}"] = (("polarity", "direction", dim), fn(v, axis=2), {
                "units": "mV", "long_name": f"{words} {cell.upper()} membrane potential relative to rest over "
                                            "the recording"})
    ds["edge_enters_s"] = ("direction", enters, {"units": "s", "long_name": "time the leading edge reaches the "
                                                                           "eye's first ommatidium"})
    ds["edge_leaves_s"] = ("direction", leaves, {"units": "s", "long_name": "time the (trailing) edge passes "
                                                                           "the eye's last ommatidium"})
    ds.attrs["stimulus"] = what


edges = protocol(_edges, EphysConfig)


# =========================================================================== summary and figure

def edges_summary(ds: xr.Dataset) -> list[str]:
    """Lines describing a stored ``edges`` recording: DSIs, polarity ratios, HS/VS mean potentials."""
    lines = [f"{ds.attrs.get('stimulus', 'edges')} at {json_param(ds, 'speed_deg_s'):g} degree/s, contrast "
             f"{json_param(ds, 'contrast'):g}"]
    for cell in ("t4", "t5"):
        lines.append(f"{cell.upper()} DSI per preferred direction: " + ", ".join(
            f"{d} {float(v):.3f}" for d, v in zip(ds.preferred_direction.values, ds[f"{cell}_dsi"].values)))
    t4 = ds.t4_mean_response.mean(("direction", "preferred_direction"))
    t5 = ds.t5_mean_response.mean(("direction", "preferred_direction"))
    for pol in POLARITIES:
        a, b = float(t4.sel(polarity=pol)), float(t5.sel(polarity=pol))
        lines.append(f"{pol.upper()}: mean T4 {a:.3g}, mean T5 {b:.3g}")
    for cell in ("hs", "vs"):
        m = ds[f"{cell}_v_mean"].mean(f"{cell}_cell")
        lines.append(f"{cell.upper()} mean potential (mV, cell mean), ON: " + ", ".join(
            f"{d} {float(m.sel(polarity='on', direction=d)):+.1f}" for d in DIRECTIONS))
    return lines


def json_param(ds: xr.Dataset, key: str):
    """One stimulus parameter of a stored recording (its ``parameters`` attribute)."""
    return json.loads(ds.attrs["parameters"])[key]


def plot_edges(ds: xr.Dataset, path) -> list:
    """T4 and T5: mean response of each layer against the direction of motion (polar; solid ON, dashed
    OFF); HS and VS: cell-mean potential against time for each direction (ON solid, OFF dashed), the
    edge's passage across the eye shaded. PNG and PDF."""
    from .figures import _colours, _plt, save_png_and_pdf

    plt = _plt()
    fig = plt.figure(figsize=(10.5, 8.6), layout="constrained")
    cols = _colours(len(DIRECTIONS))
    ang = np.radians(np.append(ds.direction_image_deg.values, ds.direction_image_deg.values[0]))
    top = max(float(ds.t4_mean_response.max()), float(ds.t5_mean_response.max()))
    polar = {}
    for i, cell in enumerate(("t4", "t5")):
        a = polar[cell] = fig.add_subplot(2, 2, i + 1, projection="polar")
        a.set_theta_zero_location("E")
        a.set_theta_direction(-1)                                  # image angles: 90 degrees points down
        for name in ds.preferred_direction.values:
            col = cols[DIRECTIONS.index(str(name))]
            for pol, ls in zip(POLARITIES, ("-", "--")):
                r = ds[f"{cell}_mean_response"].sel(polarity=pol, preferred_direction=name).values
                a.plot(ang, np.append(r, r[0]), ls=ls, color=col, lw=1.6, marker="o", ms=3,
                       label=f"{name.replace('_', '-')} layer" if pol == "on" else None)
        a.set_ylim(0, 1.2 * top)
        a.set_xticks(ang[:-1])
        a.set_xticklabels([n.replace("_", "-") for n in DIRECTIONS], fontsize=8)
        a.tick_params(axis="x", pad=10)                            # the names clear of the outer ring
        a.tick_params(axis="y", labelsize=6)
        a.set_rlabel_position(135)                                 # between back-to-front and downward
        dsi = ds[f"{cell}_dsi"].values
        pol = "ON" if cell == "t4" else "OFF"
        on, off = (float(ds[f"{cell}_mean_response"].sel(polarity=p).mean()) for p in POLARITIES)
        a.set_title(f"{cell.upper()} mean response per layer vs direction of motion\n(solid ON, dashed OFF "
                    f"{ds.attrs.get('stimulus', 'edges')}; DSI ({pol}) {np.nanmin(dsi):.2f}–{np.nanmax(dsi):.2f};\n"
                    f"mean over layers and directions: ON {on:.3g}, OFF {off:.3g})", fontsize=9)
        if i == 0:
            a.legend(fontsize=7, loc="upper left", bbox_to_anchor=(-0.25, 1.12), frameon=False)
    from .figures import edges_overlay
    edges_overlay(polar, ds, path)
    t = ds.time.values
    for i, cell in enumerate(("hs", "vs")):
        a = fig.add_subplot(2, 2, 3 + i)
        var = f"{cell}_v"
        a.axhline(0, color="0.6", lw=0.8)
        if var not in ds:
            a.text(0.5, 0.5, f"{var.replace('_', '.')} not recorded", ha="center", transform=a.transAxes)
            continue
        for name, col in zip(DIRECTIONS, cols):
            for pol, ls in zip(POLARITIES, ("-", "--")):
                v = ds[var].sel(polarity=pol, direction=name).mean(f"{cell}_cell").values
                a.plot(t, v, ls=ls, color=col, lw=1.3,
                       label=f"{name.replace('_', '-')} motion" if pol == "on" else None)
        a.axvspan(float(ds.edge_enters_s.min()), float(ds.edge_leaves_s.max()), color="0.88", zorder=0,
                  label=f"{ds.attrs.get('stimulus', 'edges')[:-1]} crossing the eye")
        a.set_xlabel("time since stimulus onset (s)")
        a.set_ylabel(f"{cell.upper()} potential re rest (mV, mean of {ds.sizes[f'{cell}_cell']} cells)")
        gap = float(np.abs(ds[var].sel(polarity="on") - ds[var].sel(polarity="off")).max())
        a.set_title(f"{cell.upper()} cells (solid ON, dashed OFF" + (f"; they coincide within {gap:.2g} mV)"
                                                                  if gap < 0.1 else ")"), fontsize=9)
        a.legend(fontsize=7, frameon=False, loc="best")
    fig.suptitle(f"Moving {ds.attrs.get('stimulus', 'edges')}: {json_param(ds, 'speed_deg_s'):g} degree/s, "
                 f"contrast {json_param(ds, 'contrast'):g} (Δφ = "
                 f"{json.loads(ds.attrs['config'])['ephys']['lattice']['dphi_deg']:g}°)", fontsize=10)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)
