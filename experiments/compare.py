"""Front ends side by side: every front end on the same footage and the same readout (`lobula compare`).

``compare_front_ends(footage, front_ends)`` runs :func:`lobula.velocity.estimate_velocity`
once per front end with one base :class:`~lobula.config.VelocityConfig` (only ``front_end``
differs, so fields, readout, filter and acceleration are shared) and scores each run:

* **r̄_f error** against exact truth, on synthetic footage only (a folder with ``depth/``
  maps and ``truth.csv``): the exact pooled rate of every field at every frame with a depth
  map (:func:`experiments.calibrate.exact_field_rates`, about the scene's epipole from
  ``scene.json``), against the front end's r̄_f interpolated to that frame's time. Reported
  as an RMSE (1/s) and relative to the RMS of the exact rates.
* **velocity RMSE and median |error|** over observable frames after ``skip_s``
  (:func:`experiments.velocity.score`), and the **observable fraction**.
* **lock-on time**: the first time t (s after the footage's first frame) such that every
  estimate in [t, t + ``hold_s``] is observable and within ``tol_m_s`` of the truth
  (defaults 0.1 m/s for 1 s); never negative: an estimate stamped before the first frame
  (the EMD's latency-corrected stamps) that starts such a window counts as 0; NaN when that
  never happens (e.g. footage shorter than ``hold_s``).
* **ms/frame of each stage** from the run's ``timings_s`` (read, flow, fields, readout for
  dense flow; read, sampling, photoreceptor, emd, fields, readout for the EMD), divided by
  the number of estimates the front end produced (flow pairs, or frames for the EMD), and
  end to end from its ``wall_s``. Counts in ``timings_s`` (``n_saccades``, ``n_ommatidia``) are
  not stages. Each stage is timed on its own; with untimed work and the flow front ends'
  parallel threads (decode, flow, fields), the stages need not add up to the end-to-end time.

The result is one ``xarray.Dataset``: dim ``front_end`` for the scalar metrics, ``(front_end,
time)`` for ``v_hat``, ``observable``, ``v_std``, ``r_median`` and ``(front_end, time, field)``
for ``r``, all on the footage's frame times (each front end's own time stamps — flow-pair
middles, or EMD outputs shifted by its latency — are interpolated linearly onto them; the
metrics are computed on the native stamps before that), ``stage_ms_per_frame`` over
``(front_end, stage)``, ``v_true`` and ``accel`` over ``time``, and ``r_exact`` over
``(depth_time, field)`` on synthetic footage. Front ends that cannot run (``flo`` without
``.flo`` files) are left out with a note in ``attrs['notes']``.
"""
from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import io
import json
import math
import sys
from pathlib import Path

import numpy as np
import xarray as xr

from lobula.config import VelocityConfig
from lobula.front_ends import FRONT_ENDS
from lobula.readers import open_footage
from lobula.readers.core import Footage, FootageError
from lobula.readers.flo import FloUnits
from lobula.readout import answered_velocity

from .store import provenance, save_figure, write_netcdf, write_text

#: every front end of lobula.front_ends.FRONT_ENDS, the EMD array first
DEFAULT_FRONT_ENDS = ("emd", "dis", "farneback", "flo")
LOCK_TOL_M_S = 0.1
LOCK_HOLD_S = 1.0
STAGE_ORDER = ("read", "flow", "sampling", "photoreceptor", "emd", "fields", "readout")
METRICS = ("rmse_m_s", "median_abs_error_m_s", "lock_on_s", "observable_fraction", "r_rmse_1_s",
           "r_rel_error", "ms_per_frame", "n_frames", "n_estimates", "wall_s")
