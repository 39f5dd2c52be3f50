"""Parameter sweeps: a grid over configuration parameters, each point a full run scored against truth.

``lobula sweep --param PATH=V1,V2,... [--param ...] --out SWEEP.zarr``

**Parameters** are dotted paths into either configuration of a run:

* the velocity configuration (:class:`lobula.config.VelocityConfig`): ``front_end``,
  ``flow.gap``, ``fields.size_deg``, ``readout.cutoff_hz``, ``emd.emd.tau_s``,
  ``emd.lattice.dphi_deg``, ``emd.photoreceptor.tau_s``, …;
* the synthetic run (:class:`stimuli.track.TrackRunConfig`): ``scene.*`` (seed, texture,
  noise, off-axis angles, …), ``imu.*`` (noise densities, biases, seed), ``start_s``,
  ``duration_s``, ``scale``, ``profile``, ``constant_velocity_m_s``;
* ``seed``: an alias setting both ``scene.seed`` and ``imu.seed``.

A prefix ``velocity.`` or ``run.`` may be written for clarity. Values are a comma list
(``3,5,10``), a JSON list (``[[0.03,0.4],[0.01,0.2]]`` for tuple-valued fields), or a range
``lin:START:STOP:N`` / ``log:START:STOP:N``; each is converted to the type of the field's
default (``none`` for None). ``lobula sweep --list-params`` prints every path and its default.
Nested frozen dataclasses are replaced, never mutated, so points never share state.

**Each grid point** is a full run: the synthetic footage for its run configuration is
rendered (:func:`stimuli.track.make_track_run`; renders are cached in ``SWEEP.renders/``
keyed by a hash of the run configuration, so points that differ only in the velocity
configuration share one render, which is deleted once all its points are done unless
``--keep-renders``), then :func:`lobula.velocity.estimate_velocity`, then the metrics of
:mod:`experiments.compare` against the exact truth: RMSE and median |error| after
``skip_s``, observable fraction, lock-on time, r̄_f error against the depth maps, ms/frame
per stage. Points whose effective configurations coincide (e.g. ``emd.*`` values on a DIS
point) are computed once.

**Resumable.** Every finished point is written atomically to ``SWEEP.points/<key>.json``
(the key is a hash of the point's effective velocity configuration, run configuration and
scoring options; the record holds both configurations, the metrics, per-frame v̂, truth,
acceleration and observability, its timings and the version). A sweep that is killed and
started again with the same command recomputes only points without a record; deleting a
record recomputes that point. The Zarr store is assembled from the records at the end and
written atomically (a temporary directory, then a rename): one dim per swept parameter
(named by its path, coordinates = the values), the metrics as variables over the grid,
``stage_ms_per_frame`` over (grid, stage), per-frame ``v_hat``, ``v_true``, ``accel``,
``observable`` over (grid, time) unless ``--no-series``, and in ``attrs`` the full base
configurations, the sweep specification, the scoring options and the version.

**Execution** uses Dask: by default a local ``dask.distributed`` cluster of ``--workers``
single-threaded worker processes (``--scheduler threads`` for threads in this process,
``--scheduler synchronous`` for a plain loop when debugging), or ``--scheduler ADDRESS`` to
use an existing ``dask.distributed`` scheduler. One task renders each distinct run
configuration; each point is a task depending on its render; the driver writes records as
points complete and shows a progress bar.

**Cost and scaling.** A point costs its render (if not shared) plus one velocity run. Measured
with this module on this 2-core machine (shared, load ≈ 3) at 320×240 (the D435i camera at
scale 0.5) on the 30 s replay (900 frames): rendering 74 s (82 ms/frame); a DIS point
(flow, fields, readout, scoring) 8–13 s, mean 10 s, with two running at once; a 4-point
sweep sharing one render took 104 s end to end. With ``W`` workers, wall time ≈ render +
((R − 1)·render + N·point)/W for N points and R distinct renders
(:func:`estimate_sweep_s`): a 100-point DIS sweep over velocity parameters (R = 1) ≈ 10 min
on 2 workers; with 10 distinct scenes ≈ 15 min; with 100 distinct scenes ≈ 70 min (renders
dominate: sweep scene parameters on shorter or smaller runs). On a ``dask.distributed``
cluster the points are independent tasks, so wall time falls as 1/W until W nears the number
of points (or of distinct renders, since a point waits for its render; one shared render is a
serial head start of one render time); the scheduler's overhead (~1 ms per task) is negligible
against seconds-long points, and the driver only receives small records. Workers need the
``lobula`` package importable and the profile CSV (an absolute path in the run configuration)
readable. Renders go to ``SWEEP.renders/``: on a shared filesystem each scene is rendered
once; otherwise a worker that cannot see a render re-renders it locally (renders are
deterministic, so results are unchanged). Records are written by the driver, so
``SWEEP.points/`` needs no shared storage. A remote cluster should not set
``MALLOC_TRIM_THRESHOLD_`` in its workers (dask's default; see :class:`_Client`).
"""
from __future__ import annotations

