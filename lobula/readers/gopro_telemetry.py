"""The GPMF streams of a GoPro MP4 over the whole file: on the video's clock, IMU axes in the camera frame.

:func:`read_telemetry` demultiplexes the ``gpmd`` track (PyAV), decodes each packet
(:func:`~lobula.readers.gpmf.decode_gpmf`), spreads each stream's samples evenly over its packet's
span (:func:`packet_sample_times`, less the stream's TIMO) and rotates ACCL and GYRO from their
stored channel order into the camera optical frame (:func:`imu_axes_to_camera`), one
:class:`Stream` per GPMF key.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import av
import numpy as np

from .core import FootageError
from .gpmf import decode_gpmf, decode_settings
from .mp4_index import Mp4Index, read_mp4_index

#: GoPro's standard output axis order (ORIO of every camera that writes one; HERO5's native order).
STANDARD_ORDER = "ZXY"

#: Rotation from a vector in GoPro's standard order (Z, X, Y components) to the camera optical
#: frame: x_cam = −X (X points left), y_cam = −Z (Z points up), z_cam = −Y (Y points out of the back).
GOPRO_TO_CAMERA = np.array([[0.0, -1.0, 0.0],
                            [-1.0, 0.0, 0.0],
                            [0.0, 0.0, -1.0]])

#: Rotation from GoPro's body axes in X, Y, Z order to the camera optical frame (what
#: ``Footage.imu_to_camera`` reports): the same axes as :data:`GOPRO_TO_CAMERA`.
GOPRO_XYZ_TO_CAMERA = np.array([[-1.0, 0.0, 0.0],
                                [0.0, 0.0, -1.0],
                                [0.0, -1.0, 0.0]])

#: The stored channel order of ACCL/GYRO for models that write no ORIN (gpmf-parser's
#: documentation: "Data order Z,X,Y" for HERO5, "Y,-X,Z" for HERO6, "-Y,X,Z" for Fusion);
#: lower case is a negated axis. Later models (HERO7 Black onwards, MAX) write ORIN themselves.
DEFAULT_ORIN = {"HERO5": "ZXY", "HERO6": "YxZ", "FUSION": "yXZ"}


def axis_order_matrix(orin: str, orio: str = STANDARD_ORDER) -> np.ndarray:
    """The 3×3 matrix M with out = M @ in, from a channel order ``orin`` to ``orio`` (GPMF ORIN/ORIO).

    Each string names the axis each channel holds, e.g. "XzY": channel 0 is +X, channel 1 is −Z,
    channel 2 is +Y (lower case: negated). M[i, j] = +1 where orio[i] and orin[j] name the same
    axis with the same sign, −1 with opposite signs, 0 otherwise (gpmf-parser's rule), so
    ``axis_order_matrix("XzY")`` is the MAX's MTRX [[0, −1, 0], [1, 0, 0], [0, 0, 1]].
    ValueError unless both are orders of the three axes X, Y, Z.
    """
    for s in (orin, orio):
        if len(s) != 3 or sorted(s.upper()) != ["X", "Y", "Z"]:
            raise ValueError(f"axis order {s!r} must name X, Y and Z once each (lower case: negated)")
    m = np.zeros((3, 3))
    for i, o in enumerate(orio):
        for j, c in enumerate(orin):
            if o.upper() == c.upper():
                m[i, j] = 1.0 if o.isupper() == c.isupper() else -1.0
    return m


def imu_axes_to_camera(order: str) -> np.ndarray:
    """Rotation taking a GoPro IMU sample stored in channel ``order`` (e.g. "ZXY", "YxZ") to the
    camera optical frame (x right, y down, z forward): v_cam = R @ v_stored. ValueError for an order
    that mirrors the axes (no rotation maps it; the metadata are wrong)."""
    m = axis_order_matrix(order, STANDARD_ORDER)
    if np.linalg.det(m) < 0:
        raise ValueError(f"axis order {order!r} mirrors the axes (a left-handed frame)")
    return GOPRO_TO_CAMERA @ m


def packet_sample_times(t_in: float, t_out: float, n: int) -> np.ndarray:
    """Times (s) of the n samples of one stream in a GPMF packet spanning [t_in, t_out):
    spread evenly from the packet's start, t_k = t_in + k (t_out − t_in) / n."""
    return t_in + np.arange(n) * ((t_out - t_in) / n) if n > 0 else np.zeros(0)



@dataclass
class Stream:
    """One GPMF stream over the whole file: ``key`` (the GPMF four-character code), ``time_s`` (n,) s on
    the video's clock, ``data`` (n, m) as gpmf-parser scaled it (in ``units``), the channel ``order``
    the data is in (ACCL/GYRO: e.g. "ZXY"), its ``name`` and ``units``, and ``props``, the properties
    of its first packet. GPS5 only: ``per_packet_fix`` (n,), each sample's packet fix (GPSF: 0 none,
    2 2D, 3 3D) and ``per_packet_dop`` (n,), its packet's dilution of precision (GPSP / 100)."""

    key: str
    time_s: np.ndarray
    data: np.ndarray
    order: str | None = None
    name: str = ""
    units: str = ""
    props: dict = field(default_factory=dict)
    per_packet_fix: np.ndarray | None = None  # GPS5: each sample's packet GPSF
    per_packet_dop: np.ndarray | None = None  # GPS5: each sample's packet GPSP / 100

    @property
    def rate_hz(self) -> float | None:
        """Mean sample rate (Hz) over the file; None for fewer than two samples."""
        t = self.time_s
        return float((len(t) - 1) / (t[-1] - t[0])) if len(t) > 1 and t[-1] > t[0] else None


def _stored_order(props: dict, key: str, model: str, path: Path) -> str:
    """The channel order gpmf-parser's scaled ACCL/GYRO data is in.

    gpmf-parser applies MTRX when it is a calibration (not only 0/±1), else the permutation
    ORIN → ORIO when both are there; without either the data keep the sensor's order: ORIN, or
    the model's documented default.
    """
    orin, orio, mtrx = props.get("ORIN"), props.get("ORIO"), props.get("MTRX")
    calibration = mtrx is not None and np.any(~np.isin(np.round(np.ravel(mtrx), 6), (-1.0, 0.0, 1.0)))
    if isinstance(orio, str) and len(orio) == 3 and (calibration or (isinstance(orin, str) and len(orin) == 3)):
        return orio
    if calibration:
        return STANDARD_ORDER
    if isinstance(orin, str) and len(orin) == 3:
        return orin
    for name, order in DEFAULT_ORIN.items():
        if name in model.upper().replace(" ", ""):
            return order
    raise FootageError(f"{path}: the {key} stream does not say its axis order (no ORIN) and GoPro documents none for "
                       f"{model or 'this camera'} (documented: HERO5, HERO6, Fusion); export the IMU in the camera "
                       f"frame to imu.csv and read a copy of the video with it (the video reader)")


def read_telemetry(path: str | Path, index: Mp4Index | None = None) -> tuple[dict[str, Stream], dict, tuple]:
    """All kept GPMF streams of the GoPro MP4 at ``path``, on the video's clock.

    index: the MP4's box index (:func:`~lobula.readers.mp4_index.read_mp4_index`), read here when None.
    Returns ({key: :class:`Stream`}, settings (:func:`decode_settings`), (first packet start s,
    last packet end s, packet count)). FootageError naming the file for an MP4 without a ``gpmd``
    track, a damaged container or a damaged telemetry packet.
    """
    path = Path(path)
    index = index if index is not None else read_mp4_index(path)
    if index is None or not index.gpmd_tracks:
        raise FootageError(f"{path}: no GPMF telemetry track (gpmd) in this file, so no IMU or GPS from the camera; "
                           f"use the camera's original file (re-encoding or editing drops the track), or give "
                           f"imu.csv and camera.json beside the video for the plain video reader")
    settings = decode_settings(index.udta_gpmf)
    chunks, spans = _demux(path, index)
    model = str(settings.get("MINF", ""))
    out = {}
    for key, parts in chunks.items():
        stream = _assemble_stream(path, key, parts, model)
        if stream is not None:
            out[key] = stream
    return out, settings, (spans[0][0], spans[-1][1], len(spans))


def packet_spans(path: str | Path) -> list[tuple[float, float]]:
    """Every ``gpmd`` telemetry packet's span [t_in, t_out) (s, on the video's clock) of the GoPro MP4 at ``path``,
    the packets not decoded. FootageError as :func:`read_telemetry`'s."""
    path = Path(path)
    index = read_mp4_index(path)
    if index is None or not index.gpmd_tracks:
        raise FootageError(f"{path}: no GPMF telemetry track (gpmd) in this file; use the camera's original file")
    return _demux(path, index, decode=False)[1]


def _demux(path: Path, index: Mp4Index, decode: bool = True) -> tuple[dict[str, list], list[tuple[float, float]]]:
    """The ``gpmd`` track's packets decoded (where ``decode``): ``{key: [(t_in, t_out, occurrence), ...]}`` for each
    data key (:func:`~lobula.readers.gpmf.decode_gpmf`'s dicts; the first device's only) and every packet's span
    [t_in, t_out) (s, on the video's clock). FootageError naming the file for a damaged container or
    packet, or a track without packets."""
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, UnicodeDecodeError) as exc:
        raise FootageError(f"{path}: FFmpeg cannot open this MP4 ({exc.__class__.__name__}); copy the file again from "
                           f"the camera's card") from None
    chunks: dict[str, list] = {}
    spans = []
    try:
        streams = [s for s in container.streams if s.id in index.gpmd_tracks and s.type == "data"]
        if not streams:
            raise FootageError(f"{path}: FFmpeg does not see the gpmd track (track {index.gpmd_tracks[0]}); copy the "
                               f"file again from the camera's card")
        stream = streams[0]
        try:
            for packet in container.demux(stream):
                if packet.size == 0 or packet.pts is None:
                    continue
                t_in = float(packet.pts * packet.time_base)
                t_out = float((packet.pts + (packet.duration or 0)) * packet.time_base)
                k = len(spans)
                if t_out <= t_in:
                    raise FootageError(f"{path}: telemetry packet {k} at {t_in:.3f} s has no duration in the MP4's "
                                       f"sample table; copy the file again from the camera's card")
                if not decode:
                    spans.append((t_in, t_out))
                    continue
                try:
                    found = decode_gpmf(bytes(packet))
                except ValueError as exc:
                    raise FootageError(f"{path}: telemetry packet {k} ({t_in:.3f}–{t_out:.3f} s) is damaged ({exc}); "
                                       f"copy the file again from the camera's card") from None
                spans.append((t_in, t_out))
                first_device = {}
                for f in found:
                    first_device.setdefault(f["key"], f["device"])
                    if f["device"] != first_device[f["key"]]:
                        continue  # a second device (a connected sensor) with the same stream: keep the camera's
                    chunks.setdefault(f["key"], []).append((t_in, t_out, f))
        except av.error.FFmpegError as exc:
            raise FootageError(f"{path}: the MP4 is damaged after {len(spans)} telemetry packets ({exc}); copy the "
                               f"file again from the camera's card") from None
    finally:
        container.close()
    if not spans:
        raise FootageError(f"{path}: the gpmd telemetry track holds no packets; use the camera's original file")
    return chunks, spans