METRIC_ATTRS = {
    "rmse_m_s": dict(units="m/s", long_name="velocity RMSE over observable frames after skip_s"),
    "median_abs_error_m_s": dict(units="m/s", long_name="median |v_hat - v_true| over observable frames after skip_s"),
    "lock_on_s": dict(units="s", long_name="lock-on time: first t after which |error| < tol_m_s for hold_s "
                                             "(s after the first frame; NaN = never)"),
    "observable_fraction": dict(units="1", long_name="fraction of estimates after skip_s that are observable"),
    "r_rmse_1_s": dict(units="1/s", long_name="RMSE of r_bar_f against exact pooled rates (synthetic footage)"),
    "r_rel_error": dict(units="1", long_name="r_rmse_1_s / RMS of the exact pooled rates"),
    "ms_per_frame": dict(units="ms", long_name="end-to-end wall time per estimate"),
    "n_frames": dict(units="1", long_name="estimates scored (after skip_s)"),
    "n_estimates": dict(units="1", long_name="estimates produced by the front end"),
    "wall_s": dict(units="s", long_name="wall time of the whole run"),
}


# ---------------------------------------------------------------------- metrics
def default_skip(footage: Footage, skip_s: float | None = None) -> float:
    """Seconds ignored at the start when scoring: ``skip_s`` if given, else 2 s capped at a quarter
    of the footage (the 1.2 s D435i sample keeps 0.9 s)."""
    if skip_s is not None:
        return float(skip_s)
    duration = float(footage.times[-1] - footage.times[0]) if len(footage) > 1 else 0.0
    return min(2.0, 0.25 * duration)


def lock_on_time(t, v_hat, v_true, tol_m_s: float = LOCK_TOL_M_S, hold_s: float = LOCK_HOLD_S,
                 t_origin: float | None = None) -> float:
    """First time (s after ``t_origin``, default ``t[0]``) from which |v̂ − v| < tol for ``hold_s``.

    A window [t_i, t_i + hold_s] counts when every estimate in it is finite and within
    ``tol_m_s`` and the estimates actually span ``hold_s`` (to half a sample interval).
    Returns t_i − t_origin for the first such window, at least 0 (a window starting at an
    estimate stamped before ``t_origin`` locks on at the origin), or NaN when none exists.
    """
    t = np.asarray(t, dtype=float)
    if t.size < 2:
        return float("nan")
    err = np.abs(np.asarray(v_hat, float) - np.asarray(v_true, float))
    good = np.isfinite(err) & (err < tol_m_s)
    dt = float(np.median(np.diff(t)))
    origin = float(t[0] if t_origin is None else t_origin)
    # bad_before[k] = number of bad samples among the first k.
    bad_before = np.concatenate([[0], np.cumsum(~good)])
    ends = np.searchsorted(t, t + hold_s + 1e-9, side="right")  # window i covers samples i..ends[i]-1
    for i in np.flatnonzero(good):
        j = ends[i]
        if t[j - 1] - t[i] < hold_s - 0.5 * dt:
            continue  # the estimates do not span hold_s from here (end of footage, or a gap)
        if bad_before[j] - bad_before[i] == 0:
            return max(float(t[i] - origin), 0.0)
    return float("nan")


def scene_epipole(footage: Footage) -> tuple[float, float]:
    """The synthetic scene's epipole (normalised) from ``scene.json``, else the principal point."""
    p = Path(footage.path) / "scene.json"
    try:
        e = json.loads(p.read_text()).get("epipole", (0.0, 0.0))
        return float(e[0]), float(e[1])
    except (OSError, ValueError, TypeError, IndexError):
        return 0.0, 0.0


def exact_rates(footage: Footage, config: VelocityConfig):
    """(frame indices, exact r̄ (k, F)) when the footage has depth maps and truth, else None."""
    if footage.truth is None or not (Path(footage.path) / "depth").is_dir():
        return None
    from .calibrate import exact_field_rates
    try:
        return exact_field_rates(footage, config, epipole=scene_epipole(footage))
    except FootageError:
        return None


