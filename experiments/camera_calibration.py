"""`lobula calibrate-camera`: a footage's focal length and IMU axes from its own gyro
(:mod:`lobula.readers.focal_length`, :mod:`lobula.readers.imu_rotation`), written as a camera.json for ``--camera``."""
from __future__ import annotations

import json

import numpy as np


def run_calibrate_camera(args) -> int:
    """Check the IMU's axes, measure the focal length, write the camera.json (atomically) and print what was found."""
    from lobula.readers import OWN_EXTRINSICS
    from lobula.readers.core import FootageError
    from lobula.readers.focal_length import estimate_focal_length
    from lobula.readers.self_calibration import check_imu_axes

    from .info import open_footage_from_args
    from .store import write_text
    from lobula.version import provenance_attrs

    footage = open_footage_from_args(args, require_imu=False)
    if footage.imu is None or footage.imu.gyro is None:
        raise FootageError(f"{footage.path}: calibrate-camera measures the focal length against the gyro, and this "
                           f"footage has no IMU; record one with the gyro, or give a calibration file with --camera")
    dist = footage.distortion if (footage.distortion or {}).get("removed") and "raw_camera" in footage.distortion \
        else None
    # opened without a calibration, the footage was self-calibrated already (its IMU turned where needed); a
    # RealSense recording or EuRoC states its own extrinsics
    axes = getattr(footage, "calibration", None)
    check = axes is None and footage.kind not in OWN_EXTRINSICS
    if check:
        axes = check_imu_axes(footage)
    est = estimate_focal_length(footage, iterations=args.iterations, min_correlation=args.min_correlation)
    if check and "imu_axes_rotation" in axes:   # refined through the focal length found (the search leaves it set)
        axes = check_imu_axes(footage, turned=axes)
    axes = axes or {}
    cam = dict(dist["raw_camera"]) if dist else footage.camera.to_dict()
    cam.update(fx=round(est.fx, 3), fy=round(est.fy, 3))
    if dist:
        cam["distortion"] = dict(model=dist["model"], coeffs=list(dist["coeffs"]))
    r = footage.camera_file_imu_rotation
    if "imu_axes_rotation" in axes:   # the IMU's axes as read disagreed with the image's rotation
        r = np.asarray(axes["imu_axes_rotation"]) @ (np.eye(3) if r is None else r)
    if r is not None:
        cam["imu_to_camera"] = np.round(r, 9).tolist()
    cam["calibration"] = dict(method="gyro against the image's rotation, the translation fitted alongside "
                                     "(lobula.readers.focal_length)",
                              scale_from_first_guess=round(est.scale, 5), correlation=round(est.correlation, 4),
                              slope_std=round(est.slope_std, 5), frame_pairs=est.n_pairs, slopes=est.steps,
                              roll_scale=round(est.roll_scale, 5), imu_axes=axes.get("imu_axes_source", "not checked"),
                              footage=str(footage.path), **provenance_attrs())
    write_text(args.out, json.dumps(cam, indent=1) + "\n")
    print(f"wrote {args.out}: fx {est.fx:.2f} px, fy {est.fy:.2f} px ({est.scale:.4f} × the first guess; std "
          f"{est.slope_std:.4f}, correlation {est.correlation:.3f} over {est.n_pairs} frame pairs)")
    if "imu_axes_source" in axes:
        print(f"IMU axes: {axes['imu_axes_source']}")
    return 0