import copy
import itertools
import json
import os
import shutil
import signal
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import xarray as xr

from lobula.config import VelocityConfig
from lobula.readers.core import FootageError
from stimuli.track import TrackRunConfig, recorded_profile

from .compare import LOCK_HOLD_S, LOCK_TOL_M_S
from .sweep_params import (ALIASES, Param, SweepError, apply_value, config_hash, effective_velocity, list_paths,
                           parse_param, run_config_from_dict, run_key)
# A point's tasks, and the records and the store, live in their own modules; named from here as well.
from .sweep_point import COUNTER_ENV, compute_point, ensure_render
from .sweep_store import assemble, read_record, sweep_paths, write_record, write_zarr


class SweepInterrupted(RuntimeError):
    """The sweep stopped before every point was done; finished points are recorded."""


@dataclass
class Point:
    """One grid point: its index and coordinates, both configurations and their hashes."""

    index: tuple
    coords: dict
    velocity: VelocityConfig
    run: TrackRunConfig
    key: str
    run_key: str


@dataclass
class SweepSpec:
    """What to sweep (params, in dim order) around which base configurations, and how to score."""

    params: list[Param]
    velocity: VelocityConfig = field(default_factory=VelocityConfig)
    run: TrackRunConfig = field(default_factory=TrackRunConfig)
    skip_s: float = 2.0
    tol_m_s: float = LOCK_TOL_M_S
    hold_s: float = LOCK_HOLD_S

    @classmethod
    def from_strings(cls, params: list[str], velocity: VelocityConfig | None = None,
                     run: TrackRunConfig | None = None, **scoring) -> "SweepSpec":
        velocity = velocity or VelocityConfig()
        run = run or TrackRunConfig()
        ps = [parse_param(p, velocity, run) for p in params]
        names = [p.name for p in ps]
        if len(set(names)) != len(names):
            raise SweepError(f"a parameter is given twice: {names}")
        targets = [t for p in ps for t in p.targets]
        if len(set(targets)) != len(targets):
            raise SweepError(f"two --param options set the same field: {targets}")
        return cls(ps, velocity, run, **scoring)

    @property
    def scoring(self) -> dict:
        return dict(skip_s=self.skip_s, tol_m_s=self.tol_m_s, hold_s=self.hold_s)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(len(p.values) for p in self.params)

    @property
    def dims(self) -> list[str]:
        return [p.name for p in self.params]

    def points(self) -> list[Point]:
        """Every grid point, in C order over the params; configurations validated."""
        out = []
        for index in itertools.product(*(range(len(p.values)) for p in self.params)):
            vel, run = copy.deepcopy(self.velocity), copy.deepcopy(self.run)
            coords = {}
            for p, i in zip(self.params, index):
                v = p.values[i]
                coords[p.name] = v
                for tgt in p.targets:
                    try:
                        vel, run = apply_value(tgt, v, vel, run)
                    except (ValueError, TypeError) as exc:
                        raise SweepError(f"--param {p.name}={v!r}: {exc}") from None
            key = config_hash(dict(velocity=effective_velocity(vel), run=run.to_dict(), scoring=self.scoring))
            out.append(Point(index, coords, vel, run, key, run_key(run)))
        return out

    def to_dict(self) -> dict:
        return dict(params=[p.to_dict() for p in self.params], dims=self.dims, shape=list(self.shape),
                    scoring=self.scoring)