def field_rate_error(ds: xr.Dataset, footage: Footage, exact, skip_s: float) -> dict:
    """RMSE (1/s) and relative error of the run's r̄_f against exact pooled rates at depth frames."""
    out = dict(r_rmse_1_s=float("nan"), r_rel_error=float("nan"))
    if exact is None:
        return out
    idx, r_x = exact
    t_frames = footage.times[idx]
    t = ds.time.values
    keep = (t_frames >= footage.times[0] + skip_s) & (t_frames >= t[0]) & (t_frames <= t[-1])
    if not keep.any():
        return out
    r = ds.r.values
    r_at = np.stack([np.interp(t_frames[keep], t, r[:, f]) for f in range(r.shape[1])], axis=1)
    diff = r_at - r_x[keep]
    ok = np.isfinite(diff)
    if not ok.any():
        return out
    rmse = float(np.sqrt(np.mean(diff[ok] ** 2)))
    scale = float(np.sqrt(np.mean(r_x[keep][ok] ** 2)))
    out.update(r_rmse_1_s=rmse, r_rel_error=rmse / scale if scale > 0 else float("nan"))
    return out


def stage_ms_per_frame(ds: xr.Dataset) -> dict:
    """Milliseconds per estimate of each timed stage (from ``attrs['timings_s']``), in pipeline order.

    Entries named ``n_*`` in ``timings_s`` are counts (``n_saccades``, ``n_ommatidia``), not seconds:
    they are left out.
    """
    n = max(int(ds.sizes["time"]), 1)
    try:
        timings = json.loads(ds.attrs.get("timings_s", "{}"))
    except ValueError:
        timings = {}
    stages = {k: float(v) for k, v in timings.items() if not k.startswith("n_") and isinstance(v, (int, float))}
    ordered = [k for k in STAGE_ORDER if k in stages] + sorted(k for k in stages if k not in STAGE_ORDER)
    return {k: 1000.0 * stages[k] / n for k in ordered}


def front_end_metrics(ds: xr.Dataset, footage: Footage, skip_s: float, exact=None,
                      tol_m_s: float = LOCK_TOL_M_S, hold_s: float = LOCK_HOLD_S) -> dict:
    """Every scalar metric of one velocity run (see the module docstring); NaN where undefined."""
    from .velocity import score

    sc = score(ds, skip_s) or {}
    m = {k: float("nan") for k in METRICS}
    m.update(rmse_m_s=sc.get("rmse_m_s", float("nan")),
             median_abs_error_m_s=sc.get("median_abs_error_m_s", float("nan")),
             observable_fraction=sc.get("observable_fraction", float("nan")),
             n_frames=float(sc.get("n_frames", 0)), n_estimates=float(ds.sizes["time"]))
    if "v_true" in ds:
        v = answered_velocity(ds)
        m["lock_on_s"] = lock_on_time(ds.time.values, v, ds.v_true.values, tol_m_s, hold_s,
                                      t_origin=float(footage.times[0]))
    m.update(field_rate_error(ds, footage, exact, skip_s))
    wall = float(ds.attrs.get("wall_s", float("nan")))
    m["wall_s"] = wall
    m["ms_per_frame"] = 1000.0 * wall / max(int(ds.sizes["time"]), 1)
    return m


def _median_r(r: np.ndarray) -> np.ndarray:
    """Median over fields per time, NaN where no field is finite (without warnings)."""
    r = np.where(np.isfinite(r), r, np.nan)
    out = np.full(r.shape[0], np.nan)
    ok = np.isfinite(r).any(1)
    out[ok] = np.nanmedian(r[ok], axis=1)
    return out


def _on_grid(t_native, x, t_grid, fill=np.nan):
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        return np.interp(t_grid, t_native, x, left=fill, right=fill)
    return np.stack([np.interp(t_grid, t_native, x[:, j], left=fill, right=fill) for j in range(x.shape[1])], 1)


