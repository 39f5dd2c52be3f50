"""Figures of the ephys protocols, drawn from the stored recording only (so a figure can be redrawn
from its NetCDF): axes in the science's words with units, one colour per stimulus condition
across panels, SEM error bars, raster beside PSTH, labelled colour bars. Each figure is
written as a PNG (200 dpi) and a vector PDF beside it.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import xarray as xr

from .protocols import psth, psth_sem, raster

__all__ = ["plot_tf_tuning", "plot_rf_map", "plot_looming", "plot_recording", "plot_eye_tf_tuning", "save_png_and_pdf", "nanmean", "sem", "DPI"]

DPI = 200


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_png_and_pdf(fig, path, provenance: dict | None = None) -> list[Path]:
    """Save ``fig`` at ``path`` (.png or .pdf) and the other format beside it, atomically; close it. Both carry
    ``provenance`` (the recording's attributes: its configuration) in their metadata.

    Cropped to what is drawn (``bbox_inches="tight"``): no blank band where a figure's width
    outgrows its panels (one field's map, one tuning panel)."""
    from experiments.store import save_figure

    path = Path(path)
    if path.suffix.lower() not in (".png", ".pdf"):
        raise ValueError(f"figure path {path} must end in .png or .pdf (both are written)")
    other = path.with_suffix(".pdf" if path.suffix.lower() == ".png" else ".png")
    out = [save_figure(fig, p, provenance=provenance, dpi=DPI, bbox_inches="tight", pad_inches=0.08) for p in (path, other)]
    _plt().close(fig)
    return out


def _colours(n: int):
    cmap = _plt().get_cmap("viridis" if n > 6 else "tab10")
    return [cmap(i / max(1, n - 1) * 0.9) if n > 6 else cmap(i) for i in range(n)]


def sem(x: np.ndarray, axis: int) -> np.ndarray:
    """Standard error of the mean along ``axis`` ignoring NaN; NaN where fewer than 2 values (no warning)."""
    n = np.sum(np.isfinite(x), axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        sd = np.sqrt(np.nansum((x - nanmean(x, axis, keepdims=True)) ** 2, axis=axis) / np.maximum(n - 1, 1))
        return np.where(n >= 2, sd / np.sqrt(np.maximum(n, 1)), np.nan)


def nanmean(x, axis, keepdims=False):
    """Mean along ``axis`` ignoring NaN; NaN where no value (no warning)."""
    n = np.sum(np.isfinite(x), axis=axis, keepdims=keepdims)
    s = np.nansum(x, axis=axis, keepdims=keepdims)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def _style(i: int) -> dict:
    """Marker and line style of the i-th condition, so that overlapping curves stay visible."""
    return dict(marker="osD^v"[i % 5], ms=5 - 0.6 * (i % 3), mfc="none" if i % 2 else None, capsize=2,
                ls=("-", "--", ":", "-.")[i % 4], lw=1.3)


def _units_of(ds: xr.Dataset, da: xr.DataArray, unit_type: str) -> xr.DataArray:
    keep = ds.neuron_type.sel(neuron=da.neuron).values == unit_type
    return da.isel(neuron=np.nonzero(keep)[0]) if keep.any() else da


def _neuron_var(ds: xr.Dataset) -> str | None:
    for v in ("lc_rate", "lc_spikes", "lc_v", "lc_x", "lc_drive"):
        if v in ds:
            return v
    return None


#: the longest stretch of a raster (s): longer, a row's ticks merge into a bar
RASTER_MAX_S = 3.0
#: spikes per trial in the raster's window above which the ticks form a solid block: an ISI histogram instead
RASTER_MAX_SPIKES = 300


def _shade_baseline(a, t0: float, onset: float) -> None:
    """Grey band over the pre-stimulus baseline [t0, onset) and a line at stimulus onset."""
    if t0 < onset:
        a.axvspan(t0, onset, color="0.9", lw=0, zorder=0)
    a.axvline(onset, color="0.4", lw=0.8, ls=":", zorder=1)


def _isi_histogram(a, ts, tr, k: int, colour, t_from: float) -> None:
    """Inter-spike intervals after ``t_from`` (s) per trial, binned in ms: mean count per trial ± SEM across
    trials (the raster of a unit firing this fast would be a solid block)."""
    isis = []
    for j in range(k):
        t = np.sort(ts[(tr == j) & (ts >= t_from)])
        isis.append(np.diff(t) * 1e3)
    allv = np.concatenate(isis) if isis else np.zeros(0)
    top = float(np.percentile(allv, 99)) if allv.size else 1.0
    edges = np.linspace(0.0, max(top, 1.0), 31)
    h = np.stack([np.histogram(x, edges)[0] for x in isis]).astype(float)             # (trial, bin)
    m = h.mean(0)
    mid = 0.5 * (edges[1:] + edges[:-1])
    a.step(mid, m, where="mid", color=colour, lw=1.2, label=f"mean over {k} trials")
    if k >= 2:
        e = h.std(0, ddof=1) / np.sqrt(k)
        a.fill_between(mid, m - e, m + e, step="mid", color=colour, alpha=0.3, lw=0, label="± SEM across trials")
    a.set_xlabel("inter-spike interval (ms)")
    a.set_ylabel(f"intervals per trial ({edges[1]:.2g} ms bins)")
    a.set_xlim(0, edges[-1])
    a.legend(fontsize=7, loc="upper right", frameon=False)


def _raster_psth(fig, a_r, a_p, ds, neuron, colour, t_label, t_shift=0.0, bin_s=0.02, onset=0.0, **sel):
    """A raster (integer trial ticks) of one unit over at most :data:`RASTER_MAX_S` from the recording's
    start, or its ISI histogram where the raster would be a solid block, and beside it the PSTH ± SEM
    across trials with its pre-stimulus baseline (before ``onset``, s, on the plotted axis) shaded and its
    mean drawn. Returns "raster" or "isi", the panel drawn on ``a_r``."""
    ts, tr = raster(ds, neuron, **sel)
    ts = ts - t_shift
    k = ds.sizes["trial"]
    t = ds.time.values - t_shift
    t_end = min(float(t[-1]), float(t[0]) + RASTER_MAX_S)
    shown = ts <= t_end
    per_trial = shown.sum() / max(k, 1)
    kind = "isi" if per_trial > RASTER_MAX_SPIKES else "raster"
    if kind == "raster":
        a_r.vlines(ts[shown], tr[shown] - 0.4, tr[shown] + 0.4, color=colour, lw=0.8)
        a_r.set_yticks(range(k) if k <= 10 else np.linspace(0, k - 1, 6).astype(int))
        a_r.set_ylim(-0.6, k - 0.4)
        a_r.set_xlim(float(t[0]), t_end)
        a_r.set_ylabel("trial")
        a_r.set_xlabel(t_label)
        _shade_baseline(a_r, float(t[0]), onset)
    else:
        _isi_histogram(a_r, ts, tr, k, colour, onset)
    one = ds[["lc_spikes"]].sel(neuron=[neuron]).sel(**sel)
    p = psth(one, bin_s=bin_s).squeeze()
    tt = p.time.values - t_shift
    _shade_baseline(a_p, float(t[0]), onset)
    a_p.plot(tt, p.values, color=colour, lw=1.2, label="PSTH (trial mean)")
    if k >= 2:
        e = psth_sem(one, bin_s=bin_s).squeeze().values
        a_p.fill_between(tt, p.values - e, p.values + e, color=colour, alpha=0.3, lw=0, label=f"± SEM ({k} trials)")
    pre = tt < onset
    if pre.any():
        a_p.axhline(float(np.mean(p.values[pre])), color="0.3", lw=0.9, ls="--",
                    label=f"baseline mean ({float(np.mean(p.values[pre])):.3g} Hz)")
    a_p.set_xlabel(t_label)
    a_p.set_ylabel(f"firing rate (Hz, {p.attrs['bin_s'] * 1e3:.0f} ms bins)")
    a_p.set_xlim(float(t[0]), float(t[-1]))
    a_p.set_ylim(bottom=0)
    a_p.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), frameon=False, ncol=2)
    return kind


# =========================================================================== tf-tuning

def plot_tf_tuning(ds: xr.Dataset, path) -> list[Path]:
    """EMD probe pairs (normalised to each curve's maximum, with the exact prediction) and LC expansion
    units (absolute rate, mean ± SEM across units) against temporal frequency, one colour per contrast;
    with spikes, a raster and the PSTH ± SEM of one expansion unit at the optimum."""
    plt = _plt()
    spikes = "lc_spikes" in ds
    var = _neuron_var(ds)
    # Only the panels the recording has data for: an empty panel is a blank band in the figure.
    names = ([k for k, has in (("emd", "emd_response_tuning" in ds), ("lc", bool(var and f"{var}_tuning" in ds)))
              if has] + (["raster", "psth"] if spikes else []))
    if not names:
        raise ValueError("the tf-tuning recording holds no EMD probe pairs, LC tuning or spikes to plot; "
                         "record emd.response or an LC variable (--record)")
    fig, axes = plt.subplots(1, len(names), figsize=(4.3 * len(names), 4.2), squeeze=False, layout="constrained")
    ax = dict(zip(names, axes[0]))
    tf = ds.temporal_frequency_hz.values
    opt = ds.attrs.get("optimum_hz")
    cols = _colours(ds.sizes["contrast"])
    if "emd" in ax:
        a = ax["emd"]
        da = ds.emd_response_tuning
        for i, (c, col) in enumerate(zip(ds.contrast.values, cols)):
            y = da.sel(contrast=c).values
            y = y / np.nanmax(np.abs(y), axis=0, keepdims=True)
            a.errorbar(tf, nanmean(y, 1), yerr=sem(y, 1), color=col, **_style(i),
                       label=f"contrast {c:g}: mean ± SEM over pairs")
        a.plot(tf, ds.emd_prediction.values, "k--", lw=1, zorder=4, label="prediction (discrete EMD × photoreceptor)")
        a.set_title(f"EMD probe pairs (n = {da.sizes['pair']})", fontsize=10)
        a.set_ylabel("response / each pair's maximum")
    if "lc" in ax:
        a = ax["lc"]
        da = ds[f"{var}_tuning"]
        if "neuron" in da.dims:
            da = _units_of(ds, da, "expansion")
        nd = da.dims[-1]
        top = 0.0
        for i, (c, col) in enumerate(zip(ds.contrast.values, cols)):
            y = da.sel(contrast=c).values
            m = nanmean(y, 1)
            top = max(top, float(np.nanmax(m)))
            a.errorbar(tf, m, yerr=sem(y, 1), color=col, **_style(i),
                       label=f"contrast {c:g}: mean ± SEM over units")
        a.plot(tf, ds.lc_drive_prediction.values * top, "k--", lw=1, zorder=4,
               label="predicted drive, scaled to the peak")
        a.set_title(f"LC expansion units (n = {da.sizes[nd]}, {ds.attrs.get('neuron_model', '')} model)",
                    fontsize=10)
        a.set_ylabel(f"steady-state {'firing rate' if var in ('lc_rate', 'lc_spikes') else var} "
                     f"({da.attrs.get('units', '')})")
    from matplotlib.ticker import LogLocator, ScalarFormatter
    for a in (ax[k] for k in ("emd", "lc") if k in ax):
        a.set_xscale("log")
        a.xaxis.set_major_locator(LogLocator(base=10, subs=(1, 2, 5)))
        a.xaxis.set_major_formatter(ScalarFormatter())
        a.xaxis.set_minor_formatter(plt.NullFormatter())
        a.set_xlabel("temporal frequency (Hz)")
        if opt:
            a.axvline(opt, color="0.5", ls=":", lw=1, label=f"1/(2πτ) = {opt:.2f} Hz")
        a.set_ylim(bottom=min(0.0, a.get_ylim()[0]))
        # Below the axes, clear of the data.
        a.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), frameon=False, ncol=1)

    if spikes:
        k = int(np.argmin(np.abs(tf - (opt or tf[len(tf) // 2]))))
        units = np.nonzero(ds.neuron_type.values == "expansion")[0]
        live = [int(ds.neuron.values[u]) for u in units if np.isfinite(ds.lc_spikes.sel(neuron=ds.neuron.values[u])).all()]
        n = live[0] if live else int(ds.neuron.values[0])
        c0 = ds.contrast.values[-1]
        dur = float(ds.time[-1] - ds.time[0])
        kind = _raster_psth(fig, ax["raster"], ax["psth"], ds, n, cols[-1], "time since grating onset (s)",
                            bin_s=max(0.02, round(dur / 30, 2)), temporal_frequency_hz=tf[k], contrast=c0)
        what = "raster" if kind == "raster" else "inter-spike intervals after onset"
        ax["raster"].set_title(f"unit {n} (expansion), {tf[k]:.2f} Hz, contrast {c0:g}: {what}", fontsize=10)
        ax["psth"].set_title("PSTH ± SEM across trials (grey: baseline)", fontsize=10)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)


# =========================================================================== rf-map

def _grid_image(az, el, v):
    """Scattered values on a regular (az, el) grid → 2-D image with NaN where no location, and edges."""
    ua, ue = np.unique(np.round(az, 6)), np.unique(np.round(el, 6))
    img = np.full((len(ue), len(ua)), np.nan)
    img[np.searchsorted(ue, np.round(el, 6)), np.searchsorted(ua, np.round(az, 6))] = v

    def edges(u):
        d = np.diff(u).min() if len(u) > 1 else 1.0
        return np.concatenate([u - d / 2, [u[-1] + d / 2]])

    return img, edges(ua), edges(ue)


def plot_rf_map(ds: xr.Dataset, path) -> list[Path]:
    """Per mapped field (up to 6): the local motion sensitivity map (colour bar labelled with its units),
    local preferred directions (arrows), designed RF (white dashed circle, FWHM or box) and mapped RF
    (red circle: centroid and deconvolved size)."""
    plt = _plt()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle

    probed = [int(f) for f in ds.field.values][:6]
    fig, ax = plt.subplots(1, len(probed), figsize=(max(4.6 * len(probed), 7.0), 4.6), squeeze=False,
                           layout="constrained")
    az, el = ds.location_azimuth_deg.values, ds.location_elevation_deg.values
    units = ds.rf_sensitivity.attrs.get("units", "")
    for a, f in zip(ax[0], probed):
        s = ds.rf_sensitivity.sel(field=f).values
        scale = 10.0 ** np.floor(np.log10(np.nanmax(np.abs(s)) + 1e-300))
        img, ea, ee = _grid_image(az, el, s / scale)
        lim = np.nanmax(np.abs(img))
        pc = a.pcolormesh(ea, ee, img, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="flat", edgecolors="none")
        pdir = np.radians(ds.rf_preferred_direction_deg.sel(field=f).values)
        mag = np.clip(s / (np.nanmax(s) + 1e-300), 0, None)
        strong = mag > 0.2
        a.quiver(az[strong], el[strong], (mag * np.cos(pdir))[strong], (mag * np.sin(pdir))[strong], color="k",
                 angles="xy", scale_units="xy", scale=1.0 / (1.2 * np.diff(ea).min()), width=0.007)
        a.add_patch(Circle((float(ds.field_azimuth_deg.sel(field=f)), float(ds.field_elevation_deg.sel(field=f))),
                           float(ds.field_size_deg.sel(field=f)) / 2, fill=False, color="0.1", ls="--", lw=1.4))
        a.add_patch(Circle((float(ds.rf_centre_azimuth_deg.sel(field=f)), float(ds.rf_centre_elevation_deg.sel(field=f))),
                           float(ds.rf_size_deg.sel(field=f)) / 2, fill=False, color="tab:red", lw=1.6))
        ext = float(json.loads(ds.attrs["parameters"])["extent_deg"])  # this field's own mapping grid
        fa, fe = float(ds.field_azimuth_deg.sel(field=f)), float(ds.field_elevation_deg.sel(field=f))
        a.set_xlim(max(ea[0], fa - ext), min(ea[-1], fa + ext))
        a.set_ylim(min(ee[-1], fe + ext), max(ee[0], fe - ext))  # elevation positive down
        a.set_aspect("equal")
        a.set_xlabel("azimuth (degree)")
        a.set_ylabel("elevation (degree, positive down)")
        a.set_title(f"LC field {f}: mapped size {float(ds.rf_size_deg.sel(field=f)):.1f}° "
                    f"(designed {float(ds.field_size_deg.sel(field=f)):.1f}°)", fontsize=9)
        cb = fig.colorbar(pc, ax=a, shrink=0.8)
        cb.set_label(f"local motion sensitivity (×{scale:.0e} {units})", fontsize=8)
        cb.formatter.set_useOffset(False)
    handles = [Line2D([], [], color="0.1", ls="--", label="designed RF (FWHM or box side)"),
               Line2D([], [], color="tab:red", label="mapped RF (centroid, deconvolved size)"),
               Line2D([], [], color="k", marker=r"$\rightarrow$", ls="", ms=10,
                      label="local preferred direction (length: sensitivity)")]
    fig.legend(handles=handles, loc="outside lower center", ncol=3 if len(probed) > 1 else 1, fontsize=8,
               frameon=False)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)


# =========================================================================== looming

def _looming_stimulus(ax_size, time_axes, ds: xr.Dataset, cols) -> None:
    """The disc's angular size per l/|v| (solid approach, dashed recede) on ``ax_size``; collision marked on
    every axis of ``time_axes``, whose abscissa is time relative to collision."""
    for lv, col in zip(ds.l_over_v_s.values, cols):
        for mot, ls in (("approach", "-"), ("recede", "--")):
            ax_size.plot(ds.time.values, ds.angular_size_deg.sel(l_over_v_s=lv, motion=mot), ls, color=col, lw=1.3)
    ax_size.set_ylabel("disc angular size (degree)")
    ax_size.set_title(f"stimulus (size cap {json.loads(ds.attrs['parameters'])['max_size_deg']:g}°)", fontsize=10)
    for a in time_axes:
        a.axvline(0.0, color="0.5", lw=0.8, ls=":")
        a.set_xlabel("time relative to collision (s)")


def _peak_time_fit(ax, lvs, t_peak, scale: float, color) -> bool:
    """The linear fit t_peak = α·l/|v| + δ over the finite peak times (s), drawn on ``ax`` in units of
    1/``scale`` s (1: s, 1e3: ms) with its equation as label; False where fewer than two are finite."""
    ok = np.isfinite(t_peak)
    if ok.sum() < 2:
        return False
    alpha, delta = np.polyfit(lvs[ok], t_peak[ok], 1)
    xx = np.linspace(0, lvs.max() * 1.05, 50)
    ax.plot(xx * scale, (alpha * xx + delta) * scale, "--", color=color, lw=1,
            label=f"fit: t_peak = {alpha:.2f}·l/|v| {'+' if delta >= 0 else '−'} {abs(delta) * 1e3:.0f} ms")
    return True


def _lgmd_overlay(ax, lvs, t_peak) -> dict:
    """The locust LGMD's peak time against l/|v| (:data:`experiments.ephys.published.LGMD_PEAK_TIME`) on ``ax``
    (s), beside the model's ``t_peak`` (s); returns :func:`~experiments.ephys.published.looming_agreement`."""
    from .published import LGMD_PEAK_TIME, lgmd_peak_time_s, looming_agreement

    xx = np.linspace(0, max(float(np.max(lvs)), max(LGMD_PEAK_TIME["values"]["l_over_v_s"])) * 1.05, 50)
    v = LGMD_PEAK_TIME["values"]
    ax.plot(xx, lgmd_peak_time_s(xx), color="tab:orange", lw=2, alpha=0.8,
            label=f"locust LGMD (Gabbiani et al. 1999, Fig. 5): θ_thres {v['theta_threshold_deg']:g}°, "
                  f"δ {v['delta_s'] * 1e3:g} ms")
    return looming_agreement(lvs, t_peak)


def edges_overlay(axes: dict, ds: xr.Dataset, path) -> dict:
    """The published T4/T5 selectivity (:data:`experiments.ephys.published.T4_T5_SELECTIVITY`) on the edges
    figure's polar panels ``axes`` ({"t4": ax, "t5": ax}): the published preferred polarity beside the model's
    agreement; writes the figure's JSON sidecar. Returns :func:`~experiments.ephys.published.edges_agreement`."""
    from .published import edges_agreement

    a = edges_agreement(ds)
    n = ds.sizes["preferred_direction"]
    for cell, ax in axes.items():
        pol = a[f"{cell}_published_polarity"].upper()
        k = int(round(a[f"{cell}_selective_fraction"] * n))
        # a caption under the panel: the source states the finding in words, so it is text, not a curve
        ax.set_xlabel(f"published (Maisak et al. 2013, in Haag et al. 2017's words):\n{cell.upper()} prefers {pol} "
                      f"edges, every layer direction selective\nmodel: polarity index {a[f'{cell}_polarity_index']:+.2f} (+1: {pol} only), "
                      f"DSI > 0 in {k}/{n} layers", fontsize=7.5, color="tab:orange", labelpad=14)
    _write_sidecar(path, {"published": "t4_t5_selectivity", "agreement": a})
    return a


def _write_sidecar(path, record: dict) -> Path:
    """A JSON file beside the figure ``path`` (same name, .json) with what the figure compares and how well."""
    from experiments.store import write_text

    return write_text(Path(path).with_suffix(".json"), json.dumps(record, indent=2, default=float) + "\n")


def looming_unit_traces(ds: xr.Dataset, var: str) -> tuple[xr.DataArray, str]:
    """The expansion units' trial-mean traces the looming figure averages, and their axis label.

    Only the units ``var``'s monitor recorded (a unit another monitor added to the shared
    ``neuron`` dim is NaN here and is left out, not counted as silent). Spike counts become a
    PSTH (Hz, 20 ms bins). Returns (l_over_v_s, motion, time[, neuron]) and the label."""
    da = ds[var]
    if "neuron" in da.dims:
        da = _units_of(ds, da, "expansion")
        recorded = da.notnull().any([d for d in da.dims if d != "neuron"]).values
        da = da.isel(neuron=np.flatnonzero(recorded))
    if var == "lc_spikes":
        # The units' own Dataset: assigning them back onto ``ds`` would realign them onto every
        # neuron, NaN-filled, and the PSTH's sums would count those as silent units.
        return psth(da.to_dataset(name=var), var, 0.02), "expansion units' PSTH (Hz, 20 ms bins)"
    da = da.mean("trial") if "trial" in da.dims else da
    return da, (f"expansion units' {da.attrs.get('long_name', var).replace('LC unit ', '')} "
                f"({da.attrs.get('units', '')})")


def plot_looming(ds: xr.Dataset, path) -> list[Path]:
    """Expansion units' response (mean ± SEM over units; PSTH with spikes) and the disc's angular size
    against time relative to collision, one colour per l/|v| (solid approach, dashed recede), and the
    peak time against l/|v| with its linear fit t_peak = α·l/|v| + δ."""
    plt = _plt()
    from matplotlib.lines import Line2D

    var = _neuron_var(ds)
    peak = f"{var}_time_of_peak_s" if var else None
    has_peak = bool(peak and peak in ds and "neuron" in ds[peak].dims)
    # Only the panels the recording has data for (the stimulus always): an empty panel is a blank band.
    names = (["units"] if var else []) + ["stimulus"] + (["peak"] if has_peak else [])
    fig, axes = plt.subplots(1, len(names), figsize=(5 * len(names), 4.4), squeeze=False, layout="constrained")
    ax = dict(zip(names, axes[0]))
    lvs = ds.l_over_v_s.values
    cols = _colours(len(lvs))
    if var:
        da, ylab = looming_unit_traces(ds, var)
        tt = da.time.values
        nd = "neuron" if "neuron" in da.dims else None
        for lv, col in zip(lvs, cols):
            for mot, ls in (("approach", "-"), ("recede", "--")):
                y = da.sel(l_over_v_s=lv, motion=mot).transpose("time", ...).values.reshape(len(tt), -1)
                m, e = nanmean(y, 1), sem(y, 1)
                ax["units"].plot(tt, m, ls, color=col, lw=1.3)
                if nd and np.isfinite(e).any():
                    ax["units"].fill_between(tt, m - e, m + e, color=col, alpha=0.2, lw=0)
        n_units = da.sizes.get("neuron", 1)
        onset = -float(ds.attrs.get("t_collision_s", -float(ds.time[0])))
        if float(ds.time[0]) < onset:  # the bare background before the disc appears
            ax["units"].axvspan(float(ds.time[0]), onset, color="0.9", lw=0, zorder=0)
            ax["units"].axvline(onset, color="0.4", lw=0.8, ls=":")
            ax["units"].text(onset, 1.0, " disc appears", transform=ax["units"].get_xaxis_transform(),
                             fontsize=7, va="top", color="0.3")
        ax["units"].set_ylabel(ylab)
        ax["units"].set_title(f"LC expansion units (n = {n_units}; mean ± SEM over units)", fontsize=10)
    _looming_stimulus(ax["stimulus"], [ax[k] for k in ("units", "stimulus") if k in ax], ds, cols)
    if has_peak:
        a = ax["peak"]
        p = _units_of(ds, ds[peak], "expansion").sel(motion="approach")
        y = p.transpose("l_over_v_s", ...).values.reshape(len(lvs), -1)
        m, e = nanmean(y, 1), sem(y, 1)
        for lv, mm, ee, col in zip(lvs, m, e, cols):
            a.errorbar([lv], [mm], yerr=[ee] if np.isfinite(ee) else None, color=col, marker="o", capsize=3)
        _peak_time_fit(a, lvs, m, 1.0, color="k")
        agreement = _lgmd_overlay(a, lvs, m)
        a.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), frameon=False)
        a.set_xlabel("l/|v| (s)")
        a.set_ylabel("time of peak relative to collision (s)")
        a.set_title("approach: peak time (model: mean ± SEM over units)\n"
                    f"slope / LGMD's = {agreement['slope_ratio']:.2f}", fontsize=10)
        _write_sidecar(path, {"published": "lgmd_peak_time", "agreement": agreement})
    handles = [Line2D([], [], color=c, lw=2, label=f"l/|v| = {lv * 1e3:g} ms") for lv, c in zip(lvs, cols)]
    handles += [Line2D([], [], color="k", ls="-", label="approach"), Line2D([], [], color="k", ls="--", label="recede")]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8, frameon=False)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)