def _assemble_stream(path: Path, key: str, parts: list, model: str) -> Stream | None:
    """One key's occurrences (:func:`_demux`) as a :class:`Stream` over the whole file, ACCL/GYRO in the
    camera frame; None where no packet holds a sample of it. model: the camera's MINF, for the
    documented axis order of models that write no ORIN."""
    # Samples of one key within a packet share its span; a key can occur more than once per packet.
    per_packet: dict[tuple, list] = {}
    for t_in, t_out, f in parts:
        per_packet.setdefault((t_in, t_out), []).append(f)
    times, data, fix, dop = [], [], [], []
    props = parts[0][2]["props"]
    order = None
    for (t_in, t_out), fs in per_packet.items():
        d = np.concatenate([f["data"] for f in fs]) if len({f["data"].shape[1] for f in fs}) == 1 else fs[0]["data"]
        if not len(d):
            continue
        p = fs[0]["props"]
        t = packet_sample_times(t_in, t_out, len(d)) - float(p.get("TIMO") or 0.0)
        if key in ("ACCL", "GYRO"):
            if d.shape[1] < 3:
                raise FootageError(f"{path}: the {key} samples have {d.shape[1]} axes, not 3: the telemetry is "
                                   f"damaged; copy the file again from the camera's card")
            o = _stored_order(p, key, model, path)
            try:
                d = d[:, :3] @ imu_axes_to_camera(o).T
            except ValueError as exc:
                raise FootageError(f"{path}: the {key} stream's axis order cannot be used ({exc}); the "
                                   f"telemetry's ORIN/ORIO are damaged: export the IMU in the camera frame to "
                                   f"imu.csv and read a copy of the video with it (the video reader)") from None
            order = order or o
        times.append(t)
        data.append(d)
        fix.append(np.full(len(d), np.nan if p.get("GPSF") is None else float(p["GPSF"])))
        dop.append(np.full(len(d), np.nan if p.get("GPSP") is None else float(p["GPSP"]) / 100.0))
    if not times:
        return None
    t = np.concatenate(times)
    bad = np.flatnonzero(~(np.diff(t) > 0))
    if not np.all(np.isfinite(t)) or bad.size:
        at = t[bad[0]] if bad.size else float("nan")
        raise FootageError(f"{path}: the {key} samples' times do not increase (at {at:.3f} s): the MP4's sample "
                           f"table for the telemetry track is damaged; copy the file again from the camera's card")
    return Stream(key, t, np.concatenate(data), order=order, name=str(props.get("STNM") or ""),
                  units=str(props.get("SIUN") or props.get("UNIT") or ""), props=props,
                  per_packet_fix=np.concatenate(fix) if key == "GPS5" else None,
                  per_packet_dop=np.concatenate(dop) if key == "GPS5" else None)