# ---------------------------------------------------------------------- the comparison
def _front_end_list(front_ends) -> list[str]:
    """The requested front ends (a comma-separated string or a sequence), checked: known, each once."""
    front_ends = [f.strip() for f in (front_ends.split(",") if isinstance(front_ends, str) else front_ends) if f.strip()]
    unknown = [f for f in front_ends if f not in FRONT_ENDS]
    if unknown or not front_ends:
        raise ValueError(f"unknown front end(s) {unknown or front_ends}; choose from {', '.join(FRONT_ENDS)}")
    if len(set(front_ends)) != len(front_ends):
        raise ValueError(f"front end listed twice: {front_ends}")
    return front_ends


def _run_front_ends(footage: Footage, base: VelocityConfig, front_ends: list[str], flo_files, flo_units, progress,
                    say, notes: list[str]) -> tuple[dict, dict]:
    """Velocity from each front end; a front end that cannot run is noted in ``notes`` and left out.
    Returns ({front end: velocity Dataset}, {front end: its configuration as JSON})."""
    from lobula.velocity import estimate_velocity

    runs, configs = {}, {}
    for fe in front_ends:
        if fe == "flo" and not flo_files:
            notes.append("flo skipped: no .flo files given (--flo FILE_OR_DIR)")
            say(notes[-1])
            continue
        cfg = base.for_front_end(fe)
        say(f"{fe}: estimating velocity on {len(footage)} frames")
        try:
            ds = estimate_velocity(footage, cfg, progress=progress,
                                   flo_files=flo_files if fe == "flo" else None, flo_units=flo_units)
        except FootageError as exc:
            notes.append(f"{fe} failed: {exc}")
            say(notes[-1])
            continue
        runs[fe] = ds
        configs[fe] = cfg.to_json()
    if not runs:
        raise FootageError(f"{footage.path}: no front end could run ({'; '.join(notes) or 'none requested'})")
    return runs, configs


def _stacked(runs: dict, names: list[str], t_grid: np.ndarray, stages_by_fe: dict, stage_names: list[str]) -> dict:
    """The per-front-end variables on the frame times ``t_grid`` (s), stacked along ``front_end``."""
    def stack(fn):
        return np.stack([fn(runs[fe]) for fe in names])

    data = {
        "v_hat": (("front_end", "time"), stack(lambda d: _on_grid(d.time.values, d.v_hat.values, t_grid)),
                  {"units": "m/s", "long_name": "estimated forward velocity (on frame times; beyond the observable "
                                                "frames carried by the accelerometer)"}),
        "observable": (("front_end", "time"),
                       stack(lambda d: _on_grid(d.time.values, d.observable.values.astype(float), t_grid, 0.0)) >= 0.5,
                       {"units": "1", "long_name": "velocity observable (nearest estimate)"}),
        "v_std": (("front_end", "time"), stack(lambda d: _on_grid(d.time.values, d.v_std.values, t_grid)),
                  {"units": "m/s", "long_name": "std of v_hat (on frame times)"}),
        "r_median": (("front_end", "time"), stack(lambda d: _on_grid(d.time.values, _median_r(d.r.values), t_grid)),
                     {"units": "1/s", "long_name": "median over fields of r_bar_f"}),
        "r": (("front_end", "time", "field"), stack(lambda d: _on_grid(d.time.values, d.r.values, t_grid)).astype(np.float32),
              {"units": "1/s", "long_name": "pooled expansion rate v/d"}),
        "stage_ms_per_frame": (("front_end", "stage"),
                               np.array([[stages_by_fe[fe].get(s, np.nan) for s in stage_names] for fe in names]),
                               {"units": "ms", "long_name": "wall time per estimate of each stage"}),
    }
    return data


