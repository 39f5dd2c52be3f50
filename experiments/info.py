"""``lobula info FOOTAGE``: what a recording holds, for every layout the project reads.

Streams, frame count, rates, duration, dropped frames (gaps in the time stamps),
intrinsics and lens distortion, IMU presence, rates and ranges, camera–IMU extrinsics,
truth — what ``ros2 bag info`` and ``rs-enumerate-devices`` tell, as plain text or
``--json``. Also the footage options every footage-reading command shares
(:func:`add_footage_options`, :func:`open_footage_from_args`).
"""
from __future__ import annotations

import json
import sys

import numpy as np


def add_footage_options(p) -> None:
    """The reader options (stream, clock, bad frames, clock offset, undistortion) on a subcommand parser
    (:func:`experiments.parsers.add_footage_options`)."""
    from .parsers import add_footage_options

    add_footage_options(p)


def open_footage_from_args(args, require_imu: bool = True, keep_nan: bool = False, require_camera: bool = True):
    """open_footage with the options of :func:`add_footage_options` (absent options: defaults);
    keep_nan: count NaN IMU and truth values instead of stopping at them (``lobula info``);
    require_camera: False opens a recording without intrinsics (a GoPro MP4) with camera None (``lobula info``)."""
    from lobula.readers import open_footage
    from lobula.readers.core import FootageError
    from lobula.velocity.inertial import no_truth_for_acceleration

    clock = getattr(args, "clock", None)
    footage = open_footage(args.footage, stream=getattr(args, "stream", None),
                           clock=None if clock == "device" else clock, require_imu=require_imu,
                           skip_bad_frames=getattr(args, "skip_bad_frames", False),
                           clock_offset=getattr(args, "clock_offset", None),
                           undistort=getattr(args, "undistort", "same-k"), camera=getattr(args, "camera", None),
                           keep_nan=keep_nan, require_camera=require_camera,
                           rolling_shutter=getattr(args, "rolling_shutter", None))
    if getattr(args, "accel_from_truth", False) and footage.truth is None:  # before the run, not in its flow stage
        raise FootageError(no_truth_for_acceleration(footage))
    return footage


def _rate(t: np.ndarray) -> float | None:
    return float((len(t) - 1) / (t[-1] - t[0])) if len(t) > 1 and t[-1] > t[0] else None


def _ranges(v: np.ndarray) -> dict:
    """Per axis [min, max] of the finite values (None where an axis has none)."""
    out = {}
    for k, ax in enumerate("xyz"):
        x = v[:, k][np.isfinite(v[:, k])]
        out[ax] = [round(float(x.min()), 4), round(float(x.max()), 4)] if x.size else None
    return out


def _nan_note(counts: dict) -> str:
    """NaN counts per column as text, e.g. "accel_x 3, gyro_z 1"."""
    return ", ".join(f"{k} {n}" for k, n in counts.items())


#: the layouts whose readers guess a lens from the file where no camera file is given
#: (lobula.readers.gopro.lens_guess_from_settings, lobula.readers.camera_telemetry), for self-calibration
SELF_CALIBRATING = ("gopro", "camera-telemetry")


