"""The velocity pipeline on a whole footage: :func:`estimate_velocity`.

It returns the velocity Dataset: dims ``time`` and ``field``; ``v_hat``, ``v_std``, ``observable``,
``accel``, ``r``, ``r2``, ``r_dot``, ``v_field``, the epipole, ``v_true`` where truth exists and the gyro
bias where one was fitted; the whole configuration, the front end, the filter kind, the acceleration
source, the version and the commit in ``attrs``.
"""
from __future__ import annotations

import json
import time as _time
from dataclasses import replace
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.spatial.transform import Rotation

from lobula.config import VelocityConfig
from lobula.front_ends import FRONT_ENDS, get_front_end
from lobula.imu import (attitude_leak, forward_axis, gravity_drift_std, gyro_bias, leak_walk, orientation_from_gyro,
                        transport_rate)
from lobula.readers.core import Footage, footage_provenance
from lobula.readers.flo import FloUnits
from lobula.readout import readout
from lobula.version import provenance

from .fields import field_rates, slerp_orientations
from .inertial import (TRUTH_ACCEL_OFFSET_M_S2, accels_at, frame_interval, gravity_tau, gyro_bias_track, kappa_accel_at,
                       offline_gravity_error, start_accel_prior, turn_rate_at)


def estimate_velocity(footage: Footage, config: VelocityConfig | None = None, progress: bool = True,
                      flo_files: list[Path] | None = None, flo_units: FloUnits | None = None) -> xr.Dataset:
    """Estimate forward velocity over a footage.

    Parameters
    ----------
    footage : lobula.readers.core.Footage
        What :func:`lobula.readers.open_footage` opens: frames, the camera, the IMU and any truth.
    config : VelocityConfig, optional
        None: ``VelocityConfig()`` (DIS flow, the kalman readout, zero-phase).
    progress : bool
        Show a progress bar.
    flo_files, flo_units : optional
        The precomputed flow of the ``flo`` front end.

    Returns
    -------
    xarray.Dataset
        The velocity Dataset (see the module's docstring); ``v_hat`` and ``v_std`` in m/s over ``time`` (n,) s.
    """
    if not (hasattr(footage, "camera") and hasattr(footage, "times")):  # a Footage, or anything read as one
        raise TypeError(f"estimate_velocity takes a Footage (lobula.readers.open_footage(path)), got "
                        f"{type(footage).__name__} {footage!r}"[:300])
    if config is not None and not isinstance(config, VelocityConfig):
        raise TypeError(f"estimate_velocity's config must be a VelocityConfig (VelocityConfig.from_dict reads a "
                        f"dict), got {type(config).__name__}")
    config = (config or VelocityConfig()).validate()
    front = get_front_end(config.front_end)
    _check_epipole(config, front)
    _note_uncorrected_shutter(footage, config, front)
    t_start = _time.perf_counter()
    rates = field_rates(footage, config, flo_files, flo_units, progress)
    causal = config.readout.filter == "causal"
    vb = gyro_bias_track(footage, rates, causal, np.radians(config.gyro_bias_prior_deg_s))
    # The attitude that removes gravity, integrated once for the acceleration and the axis its error turns with.
    imu = footage.imu if not config.accel_from_truth else None
    rot = (orientation_from_gyro(imu.time_s, imu.gyro, causal, None if vb is None else vb[0])
           if imu is not None and imu.gyro is not None and config.derotate else None)
    # The frame's acceleration for the filter's state, and what the vision terms stand beside: the same
    # acceleration averaged as each row's rates average the motion (rates.span).
    (a3, a3_rates), accel_source = accels_at(footage, rates.t, config, (None, rates.span),
                                             bias=None if vb is None else vb[0], orientation=rot)
    a, a_rates = (x if x.ndim == 1 else x[:, 2] for x in (a3, a3_rates))
    t0 = _time.perf_counter()
    res = None
    if len(rates.t) >= 3:
        rcfg, axis, gravity_error = _offset_model(footage, rates, config, accel_source, vb, rot)
        kappa = (kappa_accel_at(a3_rates, rates, imu.time_s, rot if axis is not None else None, causal,
                                rcfg.coupling_window_s)
                 if config.heading_motion and imu is not None else None)
        res = readout(rates.t, rates.r, rates.r2, a, rcfg, material=rates.material,
                      turn_rate=turn_rate_at(footage, rates.t, accel_source, config), offset_axis=axis,
                      offset_axis_prior=gravity_error, kappa_accel=kappa, a_rates=a_rates,
                      **_imu_terms(footage, rates, config, accel_source, vb))
    rates.timings["readout"] = _time.perf_counter() - t0
    ds = velocity_dataset(rates, res, a, accel_source, footage, vb, rot)
    ds.attrs.update(_run_attrs(config, front, rates, res, accel_source, footage, t_start))
    return ds


