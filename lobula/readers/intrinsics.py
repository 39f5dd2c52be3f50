"""Camera calibrations as the calibration tools write them, for ``--camera FILE``.

Besides the project's own camera.json (width, height, fx, fy, cx, cy, frame_rate_hz, optional "distortion"
and "imu_to_camera"), ``--camera`` takes:

* **OpenCV FileStorage** files (YAML with ``%YAML:1.0``, XML, or JSON) as OpenCV's calibration samples
  write them: ``camera_matrix`` (or ``K``, ``cameraMatrix``), ``distortion_coefficients`` (or ``D``,
  ``dist_coeffs``, ``distCoeffs``), ``image_width``/``image_height``; a ``distortion_model`` (``fisheye``,
  ``equidistant``, ``plumb_bob``, ``radtan``) or a true ``fisheye_model`` says the lens model, else the
  coefficients are OpenCV's pinhole (k1, k2, p1, p2[, k3]);
* **ROS camera_info YAML** (``camera_calibration``'s output: ``image_width``, ``camera_matrix: {data}``,
  ``distortion_model``, ``distortion_coefficients: {data}``);
* **Kalibr camchains** (``camchain-*.yaml``): ``cam0``'s pinhole intrinsics, its ``radtan`` or
  ``equidistant`` distortion and resolution, the IMU's rotation into the camera from ``T_cam_imu`` and
  the clock from ``timeshift_cam_imu`` (t_imu = t_cam + shift);
* **Gyroflow lens profiles** (JSON, ``fisheye_params``: OpenCV fisheye camera matrix and 4 coefficients
  at ``calib_dimension``), scaled to the footage's resolution where its aspect ratio is the same.

Each is turned into a camera.json (:func:`camera_json_of`) that every reader takes as it takes the
project's own.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .core import FootageError

#: the keys OpenCV's calibration samples and tools use for each quantity, first found wins
_K_KEYS = ("camera_matrix", "cameraMatrix", "K", "Camera_Matrix", "intrinsic_matrix", "intrinsics")
_D_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "Distortion_Coefficients",
           "distortion")
_W_KEYS = ("image_width", "width", "imageWidth", "image_Width")
_H_KEYS = ("image_height", "height", "imageHeight", "image_Height")
_FISHEYE_MODELS = ("fisheye", "equidistant", "kannala-brandt", "kb4")
_PINHOLE_MODELS = ("plumb_bob", "radtan", "radial-tangential", "pinhole")


@dataclass
class Intrinsics:
    """A calibration read from any format: pixels (width, height, fx, fy, cx, cy), the lens
    ({"model", "coeffs"} or None), the IMU's rotation into the camera (3, 3) or None, the IMU's clock
    offset onto the camera's (s, added to the IMU's times) or None, the frame rate (Hz) or None, and the
    format's name as a sentence takes it ("a Kalibr camchain"), and a rolling shutter's readout (s, first row to
    last) or None."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: dict | None = None
    imu_to_camera: np.ndarray | None = None
    imu_clock_offset_s: float | None = None
    frame_rate_hz: float | None = None
    format: str = "camera.json"
    notes: list = field(default_factory=list)
    rolling_shutter_s: float | None = None

    def scaled_to(self, width: int, height: int, path: Path) -> "Intrinsics":
        """The same lens at another resolution of the same aspect ratio (pixels scale, coefficients do not);
        FootageError naming ``path`` where the aspect ratio differs."""
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        if abs(sx / sy - 1.0) > 0.01:
            raise FootageError(f"{path}: calibrated at {self.width}x{self.height}, the footage is {width}x{height}, "
                               f"another aspect ratio (a crop): give a calibration of this resolution")
        out = Intrinsics(width, height, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                         (self.cy + 0.5) * sy - 0.5, self.distortion, self.imu_to_camera, self.imu_clock_offset_s,
                         self.frame_rate_hz, self.format, list(self.notes), self.rolling_shutter_s)
        out.notes.append(f"calibrated at {self.width}x{self.height}, scaled by {sx:.4g} to {width}x{height}")
        return out


def _lens(model: str, coeffs, path: Path) -> dict | None:
    """{"model", "coeffs"} of a lens model name and its coefficients; None for a lens without distortion."""
    c = [float(x) for x in np.asarray(coeffs, float).ravel()]
    m = str(model).lower()
    if m in _FISHEYE_MODELS:
        if len(c) != 4:
            raise FootageError(f"{path}: a fisheye (equidistant) lens takes 4 coefficients k1..k4, got {len(c)}")
        return dict(model="kannala-brandt", coeffs=c)
    if m not in _PINHOLE_MODELS:
        raise FootageError(f"{path}: lens model {model!r} is not supported; give a pinhole (radial-tangential) or "
                           f"fisheye (equidistant) calibration")
    if len(c) > 5 and any(c[5:]):
        raise FootageError(f"{path}: {len(c)} distortion coefficients (OpenCV's rational or thin-prism model) are "
                           f"not supported; calibrate with k1, k2, p1, p2[, k3] only")
    c = c[:5]
    if len(c) not in (4, 5):
        raise FootageError(f"{path}: radial-tangential distortion takes k1, k2, p1, p2[, k3], got {len(c)} numbers")
    return None if not any(c) else dict(model="radtan", coeffs=c)


