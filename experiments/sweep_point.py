"""One grid point of a parameter sweep: the tasks that run on the workers.

:func:`ensure_render` renders a point's synthetic footage (once per run configuration) and
:func:`compute_point` runs the velocity pipeline on it and scores it against the exact truth,
returning the point's record (:mod:`experiments.sweep` says what a record holds).
"""
from __future__ import annotations

import copy
import json
import os
import socket
import time as _time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from lobula import __version__
from lobula.config import VelocityConfig
from lobula.readers.core import FootageError
from stimuli.track import TrackRunConfig

from .sweep_params import run_key


COUNTER_ENV = "LOBULA_SWEEP_COUNTER"  # test hook: a file each point computation appends its key to


def _limit_threads(threads: int):
    if threads and threads > 0:
        import cv2

        from lobula._optional import optional_torch

        cv2.setNumThreads(threads)
        torch = optional_torch()   # None without torch: the EMD front end is then not in the sweep
        if torch is not None:
            torch.set_num_threads(threads)


def ensure_render(run: TrackRunConfig, renders_dir: str, key: str, threads: int = 0) -> dict:
    """Render ``run`` into ``renders_dir/key`` unless it is already there; returns its path and cost.

    Renders are deterministic functions of the run configuration, and the folder appears
    atomically (:func:`stimuli.footage_writer.write_footage`), so a complete folder is always reusable.
    """
    from stimuli.track import make_track_run

    folder = Path(renders_dir) / key
    timing = folder / "render_time.json"
    if (folder / "frames.csv").exists():
        try:
            info = json.loads(timing.read_text())
        except (OSError, ValueError):
            info = {}
        return dict(path=str(folder), render_s=float(info.get("render_s", float("nan"))), rendered=False,
                    n_frames=info.get("n_frames"))
    _limit_threads(threads)
    folder.parent.mkdir(parents=True, exist_ok=True)
    t0 = _time.perf_counter()
    try:
        make_track_run(folder, run, progress=False)
    except OSError:
        if not (folder / "frames.csv").exists():  # not a concurrent render of the same run: a real error
            raise
    render_s = _time.perf_counter() - t0
    n = sum(1 for _ in open(folder / "frames.csv")) - 1
    try:
        timing.write_text(json.dumps(dict(render_s=render_s, n_frames=n, host=socket.gethostname())))
    except OSError:
        pass
    return dict(path=str(folder), render_s=render_s, rendered=True, n_frames=n)


def compute_point(render: dict, velocity: VelocityConfig, run: TrackRunConfig, scoring: dict, key: str,
                  renders_dir: str, threads: int = 0) -> dict:
    """One grid point: velocity on its render, scored against exact truth. Returns its record."""
    from lobula.readers import open_footage

    from .compare import exact_rates, front_end_metrics, stage_ms_per_frame
    from lobula.velocity import estimate_velocity
    from lobula.velocity.inertial import forward_accel_at

    counter = os.environ.get(COUNTER_ENV)
    if counter:
        with open(counter, "a") as fh:
            fh.write(key + "\n")
    _limit_threads(threads)
    if not (Path(render["path"]) / "frames.csv").exists():  # a worker that cannot see the shared render
        render = ensure_render(run, renders_dir, run_key(run), threads)
    footage = open_footage(render["path"])
    cfg = copy.deepcopy(velocity)
    t0 = _time.perf_counter()
    ds = estimate_velocity(footage, cfg, progress=False)
    metrics = front_end_metrics(ds, footage, scoring["skip_s"], exact_rates(footage, cfg),
                                scoring["tol_m_s"], scoring["hold_s"])
    wall = _time.perf_counter() - t0
    t_grid = footage.times - footage.times[0]
    t = ds.time.values - footage.times[0]

    def on_grid(x, fill=np.nan):
        return np.interp(t_grid, t, np.asarray(x, float), left=fill, right=fill)

    try:
        accel = forward_accel_at(footage, footage.times, cfg)[0]
    except FootageError:
        accel = on_grid(ds.accel.values)
    v_true = (np.interp(footage.times, footage.truth["time_s"], footage.truth["v_forward_m_s"])
              if footage.truth is not None else np.full(t_grid.size, np.nan))
    series = dict(time_s=t_grid.round(6).tolist(), v_hat=on_grid(ds.v_hat.values).tolist(),
                  observable=(on_grid(ds.observable.values.astype(float), 0.0) >= 0.5).tolist(),
                  accel=np.asarray(accel, float).tolist(), v_true=np.asarray(v_true, float).tolist())
    return dict(key=key, velocity=velocity.to_dict(), run=run.to_dict(), scoring=scoring, metrics=metrics,
                stage_ms_per_frame=stage_ms_per_frame(ds), series=series, wall_s=wall,
                render_s=render.get("render_s"), n_frames=len(footage), n_estimates=int(ds.sizes["time"]),
                host=socket.gethostname(), pid=os.getpid(), lobula_version=__version__,
                finished_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"))