def _note_uncorrected_shutter(footage: Footage, config: VelocityConfig, front) -> None:
    """Say in ``footage``'s notes where its camera's rolling shutter cannot be put back on the frames' times: the
    correction turns each row's flow by the gyro before it is pooled (lobula.rolling_shutter)."""
    readout = getattr(footage.camera, "rolling_shutter_s", 0.0) if footage.camera is not None else 0.0
    if not readout:
        return
    imu = footage.imu
    why = ("the footage has no gyro" if imu is None or imu.gyro is None else
           "derotation is off" if not config.derotate else
           f"the {front.name} front end pools its own fields, not flow" if front.yields == "fields" else None)
    if why:
        footage.notes.append(f"rolling shutter ({1e3 * readout:.1f} ms) not corrected: {why}")


def _check_epipole(config: VelocityConfig, front) -> None:
    """Raise ValueError, saying what to use, where the front end has no such epipole policy."""
    if config.epipole not in front.epipoles:
        others = [f.name for f in FRONT_ENDS.values() if config.epipole in f.epipoles]
        raise ValueError(f"the {front.name} front end has no epipole {config.epipole} (it runs with epipole "
                         f"{' or '.join(front.epipoles)}); use epipole {front.epipoles[0]!r} (--epipole "
                         f"{front.epipoles[0]}) or another front end ({', '.join(others)})")


def _offset_model(footage: Footage, rates, config: VelocityConfig, accel_source: str, vb, rot):
    """How the readout models the acceleration's offset: (ReadoutConfig, offset_axis (n, 3) or None,
    offset_axis_prior m/s²) — the gravity reference's error as a vector that turns with the camera where a
    gyro says how, else folded into the accelerometer's own offset prior."""
    causal = config.readout.filter == "causal"
    rcfg = config.readout
    axis, gravity_error = None, 0.0
    if not accel_source.startswith("accelerometer"):
        # A derivative of the true velocity has noise but no accelerometer offset to learn.
        return replace(rcfg, bias_prior_m_s2=min(rcfg.bias_prior_m_s2, TRUTH_ACCEL_OFFSET_M_S2)), None, 0.0
    if not causal:
        gravity_error = offline_gravity_error(float(footage.imu.time_s[-1] - footage.imu.time_s[0]), rcfg.v_prior_m_s)
    else:
        # Online, the gravity reference is set at the start and holds the acceleration there.
        gravity_error = start_accel_prior(rates.r)
    if footage.imu.gyro is not None and config.derotate:
        # That error is a vector in the frame gravity was taken in; its forward share turns with the
        # camera, so the readout tracks it there beside the accelerometer's own offset.
        axis = forward_axis(footage.imu.time_s, footage.imu.gyro, causal=causal,
                            bias=None if vb is None else vb[0], orientation=rot)
        axis = np.stack([np.interp(rates.t, footage.imu.time_s, axis[:, j]) for j in range(3)], -1)
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    else:
        rcfg = replace(rcfg, bias_prior_m_s2=float(np.hypot(rcfg.bias_prior_m_s2, gravity_error)))
    return rcfg, axis, gravity_error


def _imu_terms(footage: Footage, rates, config: VelocityConfig, accel_source: str, vb) -> dict:
    """The readout's inputs from the IMU beyond the acceleration, at the flow's times (n,):
    gravity_tau (s), drift_std (m/s²/s), offset_walk (m/s²/√s) and transport (1/s), each None where absent."""
    causal = config.readout.filter == "causal"
    out = dict(gravity_tau=gravity_tau(footage, rates.t, config), drift_std=None, offset_walk=None, transport=None)
    if not (accel_source.startswith("accelerometer") and footage.imu.gyro is not None and config.derotate):
        return out
    tb, gyro = footage.imu.time_s, footage.imu.gyro
    # A turning camera's forward speed changes by −λ·v beyond its forward acceleration.
    out["transport"] = transport_rate(rates.t, tb, gyro, None if vb is None else vb[0], rates.epipole,
                                      frame_interval(footage.times), causal=causal)
    # Gravity seen through a gyro-integrated attitude ramps at up to |g|·σ_b (lobula.imu):
    # a state of the readout's filter, offline and online alike.
    out["drift_std"] = np.interp(rates.t, tb, gravity_drift_std(tb, gyro, causal=causal,
                                                                bias_std=None if vb is None else vb[1],
                                                                accel=footage.imu.accel,
                                                                prior=np.radians(config.gyro_bias_prior_deg_s)))
    if causal:
        # Online the attitude took each sample's bias estimate; where that estimate moves, the
        # gravity it let in moves the offset the filter had learned (lobula.imu.leak_walk).
        used = vb[0] if vb is not None else gyro_bias(tb, gyro, causal=True)
        out["offset_walk"] = leak_walk(rates.t, tb, attitude_leak(tb, used, footage.imu.accel))
    return out