def _matrix(k, path: Path) -> tuple[float, float, float, float]:
    k = np.asarray(k, float)
    if k.size != 9 or not np.all(np.isfinite(k)):
        raise FootageError(f"{path}: the camera matrix must be 3x3 finite numbers, got {k.size} values")
    k = k.reshape(3, 3)
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise FootageError(f"{path}: the camera matrix's focal lengths must be > 0, got fx {k[0, 0]:g}, fy {k[1, 1]:g}")
    return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])


def _size(w, h, path: Path, where: str) -> tuple[int, int]:
    try:
        w, h = int(w), int(h)
    except (TypeError, ValueError):
        raise FootageError(f"{path}: no image size ({where}); the calibration must say the resolution it was made "
                           f"at") from None
    if w <= 0 or h <= 0:
        raise FootageError(f"{path}: the image size must be > 0, got {w}x{h}")
    return w, h


def _from_opencv(path: Path) -> Intrinsics:
    """An OpenCV FileStorage file (YAML, XML or JSON), read with cv2.FileStorage."""
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise FootageError(f"{path}: OpenCV cannot read it as a calibration file ({str(exc).strip()[:120]})") from None
    try:
        root = fs.root()

        def get(keys):
            for k in keys:
                node = fs.getNode(k)
                if not node.empty():
                    if node.isString():
                        return node.string()
                    if node.isInt() or node.isReal():
                        return node.real()
                    m = node.mat()
                    if m is not None:
                        return m
                    if node.isSeq():
                        return [node.at(i).real() for i in range(node.size())]
            return None

        k, d, w, h = get(_K_KEYS), get(_D_KEYS), get(_W_KEYS), get(_H_KEYS)
        model, fisheye = get(("distortion_model", "model", "camera_model")), get(("fisheye_model", "fisheye"))
        keys = root.keys() if root.isMap() else []
    finally:
        fs.release()
    if k is None:
        raise FootageError(f"{path}: no camera matrix ({', '.join(_K_KEYS)}) among its keys {list(keys)}")
    fx, fy, cx, cy = _matrix(k, path)
    w, h = _size(w, h, path, f"{_W_KEYS[0]}, {_H_KEYS[0]}")
    if isinstance(model, str):
        name = model
    else:
        name = "fisheye" if fisheye not in (None, 0, 0.0, "0", "false", "False") else "plumb_bob"
    lens = None if d is None else _lens(name, d, path)
    return Intrinsics(w, h, fx, fy, cx, cy, lens, format="an OpenCV FileStorage file")


def _from_ros(d: dict, path: Path) -> Intrinsics:
    """A ROS camera_info YAML (camera_calibration's)."""
    k = d["camera_matrix"]["data"] if isinstance(d.get("camera_matrix"), dict) else d.get("camera_matrix")
    fx, fy, cx, cy = _matrix(k, path)
    w, h = _size(d.get("image_width"), d.get("image_height"), path, "image_width, image_height")
    coeffs = d.get("distortion_coefficients")
    coeffs = coeffs.get("data") if isinstance(coeffs, dict) else coeffs
    lens = None if coeffs is None else _lens(d.get("distortion_model", "plumb_bob"), coeffs, path)
    return Intrinsics(w, h, fx, fy, cx, cy, lens, format="a ROS camera_info file")


def _from_kalibr(d: dict, path: Path) -> Intrinsics:
    """cam0 of a Kalibr camchain: pinhole intrinsics, distortion, resolution, T_cam_imu, timeshift_cam_imu."""
    cams = sorted(k for k in d if k.startswith("cam") and isinstance(d[k], dict))
    cam = d[cams[0]]
    model = str(cam.get("camera_model", "pinhole")).lower()
    if model != "pinhole":
        raise FootageError(f"{path}: Kalibr camera model {model!r} is not supported; calibrate with pinhole-radtan "
                           f"or pinhole-equidistant")
    try:
        fu, fv, pu, pv = (float(x) for x in cam["intrinsics"])
    except (KeyError, TypeError, ValueError):
        raise FootageError(f"{path}: {cams[0]}'s intrinsics must be [fu, fv, pu, pv]") from None
    w, h = _size(*(list(cam.get("resolution") or [None, None]) + [None, None])[:2], path, f"{cams[0]}.resolution")
    lens = _lens(cam.get("distortion_model", "radtan"), cam.get("distortion_coeffs", [0, 0, 0, 0]), path)
    out = Intrinsics(w, h, fu, fv, pu, pv, lens, format="a Kalibr camchain")
    if len(cams) > 1:
        out.notes.append(f"{cams[0]} of the {len(cams)} cameras in the camchain")
    t = cam.get("T_cam_imu")
    if t is not None:
        t = np.asarray(t, float)
        if t.shape != (4, 4) or not np.all(np.isfinite(t)):
            raise FootageError(f"{path}: {cams[0]}.T_cam_imu must be a 4x4 matrix of numbers")
        r = t[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-3) or np.linalg.det(r) < 0:
            raise FootageError(f"{path}: {cams[0]}.T_cam_imu's rotation is not a rotation matrix")
        out.imu_to_camera = r
    if cam.get("timeshift_cam_imu") is not None:
        out.imu_clock_offset_s = -float(cam["timeshift_cam_imu"])  # t_imu = t_cam + shift
    return out


