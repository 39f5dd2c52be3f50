"""GoPro MP4s as the camera writes them: the video plus its GPMF telemetry track (``gpmd``).

A GoPro HERO5 and later (and the MAX in its single-lens "hero" mode) writes an MP4 with
H.264/HEVC video and a timed metadata track of sample type ``gpmd`` holding GPMF, GoPro's
key–length–value telemetry: accelerometer (ACCL, m/s²) and gyroscope (GYRO, rad/s) at about
200 Hz, GPS (GPS5, or GPS9 from the HERO11) at 10–18 Hz, and on newer models camera and image
orientation (CORI, IORI) and gravity (GRAV) once per frame. Camera settings (model, firmware,
electronic stabilisation, lens field of view) sit in a GPMF block in the MP4's ``udta`` box.

How the file is read:

* **container** — PyAV (FFmpeg) demultiplexes the ``gpmd`` track; each packet's presentation
  time and duration (the MP4 sample table, on the same clock as the video's frame times) give
  the time span its samples cover. The ``gpmd`` track and the ``udta`` settings are found by a
  walk over the MP4's box headers (:func:`~lobula.readers.mp4_index.read_mp4_index`).
* **GPMF** — GoPro's own parser, gpmf-parser, through its Python binding ``py-gpmf-parser``,
  decodes each packet: types, struct sizes, SCAL divisors and the axis order (ORIN → ORIO, or
  the calibration matrix MTRX), so ACCL and GYRO come out in GoPro's standard order Z, X, Y.
* **timing** — the n samples of a stream in a packet spanning [t_in, t_out) are spread evenly,
  t_k = t_in + k (t_out − t_in)/n (:func:`~lobula.readers.gopro_telemetry.packet_sample_times`), then moved earlier by the
  stream's TIMO offset where it has one.
* **axes** — GoPro's IMU axes (X, Y, Z of the gpmf-parser documentation: Z up out of the
  camera's top, Y out of its back, X to its left, right-handed) are rotated into the camera
  optical frame the pipeline uses (x right, y down, z forward): x = −X, y = −Z, z = −Y
  (:data:`~lobula.readers.gopro_telemetry.GOPRO_TO_CAMERA`). The signs hold on real clips (../shared/data/gopro_walking): the
  mean specific force leans back by the camera's downward pitch, which puts the focus of
  expansion above the image centre as the flow shows, and the gyro's yaw and pitch move the
  image left and down as they should (tests/test_gopro.py). Files without ORIN use the order
  GoPro documents for the model (:data:`~lobula.readers.gopro_telemetry.DEFAULT_ORIN`: HERO5 Z,X,Y; HERO6 Y,−X,Z; Fusion −Y,X,Z).
* **truth** — GPS 2D ground speed (Doppler) of the samples with a 2D or 3D fix, as
  ``truth["v_forward_m_s"]``: the camera's forward speed only when its optical axis points along
  the walk (otherwise speed × cos of the angle between them). Every output says its truth is GPS.
* **stabilisation** — HyperSmooth/EIS is read from the settings (EISE, EISA) and, where the file
  has IORI, from how far the image orientation departs from the camera body's. A stabilised clip with CORI and
  IORI has its IMU turned into the stabilised image's frame (:func:`image_frame`,
  :mod:`lobula.readers.image_orientation`); ``body_imu`` keeps the body's.

GoPro files carry no lens intrinsics (the lens is a wide-angle fisheye), so velocity needs a
camera.json: ``--camera FILE`` or ``CLIP.camera.json`` / ``camera.json`` beside the clip.

The parts, one module each: :mod:`lobula.readers.mp4_index` (the box index), :mod:`lobula.readers.gpmf`
(decoding a GPMF payload) and :mod:`lobula.readers.gopro_telemetry` (the streams over the whole file,
timed and in the camera frame). This module holds the footage (:func:`open_gopro`: GPS truth,
stabilisation, the telemetry summary) and re-exports the parts' public names.
"""
from __future__ import annotations

import json
import math

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .core import FootageError, IMU, imu_to_camera as camera_json_rotation, read_camera_json, rotation_deg
from .gopro_telemetry import (DEFAULT_ORIN, GOPRO_TO_CAMERA, GOPRO_XYZ_TO_CAMERA, STANDARD_ORDER, Stream,
                              axis_order_matrix, imu_axes_to_camera, packet_sample_times, read_telemetry)
