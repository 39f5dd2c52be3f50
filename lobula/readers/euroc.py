"""The ASL folder layout of the EuRoC MAV dataset (and TUM-VI and others that share it) as footage.

Layout read (``path`` is the sequence folder holding ``mav0/``, or ``mav0/`` itself)::

    mav0/cam0/data.csv          #timestamp [ns],filename
    mav0/cam0/data/<ns>.png     grey frames
    mav0/cam0/sensor.yaml       intrinsics [fu, fv, cu, cv], distortion_model, distortion_coefficients,
                                resolution, rate_hz, T_BS (the camera's pose in the body frame, 4×4)
    mav0/imu0/data.csv          timestamp [ns], w_RS_S_x..z [rad/s], a_RS_S_x..z [m/s²] (IMU frame S)
    mav0/imu0/sensor.yaml       T_BS of the IMU (identity in EuRoC: the IMU is the body frame)
    mav0/state_groundtruth_estimate0/data.csv   (optional) timestamp, p_RS_R, q_RS (w, x, y, z),
                                v_RS_R [m/s] (velocity in the world frame R), biases

Conventions, each also written into ``footage.notes``:

* **Times** are seconds from the first frame's time stamp (``Footage.time_origin_ns`` keeps it);
  IMU and truth on the same clock (the dataset's own, hardware-synchronised).
* **Undistortion**: radial-tangential (OpenCV's k1, k2, p1, p2) and equidistant (fisheye)
  models are removed with one ``cv2.initUndistortRectifyMap`` made at opening and one
  ``cv2.remap`` per frame, onto the same pinhole K ("same-k", default) or onto OpenCV's
  optimal new K with every output pixel valid ("optimal"); the camera reported is the
  one the frames are then in.
* **IMU** into the camera optical frame through the two T_BS: v_C = R_BCᵀ R_BS v_S
  (R_BC the rotation of cam0's T_BS, R_BS that of imu0's; in EuRoC v_C = R_BCᵀ v_B).
  The lever arm is ignored.
* **Truth** (when the ground-truth CSV is there): the body's world velocity v_R rotated
  into the body frame by the ground-truth orientation, then into the camera frame:
  v_C = R_BCᵀ R_RSᵀ v_R; its z component is ``v_forward_m_s``. The lever-arm term ω × r
  (r ≈ 7 cm in EuRoC) is ignored and said so.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from lobula.camera import PinholeCamera

from .core import IMU, Footage, FootageError, check_row_lengths, check_times, read_frame, row_of

EUROC_KIND = "euroc"
IMU_MARGIN_S = 1.0   # IMU kept this far before the first and after the last frame


def _read_yaml(path: Path) -> dict:
    """An ASL sensor.yaml (OpenCV-flavoured: a '%YAML:1.0' first line that PyYAML refuses)."""
    import yaml

    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FootageError(f"{path}: not found; an ASL/EuRoC sensor folder needs its sensor.yaml") from None
    if text.startswith("%YAML"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise FootageError(f"{path}: not readable YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(d, dict):
        raise FootageError(f"{path}: empty or not a YAML mapping")
    return d


def _t_bs(d: dict, path: Path) -> np.ndarray:
    """The 4×4 T_BS of a sensor.yaml (identity when absent)."""
    if "T_BS" not in d:
        return np.eye(4)
    t = d["T_BS"]
    data = t.get("data") if isinstance(t, dict) else t
    try:
        m = np.asarray(data, float).reshape(4, 4)
    except (TypeError, ValueError):
        raise FootageError(f"{path}: T_BS must be a 4x4 matrix (rows: 4, cols: 4, data: 16 numbers)") from None
    r = m[:3, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-3:
        raise FootageError(f"{path}: T_BS's rotation part is not a rotation")
    return m


def _ns_csv(path: Path, min_cols: int, what: str) -> tuple[np.ndarray, list[list[str]], np.ndarray]:
    """(timestamps ns int64, remaining columns as strings, each row's line number in the file) of an ASL CSV
    ('#' header line)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FootageError(f"{path}: not found; the ASL layout needs {what}") from None
    except UnicodeDecodeError:
        raise FootageError(f"{path}: not a text CSV") from None
    numbered = [(k, ln.strip()) for k, ln in enumerate(text.splitlines(), 1)]
    numbered = [(k, ln) for k, ln in numbered if ln and not ln.startswith("#")]
    if not numbered:
        raise FootageError(f"{path}: no rows")
    lines = np.array([k for k, _ in numbered])
    rows = [ln.split(",") for _, ln in numbered]
    check_row_lengths(path, rows, lines, min_cols)
    try:
        ns = np.array([int(r[0]) for r in rows], np.int64)
    except ValueError:
        raise FootageError(f"{path}: the first column must be integer time stamps in ns") from None
    return ns, [r[1:] for r in rows], lines


def _floats(path: Path, cols: list[list[str]], n: int, lines: np.ndarray) -> np.ndarray:
    """The first ``n`` of each row's ``cols`` as floats (rows, n); a FootageError names the file and the first
    bad row by its line number (``lines``, each row's)."""
    try:
        v = np.array([[float(x) for x in r[:n]] for r in cols])
    except ValueError:
        raise FootageError(f"{path}: non-numeric values; every column after the time stamp must be a number") from None
    if not np.all(np.isfinite(v)):
        row = row_of(lines, int(np.flatnonzero(~np.isfinite(v).all(1))[0]))
        raise FootageError(f"{path}: NaN or infinite values (first at row {row}); repair or remove those rows")
    return v


def _quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions (w, x, y, z) -> (n, 3, 3) rotation matrices."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)


class EurocFootage(Footage):
    """EuRoC/ASL footage: frames are undistorted with a map made once at opening.

    maps: OpenCV's remap maps (x, y), each (H, W) float32 px, or None (frames used as read);
    time_origin_ns: the first frame's time stamp (ns), which ``times`` (s) count from.
    """

    def __init__(self, *args, maps=None, time_origin_ns: int = 0, **kwargs):
        super().__init__(*args, **kwargs)
        self._maps = maps
        self.time_origin_ns = time_origin_ns

    def decode(self, i: int) -> np.ndarray:
        """Frame i as grey float32 (H, W), undistorted; FootageError if its size is not sensor.yaml's."""
        img = read_frame(self.files[i])
        raw_size = (self.distortion or {}).get("raw_size")
        want = tuple(raw_size) if raw_size else (self.camera.width, self.camera.height)
        if (img.shape[1], img.shape[0]) != want:
            raise FootageError(f"{self.files[i]}: image is {img.shape[1]}x{img.shape[0]}, sensor.yaml says "
                               f"{want[0]}x{want[1]}")
        if self._maps is not None:
            img = cv2.remap(img, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return img

    def depth_map(self, index: int) -> np.ndarray | None:
        """None: the ASL layout has no depth maps."""
        return None


def find_mav0(path: Path) -> Path:
    """The ``mav0/`` folder of an ASL/EuRoC sequence at ``path`` (the sequence folder, or ``mav0/`` itself)."""
    path = Path(path)
    if (path / "mav0").is_dir():
        return path / "mav0"
    if (path / "cam0").is_dir():
        return path
    raise FootageError(f"{path}: not an ASL/EuRoC folder (no mav0/ or cam0/)")


def open_euroc(path: str | Path, camera: str = "cam0", imu: str = "imu0", require_imu: bool = True,
               undistort: str = "same-k", intrinsics: PinholeCamera | None = None) -> EurocFootage:
    """Open an ASL/EuRoC sequence folder as footage (see the module doc for the conventions).

    path: the sequence folder holding ``mav0/``, or ``mav0/`` itself; camera, imu: the sensor
    folders to read; require_imu: stop when there is no IMU (False: ``imu=None``); undistort:
    "same-k", "optimal" or "none" (module doc).
    intrinsics: the raw camera's size, focal lengths, principal point and rate to use instead of
    sensor.yaml's (``--camera``); its distortion model and coefficients still apply.
    """
    path = Path(path)
    mav = find_mav0(path)
    cam_dir, imu_dir = mav / camera, mav / imu
    if undistort not in ("same-k", "optimal", "none"):
        raise ValueError(f"unknown undistort {undistort!r}; choose same-k, optimal or none")
    if not (cam_dir / "data.csv").exists():
        raise FootageError(f"{cam_dir / 'data.csv'}: not found; an EuRoC folder needs {camera}/data.csv "
                           f"(#timestamp [ns],filename)")
    fu, fv, cu, cv, w, h, model, coeffs, rate, t_bc = _camera_yaml(cam_dir, intrinsics)

    # ---- frames
    ns, cols, lines = _ns_csv(cam_dir / "data.csv", 2, f"{camera}/data.csv")
    files = [cam_dir / "data" / c[0].strip() for c in cols]
    missing = [f for f in files if not f.exists()]
    if missing:
        raise FootageError(f"{cam_dir / 'data.csv'}: names {len(missing)} missing frame file(s), first "
                           f"data/{missing[0].name}; restore them or drop their rows")
    origin = int(ns[0])
    times = (ns - origin) / 1e9
    check_times(cam_dir / "data.csv", times, "timestamp", lines)
    if rate <= 0:
        rate = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else 20.0
    notes = [f"EuRoC/ASL: {len(files)} frames from {camera} ({w}x{h}), times from data.csv relative to "
             f"{origin} ns"]

    k = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
    maps, new_k, distortion = _undistortion(k, model, coeffs, undistort, w, h, notes)
    camera_model = PinholeCamera(width=w, height=h, fx=float(new_k[0, 0]), fy=float(new_k[1, 1]),
                                 cx=float(new_k[0, 2]), cy=float(new_k[1, 2]), frame_rate_hz=rate)

    streams = [dict(sensor=camera, type="camera", messages=len(files), rate_hz=rate)]
    imu_obj, r_ci = _euroc_imu(imu_dir, camera, imu, require_imu, t_bc, origin, times, notes, streams)
    truth = _euroc_truth(mav, t_bc, origin, notes, streams)

    return EurocFootage(path, camera_model, times, files, imu_obj, truth, kind=EUROC_KIND, notes=notes,
                        distortion=distortion, imu_to_camera=r_ci, streams=streams, maps=maps,
                        time_origin_ns=origin)


def _camera_yaml(cam_dir: Path, intrinsics: PinholeCamera | None):
    """(fu, fv, cu, cv px, width, height px, distortion model, coefficients, rate Hz (0: not given),
    T_BC (4, 4)) from the camera's sensor.yaml, size, focal lengths, principal point and rate
    replaced by ``intrinsics`` where given."""
    sy = _read_yaml(cam_dir / "sensor.yaml")
    try:
        fu, fv, cu, cv = (float(x) for x in sy["intrinsics"])
        w, h = (int(x) for x in sy["resolution"])
    except (KeyError, TypeError, ValueError):
        raise FootageError(f"{cam_dir / 'sensor.yaml'}: needs intrinsics [fu, fv, cu, cv] and resolution "
                           f"[width, height]") from None
    model = str(sy.get("distortion_model", "none"))
    coeffs = np.asarray(sy.get("distortion_coefficients", []) or [], float)
    rate = float(sy.get("rate_hz", 0) or 0)
    if intrinsics is not None:
        c = intrinsics
        fu, fv, cu, cv, w, h, rate = c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.frame_rate_hz
    elif min(fu, fv) <= 0 or min(w, h) <= 0:
        raise FootageError(f"{cam_dir / 'sensor.yaml'}: intrinsics {[fu, fv, cu, cv]} and resolution {[w, h]} must "
                           f"have positive focal lengths and size; repair it, or give them with --camera FILE")
    t_bc = _t_bs(sy, cam_dir / "sensor.yaml")
    return fu, fv, cu, cv, w, h, model, coeffs, rate, t_bc


def _undistortion(k: np.ndarray, model: str, coeffs: np.ndarray, undistort: str, w: int, h: int, notes: list):
    """(remap maps or None, the K (3, 3) the frames are then in, distortion dict or None) for the raw
    camera matrix ``k`` (3, 3) and a ``w``×``h`` px image; a note appended where there is distortion."""
    maps, new_k = None, k
    distortion = None
    if model in ("radial-tangential", "radtan", "plumb_bob", "equidistant") and np.any(coeffs != 0) \
            and undistort != "none":
        if model == "equidistant":
            d = coeffs[:4].reshape(4, 1)
            if undistort == "optimal":
                new_k = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(k, d, (w, h), np.eye(3), balance=0.0)
            maps = cv2.fisheye.initUndistortRectifyMap(k, d, np.eye(3), new_k, (w, h), cv2.CV_32FC1)
        else:
            d = np.zeros(5)
            d[:min(len(coeffs), 5)] = coeffs[:5]
            if undistort == "optimal":
                new_k, _ = cv2.getOptimalNewCameraMatrix(k, d, (w, h), 0.0, (w, h))
            maps = cv2.initUndistortRectifyMap(k, d, None, new_k, (w, h), cv2.CV_32FC1)
        distortion = dict(model=model, coeffs=coeffs.tolist(), removed=True, target_k=undistort,
                          new_k=np.round(new_k, 4).tolist(), raw_k=k.tolist(), raw_size=[w, h])
        notes.append(f"lens distortion ({model}, {np.round(coeffs, 6).tolist()}) removed with OpenCV "
                     f"(one map, remap per frame) onto {'the same pinhole K' if undistort == 'same-k' else 'the optimal new K'}: "
                     f"fx {new_k[0, 0]:.3f}, fy {new_k[1, 1]:.3f}, cx {new_k[0, 2]:.3f}, cy {new_k[1, 2]:.3f}")
    elif np.any(coeffs != 0):
        distortion = dict(model=model, coeffs=coeffs.tolist(), removed=False, raw_size=[w, h])
        notes.append(f"lens distortion ({model}) NOT removed ({'undistort=none' if undistort == 'none' else 'unknown model'})")
    return maps, new_k, distortion


def _euroc_imu(imu_dir: Path, camera: str, imu: str, require_imu: bool, t_bc: np.ndarray, origin: int,
               times: np.ndarray, notes: list, streams: list):
    """(IMU or None, R_CI (3, 3) or None): the IMU around the frames (``times`` (n,) s after ``origin`` ns)
    into the camera frame, v_C = R_BCᵀ R_BS v_S; notes and streams appended."""
    imu_obj, r_ci = None, None
    if (imu_dir / "data.csv").exists():
        t_bs = _t_bs(_read_yaml(imu_dir / "sensor.yaml"), imu_dir / "sensor.yaml") \
            if (imu_dir / "sensor.yaml").exists() else np.eye(4)
        ins, icols, lines = _ns_csv(imu_dir / "data.csv", 7, f"{imu}/data.csv")
        v = _floats(imu_dir / "data.csv", icols, 6, lines)
        t_imu = (ins - origin) / 1e9
        check_times(imu_dir / "data.csv", t_imu, "timestamp", lines)
        # Only the IMU around the frames: a folder cut from a longer sequence (as the shared
        # one is) keeps the whole IMU log, and statistics over it (gyro bias) would mix in
        # motion the frames never saw.
        keep = (t_imu >= times[0] - IMU_MARGIN_S) & (t_imu <= times[-1] + IMU_MARGIN_S)
        if keep.sum() < 2:
            raise FootageError(f"{imu_dir / 'data.csv'}: no IMU samples within {IMU_MARGIN_S} s of the frames "
                               f"({times[0]:.2f}..{times[-1]:.2f} s after {origin} ns); the time stamps do not match")
        if not keep.all():
            notes.append(f"IMU samples more than {IMU_MARGIN_S} s outside the frames' span left out "
                         f"({int((~keep).sum())} of {len(keep)})")
        t_imu, v = t_imu[keep], v[keep]
        r_ci = t_bc[:3, :3].T @ t_bs[:3, :3]
        gyro, acc = v[:, :3] @ r_ci.T, v[:, 3:6] @ r_ci.T
        imu_obj = IMU(t_imu, acc, gyro, source=str(imu_dir / "data.csv"))
        streams.append(dict(sensor=imu, type="imu", messages=len(t_imu),
                            rate_hz=round((len(t_imu) - 1) / max(t_imu[-1] - t_imu[0], 1e-9), 3)))
        notes.append(f"IMU {imu} into the {camera} optical frame through the T_BS of both (v_C = R_BCᵀ R_BS v_S); "
                     f"lever arm ignored")
    elif require_imu:
        raise FootageError(f"{imu_dir / 'data.csv'}: missing; velocity needs the accelerometer. Give the "
                           f"sequence with its {imu}/ folder (timestamp, w_RS_S_x..z, a_RS_S_x..z)")
    else:
        notes.append(f"no {imu}/data.csv: no IMU")
    return imu_obj, r_ci


def _euroc_truth(mav: Path, t_bc: np.ndarray, origin: int, notes: list, streams: list) -> dict | None:
    """The ground truth's velocity in the camera frame (m/s; times s after ``origin`` ns), or None;
    notes and streams appended."""
    truth = None
    gt = mav / "state_groundtruth_estimate0" / "data.csv"
    if gt.exists():
        gns, gcols, lines = _ns_csv(gt, 11, "state_groundtruth_estimate0/data.csv")
        g = _floats(gt, gcols, 10, lines)
        r_rs = _quat_wxyz_to_matrix(g[:, 3:7])
        v_body = np.einsum("nji,nj->ni", r_rs, g[:, 7:10])       # R_RSᵀ v_R
        v_cam = v_body @ t_bc[:3, :3]                               # R_BCᵀ v_B, row-wise
        t_gt = (gns - origin) / 1e9
        check_times(gt, t_gt, "timestamp", lines)
        truth = {"time_s": t_gt, "v_forward_m_s": v_cam[:, 2], "v_cam_x_m_s": v_cam[:, 0],
                 "v_cam_y_m_s": v_cam[:, 1]}
        streams.append(dict(sensor="state_groundtruth_estimate0", type="truth", messages=len(t_gt)))
        notes.append("truth: state_groundtruth_estimate0 velocity rotated into the camera frame "
                     "(v_C = R_BCᵀ R_RSᵀ v_R); lever arm ignored")
    elif (mav / "state_groundtruth_estimate0").is_dir():
        notes.append("state_groundtruth_estimate0/ has no data.csv: no truth")
    return truth