# ---------------------------------------------------------------------- running
def _threads_per_worker(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(workers, 1))


@contextmanager
def _workers_ignore_sigint():
    """Worker processes started inside the block ignore SIGINT (they inherit the setting; Python then
    installs no KeyboardInterrupt of its own). A Ctrl-C at the terminal reaches the whole process group:
    only this process acts on it, closing the cluster, rather than each worker printing a traceback. A
    Ctrl-C during the cluster's start (a second or two) is not seen."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


class _Client:
    """A dask.distributed client for 'processes' / 'threads' (a LocalCluster) or an address."""

    def __init__(self, scheduler: str, workers: int):
        import logging

        from distributed import Client, LocalCluster

        self.cluster = None
        self._restore = None
        if scheduler in ("processes", "threads"):
            import dask

            # dask's nanny sets MALLOC_TRIM_THRESHOLD_ in worker processes, which also fixes glibc's
            # mmap threshold: every large numpy temporary is then mmapped and page-faulted afresh
            # (measured: 6x the page faults, 5x the system time, fields stage 2x slower). Not here.
            with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}), \
                    _workers_ignore_sigint():
                self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1,
                                            processes=scheduler == "processes", dashboard_address=None,
                                            silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
            self.threads = _threads_per_worker(workers)
            if scheduler == "threads":  # tasks set torch/OpenCV threads process-wide: restore them after
                import cv2

                from lobula._optional import optional_torch

                torch = optional_torch()
                self._restore = (torch.get_num_threads() if torch is not None else None, cv2.getNumThreads())
        else:
            try:
                self.client = Client(scheduler, timeout="20s")
            except (OSError, TimeoutError) as exc:
                raise SweepError(f"--scheduler {scheduler}: cannot reach a dask scheduler there ({exc})") from None
            self.threads = 0  # the cluster's own business

    def close(self):
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()
            if self._restore:
                import cv2

                from lobula._optional import optional_torch

                if self._restore[0] is not None:
                    optional_torch().set_num_threads(self._restore[0])
                cv2.setNumThreads(self._restore[1])


#: the schedulers run_sweep starts itself; any other --scheduler is a running dask scheduler's address
LOCAL_SCHEDULERS = ("processes", "threads", "synchronous")


def _check_scheduler(scheduler: str) -> None:
    """ValueError unless ``scheduler`` is one of :data:`LOCAL_SCHEDULERS` or an address (HOST:PORT, with or
    without a protocol such as tcp://), before anything is made."""
    if scheduler in LOCAL_SCHEDULERS:
        return
    host, _, port = scheduler.rpartition("://")[2].rpartition(":")
    if not (host and port.isdigit()):
        raise ValueError(f"--scheduler {scheduler}: use {', '.join(LOCAL_SCHEDULERS)} or a dask scheduler's "
                         f"address (tcp://HOST:PORT)")


def run_sweep(spec: SweepSpec, out: str | Path, scheduler: str = "processes", workers: int = 2,
              progress: bool = True, keep_renders: bool = False, series: bool = True,
              stop_after: int | None = None, log=None) -> xr.Dataset:
    """Run (or resume) the sweep and write the Zarr store atomically; returns the assembled Dataset.

    scheduler: "processes" (default: a local dask.distributed cluster of ``workers`` processes),
    "threads", "synchronous" (no Dask; debugging) or a dask.distributed scheduler address.
    stop_after: stop once this many points have been recorded in this call (a test hook that
    simulates a killed sweep: raises :class:`SweepInterrupted`, no store is written).
    """
    from tqdm.auto import tqdm

    _check_scheduler(scheduler)
    say = log or (lambda s: None)
    out, points_dir, renders_dir = sweep_paths(out)
    grid = spec.points()
    unique = {}
    for p in grid:
        unique.setdefault(p.key, p)
    done = {k for k in unique if read_record(points_dir, k) is not None}
    todo = [p for k, p in unique.items() if k not in done]
    say(f"sweep: {len(grid)} grid points, {len(unique)} distinct runs, {len(done)} already recorded in "
        f"{points_dir}, {len(todo)} to compute")
    points_dir.mkdir(parents=True, exist_ok=True)
    failed: dict[str, str] = {}
    computed = 0
    if todo:
        remaining = {}
        for p in todo:
            remaining[p.run_key] = remaining.get(p.run_key, 0) + 1
        bar = tqdm(total=len(todo), desc="sweep", unit="point", disable=not progress, mininterval=1)

        def finished(p: Point, rec: dict | None, exc: BaseException | None):
            nonlocal computed
            if rec is not None:
                write_record(points_dir, rec)
                computed += 1
            else:
                failed[p.key] = f"{type(exc).__name__}: {exc}"
                say(f"point {p.coords} failed: {failed[p.key]}")
            bar.update(1)
            remaining[p.run_key] -= 1
            if remaining[p.run_key] == 0 and not keep_renders:
                shutil.rmtree(renders_dir / p.run_key, ignore_errors=True)
            if stop_after is not None and computed >= stop_after:
                raise SweepInterrupted(f"stopped after {computed} point(s) (stop_after)")

        try:
            if scheduler == "synchronous":
                _run_synchronous(todo, spec, renders_dir, finished)
            else:
                _run_dask(todo, spec, renders_dir, scheduler, workers, finished)
        finally:
            bar.close()
    if failed and not computed and not done:
        # A store of NaN alone would look like a result; the records of the failures are all there is.
        key, why = next(iter(failed.items()))
        raise SweepError(f"every point failed, so no store is written (the first, {key}: {why}); "
                         f"mend that and run the same command again")
    ds = assemble(spec, grid, points_dir, series=series)
    ds.attrs.update(points_computed=computed, points_reused=len(done), scheduler=scheduler,
                    workers=workers if scheduler in ("processes", "threads") else 0,
                    failed=json.dumps(failed))
    write_zarr(ds, out)
    if not failed and not keep_renders:
        shutil.rmtree(renders_dir, ignore_errors=True)
    say(f"wrote {out}: {' × '.join(f'{d} ({n})' for d, n in zip(spec.dims, spec.shape))}; "
        f"computed {computed}, reused {len(done)}, failed {len(failed)}")
    return ds


def _run_synchronous(todo: list[Point], spec: SweepSpec, renders_dir: Path, finished):
    """The points in a plain loop in this process (no Dask; debugging), each distinct render made once."""
    threads = 0
    renders = {}
    for p in todo:
        try:
            if p.run_key not in renders:
                renders[p.run_key] = ensure_render(p.run, str(renders_dir), p.run_key, threads)
            rec = compute_point(renders[p.run_key], p.velocity, p.run, spec.scoring, p.key,
                                str(renders_dir), threads)
            exc = None
        except (FootageError, ValueError, RuntimeError, OSError) as e:
            rec, exc = None, e
        finished(p, rec, exc)


def _run_dask(todo: list[Point], spec: SweepSpec, renders_dir: Path, scheduler: str, workers: int, finished):
    from distributed import as_completed

    c = _Client(scheduler, workers)
    try:
        client = c.client
        renders = {}
        for p in todo:
            if p.run_key not in renders:
                renders[p.run_key] = client.submit(ensure_render, p.run, str(renders_dir), p.run_key, c.threads,
                                                   key=f"render-{p.run_key}", pure=False)
        futures = {}
        for p in todo:
            f = client.submit(compute_point, renders[p.run_key], p.velocity, p.run, spec.scoring, p.key,
                              str(renders_dir), c.threads, key=f"point-{p.key}", pure=False)
            futures[f.key] = (f, p)
        try:
            for f in as_completed([f for f, _ in futures.values()]):
                p = futures[f.key][1]
                try:
                    rec, exc = f.result(), None
                except Exception as e:  # a failed point is reported, not recorded: a restart retries it
                    rec, exc = None, e
                finished(p, rec, exc)
        except BaseException:
            client.cancel([f for f, _ in futures.values()] + list(renders.values()), force=True)
            raise
    finally:
        c.close()


def estimate_sweep_s(n_points: int, n_renders: int, point_s: float, render_s: float, workers: int = 2) -> float:
    """Rough wall time (s) of a sweep: one render before anything, then the rest spread over workers."""
    if n_points <= 0:
        return 0.0
    return render_s + ((n_renders - 1) * render_s + n_points * point_s) / max(workers, 1)


# ---------------------------------------------------------------------- command line
def _base_configs(args) -> tuple[VelocityConfig, TrackRunConfig]:
    def load(path, what):
        try:
            return json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise SweepError(f"{path}: not a {what} JSON ({exc})") from None

    if args.base_velocity:
        d = load(args.base_velocity, "VelocityConfig")
        if isinstance(d.get("config"), str):  # attrs of a velocity NetCDF saved as JSON
            d = json.loads(d["config"])
        try:
            vel = VelocityConfig.from_dict(d)
        except (TypeError, ValueError) as exc:
            raise SweepError(f"{args.base_velocity}: not a VelocityConfig ({exc})") from None
    elif args.paper:
        vel = VelocityConfig.paper()
    else:
        vel = VelocityConfig()
    if args.base_run:
        d = load(args.base_run, "TrackRunConfig")
        run = run_config_from_dict(d["config"] if isinstance(d.get("config"), dict) else d)
    else:
        profile = args.profile
        if profile is None and not args.builtin_profile and recorded_profile() is not None:
            profile = str(recorded_profile())
        run = TrackRunConfig(profile=profile, start_s=args.start, duration_s=args.base_duration, scale=args.scale)
    return vel, run


def _value(v) -> str:
    return f"{v:g}" if isinstance(v, (float, np.floating)) else str(v)


def rmse_summary(ds: xr.Dataset, dims: list[str]) -> list[str]:
    """Lines that say which swept values gave the lowest velocity RMSE (m/s), as `lobula sweep` prints them.

    The range over the scored points and the lowest single point; then, for each swept parameter
    with more than one value, its mean RMSE at each value over all the other parameters' values
    (over seeds, say) and the value with the lowest mean: the single lowest point may sit at a value
    whose mean is the worst. Failed points (NaN) are left out of a mean and the value says how
    many were scored; the lowest mean is taken among the values with every point scored, when
    any has.
    """
    rm = ds.rmse_m_s.transpose(*dims)
    v = rm.values
    ok = np.isfinite(v)
    if not ok.any():
        return ["RMSE: no point was scored (every point's RMSE is NaN)"]
    best = np.unravel_index(int(np.nanargmin(v)), v.shape)
    lines = [f"RMSE {np.nanmin(v):.4f}..{np.nanmax(v):.4f} m/s over {int(ok.sum())} of {v.size} points; "
             f"lowest single point: " + ", ".join(f"{d}={_value(ds[d].values[i])}" for d, i in zip(dims, best))]
    for k, d in enumerate(dims):
        n_values = v.shape[k]
        if n_values < 2:
            continue
        moved = np.moveaxis(v, k, 0).reshape(n_values, -1)
        scored = np.isfinite(moved).sum(1)
        means = np.array([np.mean(row[np.isfinite(row)]) if n else np.nan for row, n in zip(moved, scored)])
        pool = np.isfinite(means) & (scored == moved.shape[1])
        if not pool.any():
            pool = np.isfinite(means)
        lowest = int(np.flatnonzero(pool)[np.argmin(means[pool])])
        others = [o for o in dims if o != d and ds.sizes[o] > 1]
        what = ("RMSE" if moved.shape[1] == 1 else
                f"mean RMSE over the {moved.shape[1]} values of {others[0]}" if len(others) == 1 else
                f"mean RMSE over the {moved.shape[1]} combinations of {', '.join(others)}")
        parts = [f"{_value(ds[d].values[i])}: " + (f"{means[i]:.4f}" if np.isfinite(means[i]) else "—")
                 + (f" ({scored[i]} of {moved.shape[1]} scored)" if scored[i] < moved.shape[1] else "")
                 for i in range(n_values)]
        lines.append(f"{d}: {what} (m/s) at each value — {'; '.join(parts)}; lowest at "
                     f"{d}={_value(ds[d].values[lowest])}")
    return lines


def _sweep(args) -> int:
    say = (lambda s: None) if args.quiet else (lambda s: print(s, file=sys.stderr))
    vel, run = _base_configs(args)
    if args.list_params:
        print("velocity configuration (VelocityConfig):")
        for k, v in list_paths(vel).items():
            print(f"  {k} = {v!r}")
        print("synthetic run (TrackRunConfig):")
        for k, v in list_paths(run).items():
            print(f"  {k} = {v!r}")
        print("aliases: " + ", ".join(f"{k} -> {' + '.join(t.split('.', 1)[1] for t in v)}" for k, v in ALIASES.items()))
        return 0
    if not args.param:
        raise SweepError("give at least one --param PATH=V1,V2,... (lobula sweep --list-params lists the paths)")
    if not args.out:
        raise SweepError("--out SWEEP.zarr is required")
    if Path(args.out).suffix != ".zarr":  # a Zarr store is a folder: a .nc name would hide what it holds
        raise SweepError(f"--out {args.out}: a sweep is a Zarr store; give a name ending in .zarr")
    if not run.duration_s > args.skip:
        raise SweepError(f"runs of {run.duration_s:g} s (--base-duration or --base-run) leave nothing to score after "
                         f"--skip {args.skip:g} s: make them longer, or the skip shorter")
    spec = SweepSpec.from_strings(args.param, vel, run, skip_s=args.skip, tol_m_s=args.tol, hold_s=args.hold)
    grid = spec.points()
    if args.dry_run:
        _, points_dir, _ = sweep_paths(args.out)
        keys = {p.key for p in grid}
        done = sum(read_record(points_dir, k) is not None for k in keys)
        print(f"{len(grid)} points ({' × '.join(map(str, spec.shape))}), {len(keys)} distinct runs, "
              f"{len({p.run_key for p in grid})} renders, {done} already recorded")
        for p in grid[:50]:
            print(f"  {p.key}  {p.coords}")
        return 0
    try:
        ds = run_sweep(spec, args.out, scheduler=args.scheduler, workers=args.workers, progress=not args.quiet,
                       keep_renders=args.keep_renders, series=not args.no_series, log=say)
    except KeyboardInterrupt:
        _, points_dir, _ = sweep_paths(args.out)
        n = len(list(points_dir.glob("*.json")))
        print(f"lobula sweep: interrupted; {n} finished point(s) are recorded in {points_dir}. "
              f"Run the same command again to resume.", file=sys.stderr)
        return 130
    print(f"wrote {args.out}: dims {dict(zip(spec.dims, spec.shape))}; computed {ds.attrs['points_computed']}, "
          f"reused {ds.attrs['points_reused']}")
    for line in rmse_summary(ds, spec.dims):
        print(line)
    failed = json.loads(ds.attrs.get("failed", "{}"))
    if failed:
        print(f"{len(failed)} point(s) failed (NaN in the store; rerun to retry): "
              + "; ".join(f"{k}: {v}" for k, v in list(failed.items())[:3]), file=sys.stderr)
        return 1
    return 0


def add_parser(subparsers):
    """Register ``lobula sweep`` on an argparse subparsers object; returns the parser. The options are
    :func:`experiments.parsers.add_sweep_parser`'s, built without importing this module."""
    from .parsers import add_sweep_parser

    return add_sweep_parser(subparsers)