def velocity_dataset(rates, res, a: np.ndarray, accel_source: str, footage: Footage, vb=None, rot=None) -> xr.Dataset:
    """The velocity Dataset of a run: the readout's result ``res`` (None: too few pairs, all NaN) beside the
    fields' rates, the acceleration a (n,) m/s², the truth, the gyro bias track vb and the attitude rot
    ((m, 3, 3) at the IMU samples) where there are."""
    fields = rates.fields
    n, F = rates.r.shape
    nan_nf = np.full((n, F), np.nan)
    data = dict(
        v_hat=("time", res.v_hat if res else np.full(n, np.nan), {"units": "m/s", "long_name":
               "estimated forward velocity: where observable the filter's posterior, beyond carried by the "
               "accelerometer; NaN where vision has not fixed the speed"}),
        observable=("time", res.observable if res else np.zeros(n, bool), {"units": "1", "long_name":
                    "vision fixes the velocity at this frame"}),
        v_std=("time", res.v_std if res else np.full(n, np.nan), {"units": "m/s", "long_name":
               "std of v_hat: the posterior's where vision answers, beyond grown by the accelerometer offset's "
               "prior std times the time from the nearest frame where it answered (online: the last)"}),
        accel=("time", a, {"units": "m/s2", "long_name": "forward acceleration", "source": accel_source}),
        r=(("time", "field"), rates.r, {"units": "1/s", "long_name": "pooled expansion rate v/d"}),
        r2=(("time", "field"), rates.r2, {"units": "1/s2", "long_name": "pooled mean of r squared"}),
        r_dot=(("time", "field"), res.r_dot if res else nan_nf,
               {"units": "1/s2", "long_name": "time derivative of the pooled expansion rate r"}),
        v_field=(("time", "field"), res.v_field if res else nan_nf,
                 {"units": "m/s", "long_name": "per-field forward velocity a·r/(r_dot − r2)"}),
        epipole_x=("time", rates.epipole[:, 0], {"units": "1", "long_name": "epipole, normalised x"}),
        epipole_y=("time", rates.epipole[:, 1], {"units": "1", "long_name": "epipole, normalised y"}),
    )
    if res is not None:
        data.update(vision_variables(res.info))
    if footage.truth is not None:
        data["v_true"] = ("time", np.interp(rates.t, footage.truth["time_s"], footage.truth["v_forward_m_s"]),
                          {"units": "m/s", "long_name": "ground-truth forward velocity"})
    coords = dict(time=("time", rates.t, {"units": "s", "long_name": "time of the estimate on the footage clock"}),
                  azimuth_deg=("field", fields.centres_deg[:, 0],
                               {"units": "degree", "long_name": "LC field centre azimuth"}),
                  elevation_deg=("field", fields.centres_deg[:, 1],
                                 {"units": "degree", "long_name": "LC field centre elevation (positive down)"}),
                  size_deg=("field", np.full(F, fields.size_deg),
                            {"units": "degree", "long_name": "LC field size (Gaussian FWHM, or box side)"}))
    if vb is not None:
        tb = footage.imu.time_s
        at_t = lambda b: np.stack([np.interp(rates.t, tb, b[:, k]) for k in range(3)], -1)
        data["gyro_bias"] = (("time", "axis"), at_t(vb[0]), {"units": "rad/s", "long_name":
                             "gyro bias from " + vb[2]})
        data["gyro_bias_std"] = (("time", "axis"), at_t(vb[1]), {"units": "rad/s", "long_name":
                                 "std of the gyro bias estimate"})
        coords["axis"] = ("axis", ["x", "y", "z"], {"long_name": "camera axis (x right, y down, z forward)"})
    if rot is not None:
        q = Rotation.from_matrix(slerp_orientations(footage.imu.time_s, rot, rates.t)).as_quat()
        data["attitude"] = (("time", "quaternion"), q, {"units": "1", "long_name":
                            "camera orientation, camera to the first IMU sample's frame, from the integrated gyro"})
        coords["quaternion"] = ("quaternion", ["x", "y", "z", "w"], {"long_name": "unit quaternion component"})
    return xr.Dataset(data, coords=coords)