def plot_eye_tf_tuning(ds: xr.Dataset, path) -> list[Path]:
    """tf-tuning on the compound eye: EMD probe pairs and LC matched-filter input (normalised, beside the
    prediction and 1/(2πτ)), and the pooled expansion rate ρ (absolute: proportional to temporal frequency,
    the same at every contrast). Mean ± SEM over recorded pairs/fields, one colour per contrast."""
    plt = _plt()
    panels = [(v, t) for v, t in (("emd_response_tuning", "EMD probe pairs"),
                                  ("lc_input_tuning", "LC matched-filter input"),
                                  ("lc_r_tuning", "LC expansion rate ρ (pooled)")) if v in ds]
    fig, ax = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.0), squeeze=False, layout="constrained")
    tf = ds.temporal_frequency_hz.values
    opt = float(ds.attrs["optimum_hz"])
    for a, (v, title) in zip(ax[0], panels):
        for i, c in enumerate(ds.contrast.values):
            x = ds[v].sel(contrast=c).values                              # (TF, X)
            norm = v != "lc_r_tuning"
            if norm:
                x = x / np.nanmax(np.abs(x), axis=0, keepdims=True)
            a.errorbar(tf, nanmean(x, 1), yerr=sem(x, 1), **_style(i),
                       label=f"contrast {c:g}: mean ± SEM over {x.shape[1]}")
        if v != "lc_r_tuning" and "emd_prediction" in ds:
            a.plot(tf, ds.emd_prediction.values, "k--", lw=1, zorder=4, label="prediction (discrete EMD × photoreceptor)")
        a.axvline(opt, color="0.4", ls=":", lw=1, label=f"1/(2πτ) = {opt:.2f} Hz")
        a.set_xscale("log")
        a.set_xlabel("temporal frequency (Hz)")
        a.set_ylabel("response / its maximum" if v != "lc_r_tuning" else f"ρ ({ds[v].attrs.get('units', '')})")
        a.set_title(title, fontsize=10)
        a.legend(fontsize=7, frameon=False)
    fig.suptitle(f"Compound eye (Δφ = {ds.attrs.get('dphi_deg', '?')}°): expanding rings, the velocity circuit's "
                 f"own units", fontsize=10)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)


