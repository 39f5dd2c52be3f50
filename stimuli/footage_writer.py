"""Writing synthetic footage: a rendered scene into the footage-folder layout, atomically.

:func:`write_footage` writes what :mod:`lobula.readers.folder` reads (camera.json, frames/,
frames.csv, imu.csv, truth.csv, depth/); :func:`atomic_folder` is the hidden temporary every
writer of a folder here fills and renames into place, and :func:`remove_stale` clears what a
killed run left behind (the command line's outputs use it too).
"""
from __future__ import annotations

import csv
import errno
import json
import os
import re
import shutil
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np


#: when this run started (the first import of this module, before any output is begun): what a
#: killed run left is older than this
RUN_START = time.time()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process (EPERM): alive
        return True
    return True


def remove_stale(folder: str | Path, prefix: str) -> list[Path]:
    """Remove what a killed run left in ``folder``: the files and folders named ``prefix``, a process id
    and (optionally) more, whose process is gone and which were last changed before this run started.

    The writers here name their temporaries so (``.<name>.lobula-tmp-<pid>-…``,
    ``.<name>.partial-<pid>``); a run stopped by SIGKILL or a power cut cannot remove its own, so
    the next run that writes the same output does. A temporary of a run still going (its process
    alive) or begun after this one is left alone. Returns what was removed.
    """
    pattern = re.compile(re.escape(prefix) + r"(\d+)(?:\D.*)?$", re.S)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for e in entries:
        m = pattern.match(e.name)
        if not m:
            continue
        pid = int(m.group(1))
        try:
            if e.stat(follow_symlinks=False).st_mtime >= RUN_START or (pid != os.getpid() and _alive(pid)):
                continue
            if e.is_dir(follow_symlinks=False):
                shutil.rmtree(e.path)
            else:
                os.unlink(e.path)
        except OSError:
            continue
        removed.append(Path(e.path))
    return removed



@contextmanager
def atomic_folder(folder: str | Path) -> Iterator[Path]:
    """A hidden sibling folder to write footage into, renamed onto ``folder`` when the block ends
    normally and removed when it raises, so an interrupted run leaves nothing that looks finished.
    ``folder`` must not exist or be empty (FileExistsError otherwise)."""
    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        raise FileExistsError(f"{folder}: exists and is not empty; choose a new folder or delete it")
    remove_stale(folder.parent, f".{folder.name}.partial-")
    tmp = folder.parent / f".{folder.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        yield tmp
        if folder.exists():
            folder.rmdir()
        tmp.rename(folder)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError) and exc.errno in _CANNOT_WRITE:
            # Named by the folder being written, not a file inside its hidden temporary (nor none at all,
            # as a failed write() reports it): the command line turns it into one line naming OUT.
            raise OSError(exc.errno, exc.strerror or str(exc), str(folder)) from None
        raise


#: errno values that say a write failed for want of space or permission
_CANNOT_WRITE = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EROFS, errno.EACCES, errno.EPERM,
                 errno.EFBIG}


def _no_space(folder: Path) -> bool:
    """Whether the file system holding ``folder`` has no space left for an ordinary user."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < 1 << 16


def write_footage(folder: str | Path, scene, imu: dict, times: np.ndarray, metadata: dict,
                  depth_every: int = 10, progress=None) -> Path:
    """Render ``scene`` at ``times`` into a footage folder, atomically.

    Everything is written to a hidden sibling folder that is renamed into place only
    when complete, so an interrupted run leaves no folder that looks finished.

    truth.csv: v_forward_m_s is the camera-frame z velocity (m/s), a_forward_m_s2 the world
    acceleration's camera-frame z component (m/s²), position_m the distance along the track or,
    in flight, along the path (m). A scene flying a :class:`stimuli.flight.FlightPlan` adds its
    saccades to scene.json: ``saccades`` ([[start_s, end_s], ...]) and ``saccade_amplitudes_deg``.
    """
    folder = Path(folder)
    flight = getattr(scene, "flight", None)
    if flight is not None:
        metadata = {**metadata, **flight.metadata()}
    with atomic_folder(folder) as tmp:
        (tmp / "frames").mkdir()
        (tmp / "depth").mkdir()
        cam = scene.camera
        (tmp / "camera.json").write_text(json.dumps(cam.to_dict(), indent=1))
        with open(tmp / "frames.csv", "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["frame", "time_s", "file"])
            for i, t in enumerate(times):
                name = f"frames/{i:06d}.png"
                if not cv2.imwrite(str(tmp / name), scene.render(float(t), i)):  # OpenCV reports a failed write so
                    raise OSError(errno.ENOSPC if _no_space(tmp) else errno.EIO, f"cannot write {name}", str(folder))
                if depth_every and i % depth_every == 0:
                    np.save(tmp / "depth" / f"{i:06d}.npy", scene.depth(float(t)))
                wr.writerow([i, f"{t:.6f}", name])
                if progress is not None:
                    progress(1)
        with open(tmp / "imu.csv", "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["time_s", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z"])
            for t, a, g in zip(imu["time_s"], imu["accel"], imu["gyro"]):
                wr.writerow([f"{t:.6f}", *(f"{x:.6f}" for x in a), *(f"{x:.7f}" for x in g)])
        vel = scene.camera_velocity(times)
        with open(tmp / "truth.csv", "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["time_s", "v_forward_m_s", "a_forward_m_s2", "position_m"])
            if flight is not None:  # the 3-D world acceleration in the camera frame, its z
                a_fwd = np.einsum("nji,nj->ni", scene.rotation(times), scene.world_acceleration(times))[:, 2]
            else:
                acc = scene.trajectory.acceleration(times)
                # Forward (optical-axis) acceleration: the track acceleration projected on z_cam.
                a_fwd = acc * np.einsum("nji,j->ni", scene.rotation(times), np.array([0, 0, 1.0]))[:, 2]
            for t, v, a, s in zip(times, vel[:, 2], a_fwd, scene.trajectory.position(times)):
                wr.writerow([f"{t:.6f}", f"{v:.6f}", f"{a:.6f}", f"{s:.6f}"])
        (tmp / "scene.json").write_text(json.dumps(metadata, indent=1, default=str))
    return folder