from .gpmf import DATA_KEYS, GPMF_INSTALL_HINT, STICKY_KEYS, decode_gpmf, decode_settings
from .mp4_index import GPMF_SAMPLE_TYPE, Mp4Index, has_gpmf_track, read_mp4_index
from .video import VideoFootage, camera_file, container_times

if TYPE_CHECKING:
    from ..camera import PinholeCamera

#: The lowest GPS fix (GPSF, GPS9's fix field: 0 no lock, 2 2D, 3 3D) whose samples count as truth.
GPS_FIX_2D = 2

#: An image orientation (IORI) further than this from the body's (degrees) counts as stabilisation.
IORI_STABILISED_DEG = 0.5


# ----------------------------------------------------------------------------- GPS and stabilisation
def quaternion_angle_deg(q: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees) of quaternions q (n, 4) ordered w, x, y, z (any norm)."""
    q = np.asarray(q, float)
    w = np.abs(q[:, 0]) / np.maximum(np.linalg.norm(q, axis=1), 1e-12)
    return np.degrees(2.0 * np.arccos(np.clip(w, 0.0, 1.0)))


def gps_samples(streams: dict[str, Stream]) -> dict[str, np.ndarray] | None:
    """The GPS samples of GPS9 (preferred: per-sample fix and DOP) or GPS5 (the packet's GPSF/GPSP) in
    ``streams`` (:func:`~lobula.readers.gopro_telemetry.read_telemetry`'s): {time_s, lat_deg, lon_deg, alt_m,
    speed_2d_m_s, speed_3d_m_s, fix, dop: each (n,), in the units their names end in; source}; None without GPS."""
    s = streams.get("GPS9") or streams.get("GPS5")
    if s is None or s.data.shape[1] < 5:
        return None
    d = s.data
    if s.key == "GPS9" and d.shape[1] >= 9:
        fix, dop = d[:, 8], d[:, 7]
    else:
        fix, dop = s.per_packet_fix, s.per_packet_dop
    return dict(time_s=s.time_s, lat_deg=d[:, 0], lon_deg=d[:, 1], alt_m=d[:, 2], speed_2d_m_s=d[:, 3],
                speed_3d_m_s=d[:, 4], fix=fix, dop=dop, source=s.key)


def stabilisation(settings: dict, iori: np.ndarray | None = None) -> dict:
    """Electronic stabilisation (HyperSmooth/EIS) as the metadata tell it (``settings``: the camera settings,
    :func:`~lobula.readers.gpmf.decode_settings`; ``iori``: the image orientations (n, 4) w, x, y, z, or None):
    {electronic: True/False/None (unknown), setting: EISA text or None, source: where it was read,
    image_orientation_max_deg / _mean_deg: IORI's angle from the camera body where the file has IORI, imu_frame:
    "body" (the IMU as the telemetry holds it; "image" once :func:`open_gopro` has turned it into the stabilised
    image's frame)}."""
    out = dict(electronic=None, setting=None, source="none in the file", image_orientation_max_deg=None,
               image_orientation_mean_deg=None, imu_frame="body")
    eise, eisa = settings.get("EISE"), settings.get("EISA")
    if isinstance(eisa, str) and eisa:
        out["setting"] = eisa
    if isinstance(eise, str) and eise[:1] in ("Y", "N"):
        out["electronic"], out["source"] = eise[:1] == "Y", "camera settings (EISE/EISA)"
    elif out["setting"] is not None:
        out["electronic"], out["source"] = out["setting"].upper() not in ("N/A", "OFF", "N"), "camera settings (EISA)"
    if iori is not None and len(iori):
        ang = quaternion_angle_deg(iori[:, :4])
        out["image_orientation_max_deg"] = round(float(ang.max()), 3)
        out["image_orientation_mean_deg"] = round(float(ang.mean()), 3)
        if out["electronic"] is None:
            out["electronic"] = bool(ang.max() > IORI_STABILISED_DEG)
            out["source"] = "image orientation (IORI) against the camera body"
    return out


def stabilisation_notes(stab: dict) -> list[str]:
    """The note on :func:`stabilisation`'s finding ``stab``, where the image is stabilised electronically."""
    if not stab["electronic"]:
        return []
    if stab.get("imu_frame") == "image":
        return [f"electronic stabilisation on ({stab['setting'] or 'HyperSmooth'}; from {stab['source']}): the image "
                f"is warped against the body, and the IMU was turned to follow it"]
    return [f"electronic stabilisation on ({stab['setting'] or 'HyperSmooth'}; from {stab['source']}): the image is "
            f"warped against the gyro's frame, so image rotation is not the camera body's"]


# ----------------------------------------------------------------------------- footage
class GoProFootage(VideoFootage):
    """A GoPro MP4: frames decoded from the video, IMU and GPS truth from its GPMF track.

    Beside the :class:`~lobula.readers.core.Footage` fields: ``telemetry`` (a JSON-able summary:
    model, firmware, stabilisation, lens, streams), ``gps`` (every GPS sample, with or without a fix;
    :func:`gps_samples`) and ``orientation`` ({"CORI", "IORI", "GRAV": (time_s (n,), values)} where
    the file has them, in GoPro's own frame, unrotated); ``body_imu``: the IMU in the camera body's frame, as the
    telemetry holds it — ``imu`` is the same unless turned into the stabilised image's frame
    (:mod:`lobula.readers.image_orientation`). ``camera`` is None only where the footage
    was opened without intrinsics (``lobula info``). ``lens_guess``: where no camera file was given, the
    equidistant lens assumed (model, coeffs, diagonal_fov_deg, source, rel_std: the focal length's 1σ
    fraction), which :func:`lobula.readers.self_calibration.self_calibrate` measures against the gyro; None
    with a camera file.
    """

    telemetry: dict
    gps: dict | None
    orientation: dict
    body_imu: IMU | None
    nominal_fps: float
    lens_guess: dict | None

    def _index(self, t: float) -> int | None:
        """The frame whose time stamp is t (s); None for a picture after the frames kept (the video runs on
        past the telemetry's end)."""
        if len(self.times) and t > self.times[-1] + 1e-6:
            return None
        return super()._index(t)

    def provenance(self) -> dict:
        """The footage's provenance attrs plus the truth source, model, firmware and stabilisation."""
        out = super().provenance()
        stab = self.telemetry.get("stabilisation", {})
        out.update(truth_source=self.telemetry.get("truth_source", "none"),
                   gopro_model=self.telemetry.get("model") or "unknown",
                   gopro_firmware=self.telemetry.get("firmware") or "unknown",
                   electronic_stabilisation={True: "on", False: "off"}.get(stab.get("electronic"), "unknown")
                   + (f" ({stab['setting']})" if stab.get("setting") else "")
                   + f"; from {stab.get('source', 'none')}")
        if getattr(self, "calibration", None):
            out["camera_calibration"] = json.dumps(self.calibration)
        return out


def open_gopro(path: str | Path, require_imu: bool = True, camera_json: str | Path | None = None,
               require_camera: bool = True, image_orientation: bool = True) -> GoProFootage:
    """Open a GoPro MP4 as the camera wrote it (module doc): frames, IMU in the camera frame, GPS truth.

    path: the MP4. camera_json: intrinsics (``--camera FILE``); else ``CLIP.camera.json`` or ``camera.json`` beside
    the clip. Its optional imu_to_camera is applied after the GPMF axis mapping, as a correction in
    the camera frame. require_imu: FootageError when the telemetry has no accelerometer (False:
    ``imu=None``). require_camera: FootageError without a camera file (False: ``camera=None``,
    for ``lobula info``). image_orientation: where the image is stabilised electronically and the file has the
    camera's and the image's orientations (CORI, IORI), turn the IMU into the stabilised image's frame
    (:mod:`lobula.readers.image_orientation`; False: keep the body's). Every bad input is one FootageError
    naming the file and the fix.
    """
    path = Path(path)
    if not path.is_file():
        raise FootageError(f"{path}: not found; give the GoPro MP4 itself")
    index = read_mp4_index(path)
    streams, settings, (t0, t1, packets) = read_telemetry(path, index)
    times, w, h, fps, codec = container_times(path)
    if len(times) == 0:
        raise FootageError(f"{path}: no video frames could be read (empty or damaged MP4); copy the file again "
                           f"from the camera's card")
    model, firmware = str(settings.get("MINF") or ""), str(settings.get("FMWR") or "")
    cam_path = camera_file(path, camera_json)
    camera = None
    if cam_path is not None:
        camera = read_camera_json(cam_path)
        if (w, h) != (camera.width, camera.height):
            raise FootageError(f"{path}: video is {w}x{h} but {cam_path} says {camera.width}x{camera.height}; give "
                               f"the intrinsics of this resolution")
    lens_guess = None
    if cam_path is None and require_camera:
        # No calibration: an equidistant fisheye (what a GoPro's wide lenses are close to) whose diagonal sees
        # the field of view the file states, else a nominal one; its focal length is then measured against the
        # gyro where the footage allows (lobula.readers.self_calibration), and said either way.
        camera, lens_guess = lens_guess_from_settings(w, h, fps, settings)
    notes = [("" if model.upper().startswith("GOPRO") else "GoPro ") + (model or "camera")
             + (f" (firmware {firmware})" if firmware else "")
             + f": video {len(times)} frames ({w}x{h}, {codec}) with its GPMF telemetry track: {packets} packets "
             f"covering {t0:.3f}..{t1:.3f} s of the video's clock"]
    if times[-1] > t1 + 0.5 / max(fps, 1.0) and times[0] <= t1:
        # The last telemetry packet can end before the video (a clip cut or transcoded): those frames have no
        # IMU samples around them, so they are left out rather than refused with the whole clip.
        n_all, last = len(times), float(times[-1])
        times = times[times <= t1 + 0.5 / max(fps, 1.0)]
        notes.append(f"the telemetry ends at {t1:.3f} s, before the video's last {n_all - len(times)} frames "
                     f"(to {last:.3f} s): they are left out (no IMU samples around them)")
    if times[0] < t0 - 1e-6:
        notes.append(f"the telemetry covers {t0:.3f}..{t1:.3f} s and the frames {times[0]:.3f}..{times[-1]:.3f} s: "
                     f"frames before it have no IMU samples around them")
    imu, r_extra = _gopro_imu(path, streams, cam_path, require_imu, notes)
    body_imu = imu
    gps = gps_samples(streams)
    truth = gps_truth(gps, notes)
    orientation = {k: (streams[k].time_s, streams[k].data) for k in ("CORI", "IORI", "GRAV") if k in streams}
    stab = stabilisation(settings, orientation["IORI"][1] if "IORI" in orientation else None)
    if image_orientation and imu is not None and stab["electronic"]:
        imu = image_frame(imu, orientation, stab, notes)
    notes.extend(stabilisation_notes(stab))
    distortion = dict(model="GoPro wide-angle (fisheye) lens; the file gives no intrinsics or distortion, and the "
                            "pipeline treats the image as a pinhole camera's", removed=False)
    if settings.get("VFOV"):
        distortion["fov_mode"] = settings["VFOV"]
    if isinstance(settings.get("ZFOV"), float):
        distortion["diagonal_fov_deg"] = round(settings["ZFOV"], 3)
    stream_list = [dict(stream="video", codec=codec, frames=len(times), nominal_fps=round(fps, 3))]
    for k, s in sorted(streams.items()):
        entry = dict(stream=k, name=s.name, samples=int(len(s.time_s)), rate_hz=round(s.rate_hz or 0.0, 3),
                     units=s.units, axes=_axes_text(s) if s.order else None)
        stream_list.append({a: v for a, v in entry.items() if v not in (None, "")})
    telemetry = _telemetry_summary(model, firmware, packets, t0, t1, streams, settings, gps, truth, stab)
    footage = GoProFootage(path, camera, times, [], imu, truth, kind="gopro", notes=notes, distortion=distortion,
                           imu_to_camera=(GOPRO_XYZ_TO_CAMERA if r_extra is None else r_extra @ GOPRO_XYZ_TO_CAMERA)
                           if imu is not None else None, camera_file_imu_rotation=r_extra, streams=stream_list)
    footage.telemetry, footage.gps, footage.orientation, footage.nominal_fps = telemetry, gps, orientation, fps
    footage.body_imu = body_imu
    footage.lens_guess = lens_guess
    return footage


def _gopro_imu(path: Path, streams: dict[str, Stream], cam_path: Path | None, require_imu: bool,
               notes: list[str]) -> tuple[IMU | None, np.ndarray | None]:
    """The IMU of ACCL and GYRO (gyro interpolated onto the accelerometer's times where they differ), then
    rotated by the camera file's imu_to_camera where it has one: (IMU or None, that rotation (3, 3) or
    None). Appends what it did to ``notes``."""
    acc, gyr = streams.get("ACCL"), streams.get("GYRO")
    imu, r_extra = None, None
    if acc is None and require_imu:
        raise FootageError(f"{path}: the GPMF telemetry has no accelerometer (ACCL) stream (it holds "
                           f"{', '.join(sorted(streams)) or 'none of ACCL, GYRO, GPS'}); velocity needs one: pass "
                           f"--accel-from-truth to derive the acceleration from the GPS speed instead")
    if acc is not None:
        gyro = None
        if gyr is not None:
            if len(gyr.time_s) == len(acc.time_s) and np.allclose(gyr.time_s, acc.time_s, atol=1e-9):
                gyro = gyr.data
            else:
                gyro = np.stack([np.interp(acc.time_s, gyr.time_s, gyr.data[:, j]) for j in range(3)], -1)
                notes.append(f"gyroscope ({gyr.rate_hz or 0:.0f} Hz) linearly interpolated onto the accelerometer's "
                             f"times ({acc.rate_hz or 0:.0f} Hz)")
        imu = IMU(acc.time_s, acc.data, gyro, source=f"{path} (GPMF ACCL/GYRO)")
        orders = sorted({s.order for s in (acc, gyr) if s is not None and s.order})
        notes.append(f"IMU rotated from GoPro's axes (stored order {'/'.join(orders)}; X left, Y back, Z up) into the "
                     f"camera frame (x right, y down, z forward); sample times spread evenly over each telemetry "
                     f"packet's span in the MP4; the IMU and the image may be offset by tens of ms")
        if cam_path is not None:
            r_extra = camera_json_rotation(cam_path)
            if r_extra is not None:
                imu = imu.rotated(r_extra)
                notes.append(f"IMU then rotated by {cam_path.name}'s imu_to_camera ({rotation_deg(r_extra):.2f} deg), "
                             f"a correction in the camera frame")
    return imu, r_extra


def image_frame(imu: IMU, orientation: dict, stab: dict, notes: list[str]) -> IMU:
    """``imu`` turned into the stabilised image's frame by ``orientation``'s CORI and IORI ({key: (time_s (n,) s,
    quaternions (n, 4) w, x, y, z)}) where it has both and they can be used
    (:func:`lobula.readers.image_orientation.image_frame_imu`), else ``imu``. Where turned, ``stab``'s
    (:func:`stabilisation`'s) imu_frame becomes "image", with CORI's agreement with the gyro; ``notes`` say
    which it was, and why."""
    from .image_orientation import image_frame_imu

    if "CORI" not in orientation or "IORI" not in orientation:
        return imu
    (t, cori), (ti, iori) = orientation["CORI"], orientation["IORI"]
    try:
        if len(t) != len(ti) or not np.allclose(t, ti, atol=1e-6):
            raise ValueError("their samples do not pair up")
        res = image_frame_imu(imu, t, cori[:, :4], iori[:, :4])
    except ValueError as exc:
        notes.append(f"the file's camera and image orientations (CORI, IORI) are not used: {exc}; the IMU stays in "
                     f"the body's frame, which the stabilised image does not turn with")
        return imu
    stab.update(imu_frame="image", orientation_gyro_agreement=round(res.gyro_agreement, 3))
    notes.append(f"IMU turned into the stabilised image's frame by the file's camera and image orientations (CORI, "
                 f"IORI; the image up to {res.max_deg:.1f}° from the body, {res.mean_deg:.1f}° on average): the gyro "
                 f"reads the image's rotation, the accelerometer the image's axes (CORI's rates agree with the gyro's "
                 f"to {res.gyro_agreement:.2f})")
    return res.imu


def lens_guess_from_settings(width: int, height: int, fps: float, settings: dict) -> tuple[PinholeCamera, dict]:
    """(camera, lens guess) of a GoPro clip without intrinsics: an equidistant fisheye whose diagonal sees the field
    of view its ``settings`` state (ZFOV, deg), else :data:`NOMINAL_DIAGONAL_FOV_DEG`; the guess's rel_std says
    which."""
    zfov = settings.get("ZFOV")
    stated = isinstance(zfov, (int, float)) and 0 < zfov < 360
    fov = float(zfov) if stated else NOMINAL_DIAGONAL_FOV_DEG
    guess = dict(model="kannala-brandt", coeffs=[0.0, 0.0, 0.0, 0.0], diagonal_fov_deg=round(fov, 3),
                 source=(f"the file's stated diagonal field of view (ZFOV {fov:.1f}°)" if stated else
                         f"a nominal {fov:g}° diagonal (the file states no field of view)"),
                 rel_std=STATED_FOV_REL_STD if stated else NOMINAL_FOV_REL_STD)
    return equidistant_camera(width, height, fps, fov), guess


def gps_truth(gps: dict | None, notes: list[str]) -> dict | None:
    """The truth of the GPS samples (:func:`gps_samples`) with a 2D/3D fix: {time_s, v_forward_m_s (the 2D
    ground speed), gps_speed_3d_m_s, gps_fix, gps_dop}; None with fewer than two. Appends a note."""
    truth = None
    if gps is not None:
        good = np.isfinite(gps["fix"]) & (gps["fix"] >= GPS_FIX_2D) & np.isfinite(gps["speed_2d_m_s"])
        if good.sum() >= 2:
            truth = {"time_s": gps["time_s"][good], "v_forward_m_s": gps["speed_2d_m_s"][good],
                     "gps_speed_3d_m_s": gps["speed_3d_m_s"][good], "gps_fix": gps["fix"][good],
                     "gps_dop": gps["dop"][good]}
            notes.append(f"truth is GPS ({gps['source']}), not motion capture: v_forward_m_s is the 2D ground speed "
                         f"(Doppler) of the {int(good.sum())} of {len(good)} samples with a 2D/3D fix (median DOP "
                         f"{np.nanmedian(gps['dop'][good]):.2f}), the camera's forward speed only when it points along "
                         f"the motion (else speed × cos of the angle between them); good to about ±0.1 m/s")
        else:
            notes.append(f"GPS ({gps['source']}) has {int(good.sum())} of {len(good)} samples with a 2D/3D fix: "
                         f"no truth")
    return truth


def _telemetry_summary(model: str, firmware: str, packets: int, t0: float, t1: float, streams: dict[str, Stream],
                       settings: dict, gps: dict | None, truth: dict | None, stab: dict) -> dict:
    """The JSON-able ``GoProFootage.telemetry``: model, firmware, packets and their span (s), truth source,
    stabilisation, lens, streams, GPS and the camera settings kept."""
    return dict(
        model=model or None, firmware=firmware or None, packets=packets, span_s=[round(t0, 6), round(t1, 6)],
        truth_source=f"GPS ({gps['source']} 2D ground speed)" if truth is not None else "none",
        stabilisation=stab, lens=dict(fov_mode=settings.get("VFOV"), diagonal_fov_deg=settings.get("ZFOV")),
        streams={k: dict(samples=int(len(s.time_s)), rate_hz=s.rate_hz, units=s.units, name=s.name,
                         axes=_axes_text(s) if s.order else None) for k, s in sorted(streams.items())},
        gps=None if gps is None else dict(
            source=gps["source"], samples=int(len(gps["time_s"])),
            with_fix=int(np.sum(np.isfinite(gps["fix"]) & (gps["fix"] >= GPS_FIX_2D))),
            fix=sorted({int(f) for f in gps["fix"] if np.isfinite(f)}),
            dop_median=float(np.nanmedian(gps["dop"])) if np.isfinite(gps["dop"]).any() else None,
            speed_2d_mean_m_s=float(np.mean(truth["v_forward_m_s"])) if truth is not None else None),
        settings={k: v for k, v in settings.items() if k in ("MINF", "FMWR", "EISE", "EISA", "VFOV", "ZFOV", "OREN",
                                                             "DZOM", "HCTL", "PRJT")})


def _axes_text(s: Stream) -> str:
    """How an IMU stream's axes were mapped, e.g. "ORIN XzY -> ZXY -> camera"."""
    orin = s.props.get("ORIN")
    src = f"ORIN {orin} -> {s.order}" if isinstance(orin, str) and orin and orin != s.order else (
        s.order if isinstance(orin, str) and orin else f"{s.order} (documented for the model; no ORIN)")
    return f"{src} -> camera"


def describe_telemetry(telemetry: dict) -> list[str]:
    """Plain-text lines of a GoPro footage's ``telemetry`` summary (``lobula info``)."""
    t = telemetry
    out = [f"gopro:      {t.get('model') or 'unknown model'}"
           + (f", firmware {t['firmware']}" if t.get("firmware") else "")
           + f"; GPMF telemetry: {t['packets']} packets over {t['span_s'][0]:.3f}..{t['span_s'][1]:.3f} s, "
           f"streams {', '.join(t['streams'])}"]
    g = t.get("gps")
    if g:
        dop = "-" if g["dop_median"] is None else f"{g['dop_median']:.2f}"
        out.append(f"  gps:      {g['source']}, {g['with_fix']} of {g['samples']} samples with a 2D/3D fix (fix "
                   f"{g['fix']}, median DOP {dop})"
                   + (f"; mean 2D speed {g['speed_2d_mean_m_s']:.3f} m/s" if g.get("speed_2d_mean_m_s") is not None
                      else ""))
    st = t["stabilisation"]
    state = {True: "on", False: "off", None: "unknown"}[st["electronic"]]
    out.append(f"  stabilisation: electronic {state}" + (f" ({st['setting']})" if st.get("setting") else "")
               + f", from {st['source']}"
               + (f"; image orientation (IORI) up to {st['image_orientation_max_deg']:.2f} deg from the body "
                  f"(mean {st['image_orientation_mean_deg']:.2f})" if st.get("image_orientation_max_deg") is not None
                  else "")
               + ("; IMU in the stabilised image's frame" if st.get("imu_frame") == "image" else ""))
    lens = t.get("lens") or {}
    if lens.get("fov_mode") or lens.get("diagonal_fov_deg"):
        out.append(f"  lens:     field of view mode {lens.get('fov_mode') or '-'}"
                   + (f", {lens['diagonal_fov_deg']:.1f} deg diagonal"
                      if isinstance(lens.get("diagonal_fov_deg"), float) else "") + "; no intrinsics in the file")
    out.append(f"  truth:    {t['truth_source']}")
    return out


#: degree: the diagonal field of view assumed for a GoPro file that states none, before the gyro measures the focal
#: length (GoPro's wide modes see 120-155° across the diagonal; the MAX's "W" file states 137.4°)
NOMINAL_DIAGONAL_FOV_DEG = 135.0
#: 1σ fraction of the focal length: a stated field of view (the lens mode's, not this unit's calibration) and a
#: nominal one
STATED_FOV_REL_STD = 0.05
NOMINAL_FOV_REL_STD = 0.15


def equidistant_camera(width: int, height: int, fps: float, diagonal_fov_deg: float):
    """The pinhole parameters of an equidistant fisheye (Kannala–Brandt, no coefficients) whose diagonal sees
    ``diagonal_fov_deg`` (deg): f = half the diagonal (px) / half the angle (rad); principal point at the centre."""
    from lobula.camera import PinholeCamera

    f = 0.5 * math.hypot(width, height) / math.radians(0.5 * diagonal_fov_deg)
    return PinholeCamera(width, height, f, f, (width - 1) / 2, (height - 1) / 2, fps)


def equidistant_hint(width: int, height: int, fps: float, diagonal_fov_deg) -> str:
    """The error's last clause: a camera.json for an equidistant fisheye (Kannala–Brandt, no coefficients) whose
    diagonal sees the lens mode's stated field of view (deg), as a first approximation; "" where none is stated."""
    if not isinstance(diagonal_fov_deg, (int, float)) or not 0 < diagonal_fov_deg < 360:
        return ""
    f = 0.5 * math.hypot(width, height) / math.radians(0.5 * diagonal_fov_deg)
    cam = dict(width=width, height=height, fx=round(f, 1), fy=round(f, 1), cx=(width - 1) / 2, cy=(height - 1) / 2,
               frame_rate_hz=round(fps, 3), distortion=dict(model="kannala-brandt", coeffs=[0, 0, 0, 0]))
    return (f"; without a calibration, an equidistant fisheye whose diagonal sees the stated {diagonal_fov_deg:.1f}° "
            f"approximates it: {json.dumps(cam)}")