def describe(footage) -> dict:
    """Everything ``lobula info`` reports about a footage, as plain JSON-able values."""
    from lobula.readers.core import frame_gaps

    t = np.asarray(footage.times, float)
    cam = footage.camera
    # A GoPro MP4 opened without intrinsics: the container's nominal rate stands in for camera.json's.
    nominal = (float(cam.frame_rate_hz) if cam is not None
               else float(getattr(footage, "nominal_fps", 0) or _rate(t) or 1))
    d = dict(path=str(footage.path), layout=footage.kind,
             frames=dict(count=int(len(t)), start_s=float(t[0]) if len(t) else None,
                         duration_s=float(t[-1] - t[0]) if len(t) else 0.0,
                         nominal_rate_hz=nominal, measured_rate_hz=_rate(t),
                         median_interval_s=float(np.median(np.diff(t))) if len(t) > 1 else None,
                         **{f"dropped_{k}": v for k, v in frame_gaps(t, 1.0 / nominal).items()}),
             intrinsics=None if cam is None else cam.to_dict(), distortion=footage.distortion or None,
             # where the reader guesses a lens from the file (opened for velocity), the gyro measures the rest
             self_calibrates=cam is None and footage.kind in SELF_CALIBRATING)
    if getattr(footage, "telemetry", None) is not None:
        d["telemetry"] = footage.telemetry
    for extra in ("topic", "encoding", "time_source", "time_origin_s"):
        if getattr(footage, extra, None) not in (None, ""):
            d["frames"][extra] = getattr(footage, extra)
    imu = footage.imu
    if imu is None:
        d["imu"] = None
    else:
        norm = np.linalg.norm(imu.accel, axis=1)
        d["imu"] = dict(samples=int(len(imu.time_s)), rate_hz=_rate(imu.time_s),
                        span_s=[float(imu.time_s[0]), float(imu.time_s[-1])],
                        accel_range_m_s2=_ranges(imu.accel),
                        accel_mean_norm_m_s2=round(float(np.nanmean(norm)), 4) if np.isfinite(norm).any() else None,
                        gyro=None if imu.gyro is None else dict(range_rad_s=_ranges(imu.gyro),
                                                                 mean_rad_s=np.round(np.nanmean(imu.gyro, 0), 5)
                                                                 .tolist()),
                        gaps=frame_gaps(imu.time_s), source=imu.source,
                        frame="camera optical (x right, y down, z forward)",
                        nan_rows=dict(getattr(imu, "nan_counts", {}) or {}))
    r = footage.imu_to_camera
    d["extrinsics"] = None if r is None else dict(imu_to_camera=np.round(r, 6).tolist(),
                                                   angle_deg=round(float(np.degrees(np.arccos(np.clip(
                                                       (np.trace(r) - 1) / 2, -1, 1)))), 3))
    if footage.truth is None:
        d["truth"] = None
    else:
        tt = footage.truth["time_s"]
        d["truth"] = dict(columns=sorted(footage.truth), samples=int(len(tt)), span_s=[float(tt[0]), float(tt[-1])],
                          nan_rows=dict(getattr(footage, "truth_nan_counts", {}) or {}))
        if "v_forward_m_s" in footage.truth:
            v = np.asarray(footage.truth["v_forward_m_s"], float)
            v = v[np.isfinite(v)]
            if v.size:
                d["truth"]["v_forward_range_m_s"] = [round(float(np.min(v)), 4), round(float(np.max(v)), 4)]
    d["streams"] = list(footage.streams)
    d["notes"] = list(footage.notes)
    return d


def format_text(d: dict) -> str:
    """The plain-text report of :func:`describe`'s dict."""
    f, c = d["frames"], d["intrinsics"]
    out = [f"{d['path']}  [{d['layout']}]"]
    rate = f"{f['measured_rate_hz']:.3f}" if f["measured_rate_hz"] else "-"
    out.append(f"frames:     {f['count']} over {f['duration_s']:.3f} s; {rate} frames/s measured, "
               f"{f['nominal_rate_hz']:g} nominal")
    if f["dropped_gaps"]:
        out.append(f"dropped:    {f['dropped_missing']} frame(s) in {f['dropped_gaps']} gap(s); longest interval "
                   f"{f['dropped_largest_s'] * 1e3:.1f} ms, first at {f['dropped_first_at_s']:.3f} s")
    else:
        out.append("dropped:    none (no interval over 1.5 frame intervals)")
    for k in ("topic", "encoding", "time_source"):
        if k in f:
            out.append(f"{k + ':':<11} {f[k]}")
    out.append(("intrinsics: none in the recording; velocity measures them from the gyro against the image's "
                "rotation (printed and stored with their uncertainty), or takes --camera FILE (a camera.json)"
                if d["self_calibrates"] else
                "intrinsics: none in the recording; velocity needs them: --camera FILE (a camera.json)")
               if c is None else
               f"intrinsics: {c['width']}x{c['height']}, fx {c['fx']:.3f}, fy {c['fy']:.3f}, "
               f"cx {c['cx']:.3f}, cy {c['cy']:.3f}")
    out.append(f"distortion: {json.dumps(d['distortion']) if d['distortion'] else 'none reported'}")
    imu = d["imu"]
    if imu is None:
        out.append("imu:        none (velocity needs an accelerometer)")
    else:
        rate = f"{imu['rate_hz']:.1f} Hz" if imu["rate_hz"] else "-"
        out.append(f"imu:        {imu['samples']} samples, {rate}, {imu['span_s'][0]:.3f}..{imu['span_s'][1]:.3f} s; "
                   f"{imu['frame']}")
        mean = imu["accel_mean_norm_m_s2"]
        out.append("  accel:    " + ", ".join(f"{k} {v[0]:+.3f}..{v[1]:+.3f}" if v else f"{k} -" for k, v in
                                              imu["accel_range_m_s2"].items())
                   + " m/s²; mean |a| " + (f"{mean:.3f}" if mean is not None else "-"))
        if imu["gyro"]:
            out.append("  gyro:     " + ", ".join(f"{k} {v[0]:+.4f}..{v[1]:+.4f}" if v else f"{k} -" for k, v in
                                                  imu["gyro"]["range_rad_s"].items())
                       + f" rad/s; mean {imu['gyro']['mean_rad_s']}")
        else:
            out.append("  gyro:     none")
        if imu.get("nan_rows"):
            out.append(f"  NaN:      {_nan_note(imu['nan_rows'])} rows of {imu['source']} are NaN or empty "
                       f"(ranges above leave them out); velocity stops at them: repair or remove those rows")
        if imu["gaps"]["gaps"]:
            out.append(f"  gaps:     {imu['gaps']['gaps']} IMU gap(s), longest {imu['gaps']['largest_s'] * 1e3:.1f} ms")
    e = d["extrinsics"]
    out.append(f"extrinsics: {'IMU→camera rotation of %.3f deg applied: %s' % (e['angle_deg'], e['imu_to_camera']) if e else 'none applied'}")
    tr = d["truth"]
    out.append("truth:      " + ("none" if tr is None else
                                 f"{tr['samples']} samples, {', '.join(tr['columns'])}"
                                 + (f"; v_forward {tr['v_forward_range_m_s'][0]:+.3f}..{tr['v_forward_range_m_s'][1]:+.3f} m/s"
                                    if "v_forward_range_m_s" in tr else "")))
    if tr is not None and tr.get("nan_rows"):
        out.append(f"  NaN:      {_nan_note(tr['nan_rows'])} rows of the truth are NaN or empty (left out of the "
                   f"range; rows without a time are left out of the samples)")
    if d["streams"]:
        shown = [s for s in d["streams"] if "/option/" not in str(s.get("topic", ""))]
        hidden = len(d["streams"]) - len(shown)
        out.append("streams:" + (f" ({hidden} sensor-option topics not shown; see --json)" if hidden else ""))
        for s in shown:
            out.append("  " + "  ".join(f"{v}" for v in s.values()))
    if d.get("telemetry"):
        from lobula.readers.gopro import describe_telemetry
        out += describe_telemetry(d["telemetry"])
    for n in d["notes"]:
        out.append(f"note: {n}")
    return "\n".join(out)


