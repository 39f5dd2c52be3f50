"""A parameter sweep's records and its Zarr store.

Each finished point is a JSON record in ``SWEEP.points/`` (:func:`write_record`,
:func:`read_record`); :func:`assemble` gathers the records into the grid Dataset and
:func:`write_zarr` writes it atomically (:mod:`experiments.sweep` says what the store holds).
"""
from __future__ import annotations

import json
import os
import shutil
import warnings
from datetime import datetime, timezone
from pathlib import Path
import numpy as np
import xarray as xr

from .compare import METRIC_ATTRS, METRICS
from .store import provenance
from .sweep_params import Param, jsonable


# ---------------------------------------------------------------------- records
def sweep_paths(out: str | Path) -> tuple[Path, Path, Path]:
    """(store, points folder, renders folder): ``X.zarr`` → ``X.points/``, ``X.renders/`` beside it."""
    out = Path(out)
    stem = out.name[:-5] if out.name.endswith(".zarr") else out.name
    return out, out.parent / f"{stem}.points", out.parent / f"{stem}.renders"


def write_record(points_dir: Path, record: dict) -> Path:
    """Write one point's record atomically (temporary file, then rename)."""
    points_dir.mkdir(parents=True, exist_ok=True)
    path = points_dir / f"{record['key']}.json"
    tmp = points_dir / f".{record['key']}.{os.getpid()}.tmp"
    try:
        tmp.write_text(json.dumps(record, default=float))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def read_record(points_dir: Path, key: str) -> dict | None:
    """A finished point's record, or None (absent or unreadable: it will be recomputed)."""
    try:
        rec = json.loads((points_dir / f"{key}.json").read_text())
    except (OSError, ValueError):
        return None
    return rec if rec.get("key") == key and "metrics" in rec else None


# ---------------------------------------------------------------------- the store
def _coord_values(values: list):
    if all(isinstance(v, bool) for v in values):
        return np.array(values, dtype=bool)
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return np.array(values, dtype=int if all(isinstance(v, int) for v in values) else float)
    return np.array([v if isinstance(v, str) else json.dumps(jsonable(v)) for v in values], dtype=object)


# The configuration's leaves carry their units in their names; these suffixes name UDUNITS units.
_UNIT_SUFFIXES = (("_m_s2", "m/s2"), ("_m_s", "m/s"), ("_rad_s", "rad/s"), ("_deg", "degree"), ("_hz", "Hz"),
                  ("_ms", "ms"), ("_s", "s"), ("_m", "m"))
_DIMENSIONLESS = ("fraction", "frac", "scale", "contrast", "brightness", "rel_error", "scale_error", "scale_prior",
                  "scale_std")


def _param_attrs(p: Param, values: np.ndarray) -> dict:
    """CF attributes of a swept parameter's coordinate: long_name, and units from the leaf's name (integers and
    booleans: counts, seeds and switches, "1"); a float leaf whose name gives no units gets none, which
    :func:`experiments.store.cf_problems` reports."""
    attrs = dict(long_name=f"swept parameter {p.name}", sets=", ".join(p.targets))
    if values.dtype.kind not in "biuf":
        return attrs
    leaf = p.targets[0].rsplit(".", 1)[-1]
    units = next((u for suffix, u in _UNIT_SUFFIXES if leaf.endswith(suffix)), None)
    if units is None and (values.dtype.kind in "biu" or leaf.endswith(_DIMENSIONLESS)):
        units = "1"
    if units is not None:
        attrs["units"] = units
    return attrs