def plot_eye_looming(ds: xr.Dataset, path) -> list[Path]:
    """looming on the compound eye: the LC fields the disc reaches — their expansion rate ρ and matched-filter
    input, mean ± SEM over those fields, one colour per l/|v| (solid approach, dashed recede) — the disc's
    angular size, and the approach's peak time (median over those fields) against l/|v| with its linear fit."""
    plt = _plt()
    lvs = ds.l_over_v_s.values
    cols = _colours(len(lvs))
    t = ds.time.values
    sees = ds.field_sees_disc.values if "field_sees_disc" in ds.coords else np.ones(ds.sizes.get("field", 0), bool)
    panels = [(v, title) for v, title in (("lc_r", "LC expansion rate ρ"), ("lc_input", "LC matched-filter input"))
              if v in ds]
    peaks = [(k, v, title) for k, (v, title) in enumerate(panels) if f"{v}_time_of_peak_s" in ds]
    # Only the panels the recording has data for (the stimulus always): an empty panel is a blank band.
    n = len(panels) + 1 + bool(peaks)
    fig, axes = plt.subplots(1, n, figsize=(4.8 * n, 4.4), squeeze=False, layout="constrained")
    ax = list(axes[0])
    a_size, a_peak = ax[len(panels)], (ax[-1] if peaks else None)
    for a, (v, title) in zip(ax, panels):
        for lv, col in zip(lvs, cols):
            for mot, ls in (("approach", "-"), ("recede", "--")):
                y = ds[v].sel(l_over_v_s=lv, motion=mot).values[:, sees]
                m, e = nanmean(y, 1), sem(y, 1)
                a.plot(t, m, ls, color=col, lw=1.3, label=f"l/|v| = {lv * 1e3:g} ms" if mot == "approach" else None)
                a.fill_between(t, m - e, m + e, color=col, alpha=0.2, lw=0)
        a.set_ylabel(f"{title} ({ds[v].attrs.get('units', '')})")
        a.set_title(f"{title}, {int(sees.sum())} fields the disc reaches\n(mean ± SEM over fields)", fontsize=10)
    if panels:
        ax[0].legend(fontsize=8, frameon=False, loc="upper left", title="solid approach, dashed recede",
                     title_fontsize=8)
    _looming_stimulus(a_size, ax[:len(panels) + 1], ds, cols)
    for k, v, title in peaks:
        y = ds[f"{v}_time_of_peak_s"].sel(motion="approach").transpose("l_over_v_s", "field").values[:, sees]
        m = np.nanmedian(y, 1)
        a_peak.plot(lvs * 1e3, m * 1e3, "o", color=f"C{k}", label=f"{title} (median over fields)")
        _peak_time_fit(a_peak, lvs, m, 1e3, color=f"C{k}")
    if a_peak is not None:
        a_peak.set_xlabel("l/|v| (ms)")
        a_peak.set_ylabel("approach: time of peak relative to collision (ms)")
        a_peak.set_title("peak time against l/|v|", fontsize=10)
        a_peak.legend(fontsize=7, frameon=False, loc="lower left")
    fig.suptitle(f"Compound eye (Δφ = {ds.attrs.get('dphi_deg', '?')}°): a dark disc approaching or receding "
                 "straight ahead, recorded on the velocity circuit's own LC fields", fontsize=10)
    return save_png_and_pdf(fig, path, provenance=ds.attrs)


