"""The folder layouts: the footage folder and the D435i sample (DESIGN.md, "Footage folder").

* a **footage folder** (:func:`open_folder`): camera.json, frames/, frames.csv, imu.csv,
  optional truth.csv and depth/ (what the synthetic scenes' writer,
  ``stimuli.footage_writer.write_footage``, makes);
* the **D435i sample** of the FLIVVER track run as shipped in ``../shared/data``
  (:func:`open_d435i_sample`): frames named by raw frame number, ``velocity.csv`` with
  raw_frame = sample + 3 and no IMU, so forward acceleration is derived from the smoothed
  ground truth (and every output says so).

Frames are decoded one at a time on iteration, so memory does not grow with length.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .core import (Footage, FootageError, check_imu_csv, check_times as _check_times, imu_to_camera,
                   read_camera_json, read_csv_columns as _read_csv, read_csv_table, read_imu_csv, read_truth_csv,
                   rotation_deg)


def open_folder(path: Path, cam_json: Path | None = None, keep_nan: bool = False) -> Footage:
    """The footage folder at ``path`` (frames.csv, frames/, camera.json or ``cam_json``, imu.csv, truth.csv).

    keep_nan: open what ``lobula info`` reports rather than stops at: IMU and truth logs with NaN or empty
    values (counted per column), and an IMU that cannot be one (said in the notes).
    """
    cam_json = cam_json or path / "camera.json"
    camera = read_camera_json(cam_json)
    fr, lines = read_csv_table(path / "frames.csv", ("frame", "time_s", "file"))
    _check_times(path / "frames.csv", fr["time_s"], lines=lines)
    files = [path / str(f) for f in fr["file"]]
    missing = [f for f in files if not f.exists()]
    if missing:
        raise FootageError(f"{path / 'frames.csv'}: names {len(missing)} missing frame file(s), first "
                           f"{missing[0].relative_to(path)}; restore them or drop their rows")
    imu = None
    imu_path = path / "imu.csv"
    r = imu_to_camera(cam_json)
    notes = []
    if imu_path.exists():
        imu = read_imu_csv(imu_path, r, keep_nan=keep_nan)
        check_imu_csv(imu, fr["time_s"], notes, keep_nan)
        if r is not None:
            notes.append(f"IMU rotated into the camera frame by {cam_json.name}'s imu_to_camera "
                         f"({rotation_deg(r):.2f} deg)")
    truth, truth_nan = read_truth_csv(path / "truth.csv", keep_nan) if (path / "truth.csv").exists() else (None, {})
    return Footage(path, camera, fr["time_s"], files, imu, truth, kind="folder", notes=notes, imu_to_camera=r,
                   camera_file_imu_rotation=r, truth_nan_counts=truth_nan)


def open_d435i_sample(path: Path, cam_json: Path | None = None) -> Footage:
    """The D435i sample folder at ``path`` (frames/ named by raw frame number, velocity.csv; no IMU), its
    intrinsics from ``cam_json`` or the camera.json in it."""
    camera = read_camera_json(cam_json or path / "camera.json")
    vel = _read_csv(path / "velocity.csv", ("sample", "raw_frame", "time_s", "v_true_m_s"))
    _check_times(path / "velocity.csv", vel["time_s"])
    files = sorted((p for p in (path / "frames").iterdir() if re.fullmatch(r"\d+\.(png|jpg)", p.name)),
                   key=lambda p: int(p.stem))
    if not files:
        raise FootageError(f"{path / 'frames'}: no frames named by raw frame number (e.g. 0705.png)")
    raw = np.array([int(p.stem) for p in files])
    lookup = dict(zip(vel["raw_frame"].astype(int), vel["time_s"]))
    absent = [r for r in raw if r not in lookup]
    if absent:
        raise FootageError(f"{path / 'velocity.csv'}: no raw_frame {absent[0]} for frames/{files[0].name}")
    times = np.array([lookup[r] for r in raw])
    truth = {"time_s": vel["time_s"], "v_forward_m_s": vel["v_true_m_s"]}
    if "v_flivver_published_m_s" in vel:
        truth["v_published_m_s"] = vel["v_flivver_published_m_s"]
    note = ("D435i sample: no IMU recorded; forward acceleration derived from the ground-truth "
            "velocity (Gaussian-smoothed derivative); frame times from velocity.csv with "
            "raw_frame = sample + 3 (the authors' alignment, uncertain by about 3 frames)")
    return Footage(path, camera, times, files, None, truth, kind="d435i-sample", notes=[note])