def _from_gyroflow(d: dict, path: Path) -> Intrinsics:
    """A Gyroflow lens profile: the OpenCV fisheye model at calib_dimension."""
    fp = d.get("fisheye_params") or {}
    fx, fy, cx, cy = _matrix(fp.get("camera_matrix"), path)
    dim = d.get("calib_dimension") or {}
    w, h = _size(dim.get("w"), dim.get("h"), path, "calib_dimension")
    lens = _lens("fisheye", fp.get("distortion_coeffs") or [], path)
    name = " ".join(str(d[k]) for k in ("camera_brand", "camera_model", "lens_model") if d.get(k))
    out = Intrinsics(w, h, fx, fy, cx, cy, lens, frame_rate_hz=d.get("fps") or None, format="a Gyroflow lens profile")
    if name:
        out.notes.append(f"profile of {name}")
    readout = d.get("frame_readout_time")
    if isinstance(readout, (int, float)) and not isinstance(readout, bool) and readout > 0:
        direction = d.get("frame_readout_direction") or "TopToBottom"
        if direction == "TopToBottom":
            out.rolling_shutter_s = float(readout) / 1e3
            out.notes.append(f"rolling shutter: {readout:g} ms readout (frame_readout_time)")
        else:
            out.notes.append(f"its rolling shutter reads {direction}, which is not modelled (top to bottom is): "
                             f"treated as a global shutter")
    if d.get("input_horizontal_stretch") not in (None, 1, 1.0):
        raise FootageError(f"{path}: a lens profile for horizontally stretched footage (input_horizontal_stretch "
                           f"{d['input_horizontal_stretch']}) is not supported")
    return out


def read_intrinsics(path: str | Path) -> Intrinsics:
    """The calibration in ``path``, any format of the module doc; one FootageError naming the file otherwise."""
    from .core import read_camera_json

    path = Path(path)
    if not path.is_file():
        raise FootageError(f"{path}: not found; give a camera calibration file (camera.json, OpenCV YAML/XML/JSON, "
                           f"ROS camera_info, Kalibr camchain or a Gyroflow lens profile)")
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise FootageError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    head = text.lstrip()[:200]
    if head.startswith("%YAML") or head.startswith("<?xml") or head.startswith("<opencv_storage"):
        return _from_opencv(path)
    if head.startswith("{"):
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise FootageError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
        if isinstance(d, dict) and "fisheye_params" in d:
            return _from_gyroflow(d, path)
        if isinstance(d, dict) and any(k in d for k in _K_KEYS):
            return _from_opencv(path)
        cam = read_camera_json(path)  # the project's own: its errors name the field
        return Intrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, frame_rate_hz=cam.frame_rate_hz,
                          format="camera.json", rolling_shutter_s=cam.rolling_shutter_s or None)
    import yaml

    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise FootageError(f"{path}: not a calibration file this reads (not JSON, OpenCV FileStorage or YAML: "
                           f"{str(exc).splitlines()[0]})") from None
    if isinstance(d, dict) and any(k.startswith("cam") and isinstance(v, dict) and "intrinsics" in v
                                   for k, v in d.items() if isinstance(k, str)):
        return _from_kalibr(d, path)
    if isinstance(d, dict) and "camera_matrix" in d and "image_width" in d:
        return _from_ros(d, path)
    raise FootageError(f"{path}: not a calibration file this reads; give a camera.json, an OpenCV FileStorage "
                       f"YAML/XML/JSON, a ROS camera_info YAML, a Kalibr camchain or a Gyroflow lens profile")


def camera_json_of(intr: Intrinsics, frame_rate_hz: float) -> dict:
    """The camera.json (a dict) of ``intr``, with ``frame_rate_hz`` where the calibration states none."""
    d = dict(width=intr.width, height=intr.height, fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy,
             frame_rate_hz=float(intr.frame_rate_hz or frame_rate_hz))
    if intr.distortion is not None:
        d["distortion"] = intr.distortion
    if intr.imu_to_camera is not None:
        d["imu_to_camera"] = np.asarray(intr.imu_to_camera, float).tolist()
    if intr.rolling_shutter_s:
        d["rolling_shutter_s"] = float(intr.rolling_shutter_s)
    return d