def compare_front_ends(footage: Footage | str | Path, front_ends=DEFAULT_FRONT_ENDS,
                       config: VelocityConfig | None = None, flo_files: list[Path] | None = None,
                       flo_units: FloUnits | None = None, skip_s: float | None = None,
                       tol_m_s: float = LOCK_TOL_M_S, hold_s: float = LOCK_HOLD_S,
                       progress: bool = True, log=None) -> xr.Dataset:
    """Run each front end on ``footage`` with the same readout; returns the comparison Dataset.

    config: the shared configuration (default :class:`VelocityConfig`); only ``front_end`` is
    changed per run. flo_files/flo_units: precomputed flow for ``"flo"`` (skipped with a note
    when absent). skip_s: seconds ignored when scoring (default :func:`default_skip`).
    log: a callable receiving progress lines (default: none).
    """
    from lobula.velocity.inertial import forward_accel_at

    if not isinstance(footage, Footage):
        footage = open_footage(footage)
    base = copy.deepcopy(config) if config is not None else VelocityConfig()
    front_ends = _front_end_list(front_ends)
    skip = default_skip(footage, skip_s)
    say = log or (lambda s: None)
    exact = exact_rates(footage, base)
    notes = list(footage.notes)
    runs, configs = _run_front_ends(footage, base, front_ends, flo_files, flo_units, progress, say, notes)

    names = list(runs)
    t_grid = np.asarray(footage.times, dtype=float)
    metrics = {fe: front_end_metrics(ds, footage, skip, exact, tol_m_s, hold_s) for fe, ds in runs.items()}
    stages_by_fe = {fe: stage_ms_per_frame(ds) for fe, ds in runs.items()}
    stage_names = [s for s in STAGE_ORDER if any(s in st for st in stages_by_fe.values())]
    stage_names += sorted({s for st in stages_by_fe.values() for s in st} - set(stage_names))

    first = runs[names[0]]
    data = _stacked(runs, names, t_grid, stages_by_fe, stage_names)
    for k in METRICS:
        data[k] = ("front_end", np.array([metrics[fe][k] for fe in names], dtype=float), METRIC_ATTRS[k])
    try:
        a, _src = forward_accel_at(footage, t_grid, base)
        data["accel"] = ("time", a, {"units": "m/s2", "long_name": "forward acceleration",
                                     "source": first.accel.attrs.get("source", "")})
    except FootageError:
        pass
    if footage.truth is not None:
        data["v_true"] = ("time", np.interp(t_grid, footage.truth["time_s"], footage.truth["v_forward_m_s"]),
                          {"units": "m/s", "long_name": "ground-truth forward velocity"})
    coords = dict(front_end=("front_end", np.array(names, dtype=object), {"long_name": "velocity front end"}),
                  time=("time", t_grid, {"units": "s", "long_name": "frame time on the footage clock"}),
                  stage=("stage", np.array(stage_names, dtype=object), {"long_name": "pipeline stage"}),
                  azimuth_deg=("field", first.azimuth_deg.values,
                               {"units": "degree", "long_name": "LC field centre azimuth"}),
                  elevation_deg=("field", first.elevation_deg.values,
                                 {"units": "degree", "long_name": "LC field centre elevation (positive down)"}),
                  size_deg=("field", first.size_deg.values,
                            {"units": "degree", "long_name": "LC field size (Gaussian FWHM, or box side)"}))
    if exact is not None:
        idx, r_x = exact
        data["r_exact"] = (("depth_time", "field"), r_x, {"units": "1/s", "long_name": "exact pooled rate from depth maps"})
        coords["depth_time"] = ("depth_time", t_grid[idx], {"units": "s", "long_name": "time of a frame with exact depth"})
    out = xr.Dataset(data, coords=coords)
    out.attrs.update(provenance(
        base.to_json(), footage=str(footage.path), footage_kind=footage.kind,
        front_end_configs=json.dumps(configs), readout=base.readout.method, filter=base.readout.filter,
        acceleration_source=first.attrs.get("acceleration_source", ""), skip_s=skip,
        lock_on=f"first t after which |v_hat - v_true| < {tol_m_s:g} m/s for {hold_s:g} s (observable only)",
        lock_tol_m_s=tol_m_s, lock_hold_s=hold_s,
        time_grid="frame times; each front end's estimates interpolated linearly from its own stamps",
        timings_s=json.dumps({fe: json.loads(ds.attrs.get("timings_s", "{}")) for fe, ds in runs.items()}),
        notes="; ".join(notes) or "none"))
    return out


