"""Calibrating the EMD front end on a synthetic run with exact depth, to be held fixed elsewhere.

The exact pooled rate of each field at a frame with a depth map is the least-squares
pooling of the exact flow r(p)·(p − e), r = v/d, which is what a perfect dense flow
would give; the EMD's gradient-ratio r̄_f at the same frames is regressed onto it.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from lobula.config import VelocityConfig
from lobula.receptive_field import pool_fields, tile_fields
from lobula.readers.core import Footage, FootageError


def exact_field_rates(footage: Footage, config: VelocityConfig, epipole=(0.0, 0.0)):
    """(frame indices, r_exact (k, F)) from the footage's depth maps and true forward velocity."""
    if footage.truth is None:
        raise FootageError(f"{footage.path}: calibration needs truth.csv and depth/ maps (a synthetic run)")
    fields = tile_fields(footage.camera, config.fields)
    idx, rows = [], []
    for i, t in enumerate(footage.times):
        d = footage.depth_map(i)
        if d is None:
            continue
        v = np.interp(t, footage.truth["time_s"], footage.truth["v_forward_m_s"])
        r_pix = v / d
        flow = r_pix * np.stack([fields.x - epipole[0], fields.y - epipole[1]])
        rows.append(pool_fields(flow, fields, epipole)[0])
        idx.append(i)
    if not idx:
        raise FootageError(f"{footage.path}: no depth maps in depth/; render it with lobula scene")
    return np.array(idx), np.array(rows)


def calibrate_emd(footage: Footage, config: VelocityConfig | None = None, per_field: bool = True):
    """Gains and latency for ``config.emd`` fitted on this footage (which is then not a test scene).

    The latency (s) is the shift of the decoded r̄ that best correlates with the exact
    rates (searched in 1/4-frame steps over 0–0.3 s); the gains are then fitted at it.
    Returns (gains, latency_s, number of frames with depth used).
    """
    from lobula._optional import require_torch
    from lobula.emd_front_end import EMDFrontEnd, fit_calibration

    require_torch("the EMD front end")
    config = config or VelocityConfig(front_end="emd")
    config.emd.calibration = 1.0
    config.emd.latency_s = 0.0
    idx, r_exact = exact_field_rates(footage, config)
    fields = tile_fields(footage.camera, config.fields)
    # The exact rates are the camera's own fields', so the front end reads the camera's own image
    # (no stabilised gaze, whose fields would look elsewhere while the camera turns).
    front = EMDFrontEnd(footage.camera, fields, replace(config.emd, gaze="none"))
    out = list(front.run(footage.frames()))
    t = np.array([o[0] for o in out])
    r_emd = np.array([o[1] for o in out])
    keep = idx >= 15  # let the photoreceptor high-pass settle (0.5 s)
    t_x, r_x = footage.times[idx[keep]], r_exact[keep]
    dt = float(np.median(np.diff(t)))

    def shifted(lag):
        return np.array([np.interp(t_x + lag, t, r_emd[:, f]) for f in range(r_emd.shape[1])]).T

    lags = np.arange(0.0, 0.3 + 1e-9, dt / 4)
    score = [np.corrcoef(np.nan_to_num(shifted(l)).ravel(), r_x.ravel())[0, 1] for l in lags]
    latency = float(lags[int(np.nanargmax(score))])
    return fit_calibration(shifted(latency), r_x, per_field), latency, len(idx)


def write_calibration(gains, latency_s: float, path, source: str) -> Path:
    from lobula import __version__
    path = Path(path)
    payload = dict(gains=np.atleast_1d(gains).tolist(), latency_s=latency_s, source=source,
                   lobula_version=__version__)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(payload))
    tmp.replace(path)
    return path


def read_calibration(path):
    """(gains: float or list, latency_s) from a calibration JSON."""
    try:
        d = json.loads(Path(path).read_text())
        g = d["gains"]
        return (g[0] if len(g) == 1 else g), float(d["latency_s"])
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise FootageError(f"{path}: not a calibration file from `lobula calibrate-emd` ({exc})") from None


def run_calibrate(args) -> int:
    from experiments.calibrate import calibrate_emd, write_calibration
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage

    fo = open_footage(args.footage)
    gains, latency, n = calibrate_emd(fo, VelocityConfig(front_end="emd"), per_field=not args.single_gain)
    write_calibration(gains, latency, args.out, str(fo.path))
    g = np.atleast_1d(gains)
    print(f"wrote {args.out}: {g.size} gain(s) from {n} frames with depth; median {np.median(g):.3f}, "
          f"range {g.min():.3f}..{g.max():.3f}; latency {1000 * latency:.0f} ms")
    return 0


def add_parser(subparsers):
    """Register ``lobula calibrate-emd`` on an argparse subparsers object; returns the parser. The options are
    :func:`experiments.parsers.add_calibrate_parser`'s, built without importing this module."""
    from .parsers import add_calibrate_parser

    return add_calibrate_parser(subparsers)