def vision_variables(info: dict) -> dict:
    """The readout's verdicts on vision as Dataset variables (name: (dims, values, attrs)), each (n,) over time:
    what :func:`lobula.readout.readout`'s ``info`` holds of them (vision_coupling, vision_locked,
    vision_informing, vision_refuted, scene_depth) and the filter's posterior_std; {} where it holds none (a
    readout without the coupling test)."""
    if "vision_coupling" not in info:
        return {}
    return dict(
        vision_coupling=("time", info["vision_coupling"], {"units": "1", "long_name":
                         "Fisher z of the fields' r_dot - r2 against the acceleration (lobula.readout.coupling)"}),
        vision_locked=("time", info["vision_locked"], {"units": "1", "long_name":
                       "vision has fixed the speed (coupling reached readout.coupling_z, or the camera held still) "
                       "and has not since been refuted; between, the accelerometer carries v_hat"}),
        vision_informing=("time", info["vision_informing"], {"units": "1", "long_name":
                          "a measurement of vision (kappa, the rest bound or a reversal) entered the filter at this "
                          "frame; elsewhere the accelerometer alone carries v_hat"}),
        vision_refuted=("time", info["vision_refuted"], {"units": "1", "long_name":
                        "the acceleration varied over the coupling window and the expansion did not follow"}),
        scene_depth=("time", info["scene_depth"], {"units": "m", "long_name":
                     "the fields' median depth as the footage has shown it while vision followed the accelerometer "
                     "(lobula.readout.scene_depth): the rest bound's depth; NaN: none yet, inf: a scene too far to "
                     "bound the speed by"}),
        posterior_std=("time", info["posterior_std"], {"units": "m/s", "long_name":
                       "the filter's posterior std of v on every frame; beyond the observable frames it takes the "
                       "offset vision taught as known, which v_std does not (lobula.readout.carry)"}),
    )


def _run_attrs(config: VelocityConfig, front, rates, res, accel_source: str, footage: Footage, t_start: float) -> dict:
    """The run's attributes: its configuration and provenance, the filter and when its estimates are known,
    the derotation, the acceleration's source, the footage, and the seconds each stage took."""
    lag = config.readout.lag_s if config.readout.filter == "causal" else 0.0
    online = {}
    if config.readout.filter == "causal" and rates.known is not None and res is not None:
        # When each v̂ is known after the time it is stamped with: its pair's second frame (half the
        # flow gap after the pair's middle) plus any declared look-ahead. The vision measurements speak
        # of the moment measurement_delay_s before that stamp, bridged by the integrated accelerometer.
        online = dict(output_latency_s=round(float(np.median(rates.known - rates.t)) + lag, 4))
        if "measurement_delay_s" in res.info:  # the kalman readout's (the paper's has no bridge)
            online["measurement_delay_s"] = round(float(res.info["measurement_delay_s"]), 4)
    filt = config.readout.filter + (f", fixed lag {lag:g} s" if lag else "")
    if online:
        filt += f" (each v_hat known {online['output_latency_s']:g} s after its time)"
    gyro = footage.imu is not None and footage.imu.gyro is not None
    if front.derotation == "gaze":
        derotation = (f"gaze stabilised by the integrated gyro (fixations, saccades beyond "
                      f"{config.emd.saccade_limit_deg:g} deg: {int(rates.timings.get('n_saccades', 0))})"
                      if config.derotate and gyro and config.emd.gaze == "fixate" else
                      "none: the EMD front end's image is not stabilised (the gyro serves the accelerometer's "
                      "attitude only)")
    else:
        derotation = "exact finite rotation from the integrated gyro" if config.derotate and gyro else "none"
    return provenance(config.to_json(), front_end=config.front_end, filter=filt, **online,
                      derotation=derotation, epipole=config.epipole,
                      readout=config.readout.method, acceleration_source=accel_source,
                      footage=str(footage.path), footage_kind=footage.kind,
                      notes="; ".join(footage.notes) or "none",
                      timings_s=json.dumps({k: round(v, 4) for k, v in rates.timings.items()}),
                      wall_s=round(_time.perf_counter() - t_start, 3), **footage_provenance(footage))
