"""`lobula calibrate-camera`: a footage's focal length from its own gyro (:mod:`lobula.readers.focal_length`),
written as a camera.json for ``--camera``."""
from __future__ import annotations

import json


def run_calibrate_camera(args) -> int:
    """Measure the focal length, write the camera.json (atomically) and print what was found."""
    from lobula.readers.focal_length import estimate_focal_length

    from .info import open_footage_from_args
    from .store import write_text
    from lobula.version import provenance_attrs

    footage = open_footage_from_args(args)
    dist = footage.distortion if (footage.distortion or {}).get("removed") and "raw_camera" in footage.distortion \
        else None
    est = estimate_focal_length(footage, iterations=args.iterations, min_correlation=args.min_correlation)
    cam = dict(dist["raw_camera"]) if dist else footage.camera.to_dict()
    cam.update(fx=round(est.fx, 3), fy=round(est.fy, 3))
    if dist:
        cam["distortion"] = dict(model=dist["model"], coeffs=list(dist["coeffs"]))
    if footage.imu_to_camera is not None and footage.kind == "folder":
        cam["imu_to_camera"] = footage.imu_to_camera.tolist()
    cam["calibration"] = dict(method="gyro against the image's rotation (lobula.readers.focal_length)",
                              scale_from_first_guess=round(est.scale, 5), correlation=round(est.correlation, 4),
                              slope_std=round(est.slope_std, 5), frame_pairs=est.n_pairs, slopes=est.steps,
                              relative_to_roll=est.by_roll, footage=str(footage.path), **provenance_attrs())
    write_text(args.out, json.dumps(cam, indent=1) + "\n")
    print(f"wrote {args.out}: fx {est.fx:.2f} px, fy {est.fy:.2f} px ({est.scale:.4f} × the first guess; slope std "
          f"{est.slope_std:.4f}, correlation {est.correlation:.3f} over {est.n_pairs} frame pairs"
          + (", relative to the roll's" if est.by_roll else "") + ")")
    return 0