# ---------------------------------------------------------------------- outputs
def comparison_rows(ds: xr.Dataset) -> list[dict]:
    """One dict per front end: its metrics and per-stage ms/frame (``ms_<stage>``)."""
    rows = []
    for i, fe in enumerate(ds.front_end.values):
        row = {"front_end": str(fe)}
        for k in METRICS:
            if k in ds:
                v = float(ds[k].values[i])
                row[k] = int(v) if k.startswith("n_") and math.isfinite(v) else v
        for j, s in enumerate(ds.stage.values):
            row[f"ms_{s}"] = float(ds.stage_ms_per_frame.values[i, j])
        rows.append(row)
    return rows


def _fmt(v, digits=3):
    if isinstance(v, str):
        return v
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


#: The table's columns: (metric, header with its unit, decimals).
TABLE_COLUMNS = (("front_end", "front end", 0), ("rmse_m_s", "RMSE m/s", 4),
                 ("median_abs_error_m_s", "median|e| m/s", 4), ("lock_on_s", "lock-on s", 2),
                 ("observable_fraction", "observable fraction", 3), ("r_rel_error", "r̄ rel.err", 3),
                 ("ms_per_frame", "end-to-end ms", 1))
TIME_NOTE = ("ms: wall time per estimate. Each stage is timed on its own; with untimed work (set-up, hand-offs) "
             "and the flow front ends' parallel threads, the stages need not add up to end-to-end.")


def format_table(ds: xr.Dataset) -> str:
    """A plain-text table of the comparison (one row per front end), and a line saying what its times are."""
    rows = comparison_rows(ds)
    cols = TABLE_COLUMNS
    stages = [f"ms_{s}" for s in ds.stage.values]
    header = [c[1] for c in cols] + [s[3:] + " ms" for s in stages]
    body = [[_fmt(r.get(k), d) for k, _, d in cols] + [_fmt(r.get(s), 1) for s in stages] for r in rows]
    widths = [max(len(h), *(len(b[i]) for b in body)) for i, h in enumerate(header)]
    lines = ["  ".join(h.rjust(w) if i else h.ljust(w) for i, (h, w) in enumerate(zip(header, widths)))]
    lines += ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(b, widths))) for b in body]
    return "\n".join(lines + [TIME_NOTE])


def write_csv(ds: xr.Dataset, path: str | Path) -> Path:
    """The comparison table as CSV (one row per front end), written atomically."""
    rows = comparison_rows(ds)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()})
    return write_text(path, buf.getvalue())


COLOURS = {"emd": "tab:green", "dis": "tab:purple", "farneback": "tab:orange", "flo": "tab:blue"}


def time_bars(ds: xr.Dataset) -> dict[str, np.ndarray]:
    """The time panel's bars, (n_front_end,) ms each: ``"end to end"`` (the table's end-to-end column,
    ``ms_per_frame``) and every stage (its ``<stage> ms`` column); NaN where a front end has no such stage."""
    rows = comparison_rows(ds)
    bars = {"end to end": np.array([r["ms_per_frame"] for r in rows], float)}
    for s in ds.stage.values:
        bars[str(s)] = np.array([r[f"ms_{s}"] for r in rows], float)
    return bars


