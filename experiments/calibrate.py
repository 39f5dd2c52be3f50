"""Calibrating the EMD front end on a synthetic run with exact depth, to be held fixed elsewhere.

The exact pooled rate of each field at a frame with a depth map is the least-squares
pooling of the exact flow r(p)·(p − e), r = v/d, which is what a perfect dense flow
would give; the EMD's gradient-ratio r̄_f at the same frames is regressed onto it.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lobula.config import VelocityConfig
from lobula.emd_decoding import EMDFrontEnd, fit_calibration
from lobula.receptive_field import pool_fields, tile_fields
from stimuli.footage import Footage, FootageError


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
    """Gains for ``config.emd.calibration`` fitted on this footage (which is then not a test scene)."""
    config = config or VelocityConfig(front_end="emd")
    config.emd.calibration = 1.0
    idx, r_exact = exact_field_rates(footage, config)
    fields = tile_fields(footage.camera, config.fields)
    front = EMDFrontEnd(footage.camera, fields, config.emd)
    r_emd = np.array([r for _, r, _ in front.run(footage.frames())])
    skip = idx >= 15  # let the photoreceptor high-pass settle (0.5 s)
    return fit_calibration(r_emd[idx[skip]], r_exact[skip], per_field), len(idx)


def write_calibration(gains, path, source: str) -> Path:
    from lobula import __version__
    path = Path(path)
    payload = dict(gains=np.atleast_1d(gains).tolist(), source=source, lobula_version=__version__)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(payload))
    tmp.replace(path)
    return path


def read_calibration(path):
    d = json.loads(Path(path).read_text())
    g = d["gains"]
    return g[0] if len(g) == 1 else g