def assemble(spec, grid: list, points_dir: Path, series: bool = True) -> xr.Dataset:
    """The grid Dataset from the point records (NaN where a point has no record).

    spec: the sweep's :class:`experiments.sweep.SweepSpec`; grid: its :class:`experiments.sweep.Point` list;
    points_dir: the folder of the point records.
    """
    shape, dims = spec.shape, spec.dims
    records = {}
    for p in grid:
        if p.key not in records:
            records[p.key] = read_record(points_dir, p.key)
    recs = [r for r in records.values() if r]
    stages = list(dict.fromkeys(s for r in recs for s in r.get("stage_ms_per_frame", {})))
    data = {k: np.full(shape, np.nan) for k in METRICS}
    extra = {k: np.full(shape, np.nan) for k in ("render_s", "point_wall_s")}
    stage = np.full(shape + (len(stages),), np.nan)
    keys = np.empty(shape, dtype=object)
    done = np.zeros(shape, dtype=bool)
    t_grid = None
    if series and recs:
        longest = max(recs, key=lambda r: len(r["series"]["time_s"]))
        t_grid = np.asarray(longest["series"]["time_s"], float)
        ser = {k: np.full(shape + (t_grid.size,), np.nan) for k in ("v_hat", "v_true", "accel")}
        obs = np.zeros(shape + (t_grid.size,), dtype=bool)
    for p in grid:
        keys[p.index] = p.key
        r = records[p.key]
        if not r:
            continue
        done[p.index] = True
        for k in METRICS:
            v = r["metrics"].get(k)
            data[k][p.index] = np.nan if v is None else v
        extra["render_s"][p.index] = np.nan if r.get("render_s") is None else r["render_s"]
        extra["point_wall_s"][p.index] = r.get("wall_s", np.nan)
        for j, s in enumerate(stages):
            stage[p.index + (j,)] = r["stage_ms_per_frame"].get(s, np.nan)
        if t_grid is not None:
            s = r["series"]
            ts = np.asarray(s["time_s"], float)
            for k in ser:
                ser[k][p.index] = np.interp(t_grid, ts, np.asarray(s[k], float), left=np.nan, right=np.nan)
            obs[p.index] = np.interp(t_grid, ts, np.asarray(s["observable"], float), left=0, right=0) >= 0.5
    vars_ = {k: (dims, data[k], METRIC_ATTRS[k]) for k in METRICS}
    vars_["render_s"] = (dims, extra["render_s"], dict(units="s", long_name="time to render the point's footage"))
    vars_["point_wall_s"] = (dims, extra["point_wall_s"], dict(units="s", long_name="velocity run + scoring wall time"))
    vars_["stage_ms_per_frame"] = (dims + ["stage"], stage, dict(units="ms", long_name="wall time per estimate of each stage"))
    vars_["point_key"] = (dims, keys, dict(long_name="record name in the points folder (<key>.json)"))
    vars_["done"] = (dims, done, dict(units="1", long_name="point has a record"))
    coords = {p.name: (p.name, v, _param_attrs(p, v)) for p in spec.params for v in [_coord_values(p.values)]}
    coords["stage"] = ("stage", np.array(stages, dtype=object), dict(long_name="pipeline stage"))
    if t_grid is not None:
        vars_["v_hat"] = (dims + ["time"], ser["v_hat"], dict(units="m/s", long_name="estimated forward velocity"))
        vars_["v_true"] = (dims + ["time"], ser["v_true"], dict(units="m/s", long_name="true forward velocity"))
        vars_["accel"] = (dims + ["time"], ser["accel"], dict(units="m/s2", long_name="forward acceleration used"))
        vars_["observable"] = (dims + ["time"], obs, dict(units="1", long_name="velocity observable"))
        coords["time"] = ("time", t_grid, dict(units="s", long_name="time since the run's first frame"))
    ds = xr.Dataset(vars_, coords=coords)
    base = dict(velocity=spec.velocity.to_dict(), run=spec.run.to_dict())
    ds.attrs.update(provenance(json.dumps(base, sort_keys=True, default=str),
                               base_velocity_config=spec.velocity.to_json(),
                               base_run_config=json.dumps(spec.run.to_dict(), sort_keys=True, default=str),
                               sweep=json.dumps(spec.to_dict(), default=str), skip_s=spec.skip_s,
                               lock_tol_m_s=spec.tol_m_s, lock_hold_s=spec.hold_s,
                               n_points=int(np.prod(shape)), n_distinct=len(records),
                               points_dir=str(points_dir),
                               created_utc=datetime.now(timezone.utc).isoformat(timespec="seconds")))
    return ds


def write_zarr(ds: xr.Dataset, out: str | Path) -> Path:
    """Write ``ds`` as a Zarr store atomically: a temporary directory beside it, then a rename.

    The store declares CF-1.10, its variables walked first (:func:`experiments.store.cf_ready`)."""
    from .store import cf_ready

    out = Path(out)
    ds = cf_ready(ds, out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    old = out.parent / f".{out.name}.old-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
            ds.to_zarr(tmp, mode="w", consolidated=True)
        if out.exists():
            os.replace(out, old)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists() and not out.exists():
            os.replace(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)
    return out