def plot_recording(ds: xr.Dataset, path) -> list[Path]:
    """The protocol's figure (from ds.attrs["protocol"]); PNG and PDF."""
    p = ds.attrs.get("protocol")
    if ds.attrs.get("eye") == "fly":
        if p == "tf-tuning":
            return plot_eye_tf_tuning(ds, path)
        if p == "looming":
            return plot_eye_looming(ds, path)
        if p not in ("rf-map", "velocity-replay"):
            raise ValueError(f"no figure for {p} on the compound eye (--eye fly) yet; drop --plot")
    if p == "velocity-replay":
        from .replay_figures import plot_velocity_replay
        return plot_velocity_replay(ds, path)
    if p == "edges":
        from .edges import plot_edges
        return plot_edges(ds, path)
    if p in ("contrast", "flicker"):
        from .contrast import plot_contrast
        from .flicker import plot_flicker
        return (plot_contrast if p == "contrast" else plot_flicker)(ds, path)
    if p == "adaptation":
        from .adaptation import plot_adaptation
        return plot_adaptation(ds, path)
    if p == "current-injection":
        from .injection import plot_current_injection
        return plot_current_injection(ds, path)
    if p == "white-noise":
        from .white_noise import plot_white_noise
        return plot_white_noise(ds, path)
    fn = {"tf-tuning": plot_tf_tuning, "rf-map": plot_rf_map, "looming": plot_looming}.get(p)
    if fn is None:
        raise ValueError(f"no figure for protocol {p!r}")
    return fn(ds, path)