def comparison_figure(ds: xr.Dataset, title: str | None = None):
    """The comparison figure; returns the matplotlib Figure (see :func:`plot_comparison`)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [str(f) for f in ds.front_end.values]
    cols = [COLOURS.get(f, f"C{i}") for i, f in enumerate(names)]
    t = ds.time.values - ds.time.values[0]
    fig = plt.figure(figsize=(11, 9.5), layout="constrained")
    gs = fig.add_gridspec(3, 2, height_ratios=[1.5, 1, 1])
    ax = fig.add_subplot(gs[0, :])
    for i, fe in enumerate(names):
        obs = ds.observable.values[i].astype(bool) if "observable" in ds else np.ones(len(t), bool)
        ax.plot(t, np.where(obs, ds.v_hat.values[i], np.nan), color=cols[i], lw=1.6,
                label=f"{fe}: RMSE {_fmt(float(ds.rmse_m_s.values[i]), 4)} m/s")
        # Where the accelerometer carries v̂ (not observable): dotted, as `lobula velocity` draws it.
        carried = np.where(obs, np.nan, ds.v_hat.values[i])
        ax.plot(t, carried, color=cols[i], lw=1.0, ls=":",
                label=f"{fe}: v̂ carried by the accelerometer (not observable)" if np.isfinite(carried).any() else None)
    if "v_true" in ds:
        # Over the estimates, thin and dashed, so it stays visible where they agree with it.
        ax.plot(t, ds.v_true, "k--", lw=1.2, label="truth", zorder=4)
    skip = float(ds.attrs.get("skip_s", 0.0))
    if skip > 0:
        ax.axvspan(0, skip, color="0.92", lw=0, label=f"not scored (first {skip:.3g} s)")
    ax.axhline(0, color="0.4", lw=0.8, zorder=1)
    ax.set_xlabel("time since the first frame (s)")
    ax.set_ylabel("forward velocity (m/s)\nbelow 0: moving backwards")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.set_title(title or f"front ends on {Path(ds.attrs.get('footage', '')).name} "
                          f"({ds.attrs.get('readout')} readout, {ds.attrs.get('filter')} filter)")
    x = np.arange(len(names))
    b1 = fig.add_subplot(gs[1, 0])
    b1.bar(x - 0.2, np.nan_to_num(ds.rmse_m_s.values), 0.4, color=cols)
    b1.bar(x + 0.2, np.nan_to_num(ds.median_abs_error_m_s.values), 0.4, color=cols, alpha=0.45)
    for i, v in enumerate(ds.rmse_m_s.values):
        if not np.isfinite(v):
            b1.text(x[i], 0, "n/a", ha="center", va="bottom", fontsize=8)
    b1.set_xticks(x, names)
    b1.set_ylabel("velocity error (m/s)")
    b1.set_title("RMSE (solid), median |error| (pale)", fontsize=9)
    b2 = fig.add_subplot(gs[1, 1])
    lock = ds.lock_on_s.values
    b2.bar(x, np.nan_to_num(lock), 0.6, color=cols)
    for i, v in enumerate(lock):
        b2.text(x[i], np.nan_to_num(v), f"{v:.2f} s" if np.isfinite(v) else "never", ha="center", va="bottom",
                fontsize=8)
    finite = lock[np.isfinite(lock)]
    b2.set_ylim(0, 1.2 * max(float(finite.max()) if finite.size else 0.0, 1.0))
    b2.set_xticks(x, names)
    b2.set_ylabel("lock-on time (s)")
    b2.set_title(f"lock-on: time from the first frame until |error| < {ds.attrs.get('lock_tol_m_s', LOCK_TOL_M_S):g} "
                 f"m/s holds for {ds.attrs.get('lock_hold_s', LOCK_HOLD_S):g} s", fontsize=9)
    b3 = fig.add_subplot(gs[2, :])
    bars = time_bars(ds)
    stage_cols = plt.get_cmap("Set2")
    width = 0.85 / len(bars)
    for j, (label, h) in enumerate(bars.items()):
        xs = x - 0.425 + (j + 0.5) * width
        colour = "0.25" if label == "end to end" else stage_cols(j % 8)
        ok = np.isfinite(h)  # a stage the front end does not have: no bar
        b3.bar(xs[ok], h[ok], width, color=colour, edgecolor="0.3", lw=0.5, label=label)
        if label == "end to end":
            for xi, v in zip(xs, h):
                if np.isfinite(v):
                    b3.text(xi, v, f"{v:.1f}", ha="center", va="bottom", fontsize=7)
    top = max((float(np.nanmax(h)) for h in bars.values() if np.isfinite(h).any()), default=1.0)
    b3.set_ylim(0, 1.12 * top)
    b3.set_xticks(x, names)
    b3.set_ylabel("ms per estimate")
    b3.set_title("wall time per estimate, end to end and each stage timed on its own (the table's ms columns); "
                 "untimed work and parallel threads:\nthe stages need not add up to end to end", fontsize=9)
    b3.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return fig


def plot_comparison(ds: xr.Dataset, path: str | Path, title: str | None = None) -> Path:
    """v̂ of every front end against truth (top); bars of RMSE/median error and lock-on time (middle);
    wall time per estimate, end to end and by stage, from the table's columns (bottom). Written atomically."""
    import matplotlib.pyplot as plt

    fig = comparison_figure(ds, title)
    save_figure(fig, path, provenance=ds.attrs, dpi=120)
    plt.close(fig)
    return Path(path)