def describe_eye(fo) -> dict:
    """What compound-eye footage (``lobula scene OUT --eye fly``; a :class:`stimuli.eye.EyeFootage`) holds."""
    t = fo.times
    d = dict(footage=str(fo.path), kind="compound-eye footage",
             ommatidia=int(fo.eye.n), dphi_deg=float(fo.eye.config.dphi_deg), eyes=fo.eye.config.eyes,
             samples=int(len(t)), rate_hz=float(fo.rate_hz), duration_s=float(t[-1] - t[0]) if len(t) else 0.0,
             imu=None, truth=fo.truth is not None, head_stabilised=fo.head is not None,
             read_with="lobula eye-velocity FOOTAGE")
    if fo.imu is not None and len(fo.imu.time_s) > 1:
        d["imu"] = dict(samples=int(len(fo.imu.time_s)),
                        rate_hz=float((len(fo.imu.time_s) - 1) / (fo.imu.time_s[-1] - fo.imu.time_s[0])))
    return d


def format_eye_text(d: dict) -> str:
    """:func:`describe_eye`'s dict as lines of text."""
    imu = d["imu"]
    return "\n".join([
        f"{d['footage']}: {d['kind']}",
        f"eye: {d['ommatidia']} ommatidia ({d['eyes']}), Δφ {d['dphi_deg']:g}°",
        f"samples: {d['samples']} at {d['rate_hz']:.1f} Hz, {d['duration_s']:.2f} s",
        "IMU: " + (f"{imu['samples']} samples at {imu['rate_hz']:.1f} Hz" if imu else "none"),
        f"truth: {'yes' if d['truth'] else 'none'}; head stabilised: {'yes' if d['head_stabilised'] else 'no'}",
        f"read it with: {d['read_with']}"])


def run_info(args) -> int:
    from stimuli.eye import is_eye_footage, open_eye_footage

    if is_eye_footage(args.footage):
        d = describe_eye(open_eye_footage(args.footage))
        print(json.dumps(d, indent=1) if args.json else format_eye_text(d))
        return 0
    footage = open_footage_from_args(args, require_imu=False, keep_nan=True, require_camera=False)
    d = describe(footage)
    if args.json:
        json.dump(d, sys.stdout, indent=1, default=str)
        print()
    else:
        print(format_text(d))
    return 0


def add_parser(subparsers):
    """Register `lobula info` (see experiments.cli)."""
    p = subparsers.add_parser("info", help="what a recording holds: streams, rates, intrinsics, IMU, gaps, truth")
    p.add_argument("footage", help="footage folder, D435i sample, RealSense .bag/.db3, EuRoC folder or video file")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    add_footage_options(p)
    p.set_defaults(func=run_info)