# ---------------------------------------------------------------------- command line
def _config_from_args(args) -> VelocityConfig:
    from .velocity import apply_velocity_options

    if args.config:
        try:
            text = Path(args.config).read_text()
            # A key the configuration does not have would be dropped (from_json reads older runs' configs so).
            given = json.loads(text)
            if not isinstance(given, dict):
                raise ValueError(f"a JSON object is needed, not a {type(given).__name__}")
            unknown = sorted(set(given) - {f.name for f in dataclasses.fields(VelocityConfig)})
            if unknown:
                raise ValueError(f"no field {', '.join(map(repr, unknown))}")
            cfg = VelocityConfig.from_json(text)
        except (OSError, ValueError, TypeError, AttributeError) as exc:
            raise FootageError(f"{args.config}: not a VelocityConfig JSON ({exc})") from None
    elif args.paper:
        cfg = VelocityConfig.paper("dis", args.filter or "zero-phase")
    else:
        cfg = VelocityConfig()
    if getattr(args, "emd_gaze", None):
        cfg.emd.gaze = args.emd_gaze   # the EMD run's; the flow front ends derotate their flow exactly
    return apply_velocity_options(cfg, argparse.Namespace(**{k: v for k, v in vars(args).items() if k != "emd_gaze"}))


def _compare(args) -> int:
    front_ends = [f.strip() for f in args.front_ends.split(",") if f.strip()]
    flo_files = None
    if args.flo:
        p = Path(args.flo)
        flo_files = sorted(p.glob("*.flo")) if p.is_dir() else [p]
        if not flo_files or not all(f.exists() for f in flo_files):
            raise FootageError(f"{args.flo}: no .flo files there")
    units = FloUnits(args.flo_units, args.flo_gap, *args.flo_size)
    say = (lambda s: None) if args.quiet else (lambda s: print(s, file=sys.stderr))
    from .info import open_footage_from_args

    footage = open_footage_from_args(args, require_imu=not args.accel_from_truth)
    ds = compare_front_ends(footage, front_ends, _config_from_args(args), flo_files, units,
                            skip_s=args.skip, tol_m_s=args.tol, hold_s=args.hold, progress=not args.quiet, log=say)
    write_netcdf(ds, args.out)
    print(format_table(ds))
    if footage.truth is None:
        print(f"{args.footage} holds no truth: the accuracy columns are empty, only the timings are measured")
    print(f"scored after {ds.attrs['skip_s']:g} s; lock-on: {ds.attrs['lock_on']}; acceleration: "
          f"{ds.attrs['acceleration_source']}")
    if ds.attrs.get("notes", "none") != "none":
        print(f"notes: {ds.attrs['notes']}")
    print(f"wrote {args.out}")
    if args.csv:
        write_csv(ds, args.csv)
        print(f"wrote {args.csv}")
    if args.plot:
        plot_comparison(ds, args.plot)
        print(f"wrote {args.plot}")
    return 0


def add_parser(subparsers):
    """Register ``lobula compare`` on an argparse subparsers object; returns the parser. The options are
    :func:`experiments.parsers.add_compare_parser`'s, built without importing this module."""
    from .parsers import add_compare_parser

    return add_compare_parser(subparsers)
