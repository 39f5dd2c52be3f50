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
  walk over the MP4's box headers (:func:`read_mp4_index`).
* **GPMF** — GoPro's own parser, gpmf-parser, through its Python binding ``py-gpmf-parser``,
  decodes each packet: types, struct sizes, SCAL divisors and the axis order (ORIN → ORIO, or
  the calibration matrix MTRX), so ACCL and GYRO come out in GoPro's standard order Z, X, Y.
* **timing** — the n samples of a stream in a packet spanning [t_in, t_out) are spread evenly,
  t_k = t_in + k (t_out − t_in)/n (:func:`packet_sample_times`), then moved earlier by the
  stream's TIMO offset where it has one.
* **axes** — GoPro's IMU axes (X, Y, Z of the gpmf-parser documentation: Z up out of the
  camera's top, Y out of its back, X to its left, right-handed) are rotated into the camera
  optical frame the pipeline uses (x right, y down, z forward): x = −X, y = −Z, z = −Y
  (:data:`GOPRO_TO_CAMERA`). The signs hold on real clips (../shared/data/gopro_walking): the
  mean specific force leans back by the camera's downward pitch, which puts the focus of
  expansion above the image centre as the flow shows, and the gyro's yaw and pitch move the
  image left and down as they should (tests/test_gopro.py). Files without ORIN use the order
  GoPro documents for the model (:data:`DEFAULT_ORIN`: HERO5 Z,X,Y; HERO6 Y,−X,Z; Fusion −Y,X,Z).
* **truth** — GPS 2D ground speed (Doppler) of the samples with a 2D or 3D fix, as
  ``truth["v_forward_m_s"]``: the camera's forward speed only when its optical axis points along
  the walk (otherwise speed × cos of the angle between them). Every output says its truth is GPS.
* **stabilisation** — HyperSmooth/EIS is read from the settings (EISE, EISA) and, where the file
  has IORI, from how far the image orientation departs from the camera body's.

GoPro files carry no lens intrinsics (the lens is a wide-angle fisheye), so velocity needs a
camera.json: ``--camera FILE`` or ``CLIP.camera.json`` / ``camera.json`` beside the clip.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import av
import numpy as np

from .core import FootageError, IMU, imu_to_camera as camera_json_rotation, read_camera_json, rotation_deg
from .video import VideoFootage, container_times

#: Sample-description type of the MP4 track that holds GPMF.
GPMF_SAMPLE_TYPE = b"gpmd"

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

#: GPMF streams this reader keeps (data keys) and the per-stream properties it reads beside them.
DATA_KEYS = ("ACCL", "GYRO", "GPS5", "GPS9", "CORI", "IORI", "GRAV")
STICKY_KEYS = ("ORIN", "ORIO", "MTRX", "TIMO", "STNM", "SIUN", "UNIT", "GPSF", "GPSP")

#: GPMF type characters of fixed-size numbers, as big-endian numpy dtypes.
_DTYPES = {"b": ">i1", "B": ">u1", "s": ">i2", "S": ">u2", "l": ">i4", "L": ">u4", "f": ">f4", "d": ">f8",
           "j": ">i8", "J": ">u8"}

#: The lowest GPS fix (GPSF, GPS9's fix field: 0 no lock, 2 2D, 3 3D) whose samples count as truth.
GPS_FIX_2D = 2

#: An image orientation (IORI) further than this from the body's (degrees) counts as stabilisation.
IORI_STABILISED_DEG = 0.5

GPMF_INSTALL_HINT = ("reading GoPro telemetry needs py-gpmf-parser (GoPro's gpmf-parser; wheels for Linux x86-64, "
                     "Python 3.8–3.12): pip install 'py-gpmf-parser>=0.1.1,<1'")


# ----------------------------------------------------------------------------- pure helpers
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


def quaternion_angle_deg(q: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees) of quaternions q (n, 4) ordered w, x, y, z (any norm)."""
    q = np.asarray(q, float)
    w = np.abs(q[:, 0]) / np.maximum(np.linalg.norm(q, axis=1), 1e-12)
    return np.degrees(2.0 * np.arccos(np.clip(w, 0.0, 1.0)))


# ----------------------------------------------------------------------------- MP4 boxes
@dataclass
class Mp4Index:
    """What the MP4's box headers say: the track IDs whose sample type is ``gpmd`` and the GPMF
    settings block of ``moov/udta`` (bytes, or None where the file has none)."""

    gpmd_tracks: list[int] = field(default_factory=list)
    udta_gpmf: bytes | None = None


def _boxes(buf: bytes, start: int, end: int, where: str):
    """(type, payload start, box end) of each box in buf[start:end]; ValueError where a box runs
    past its parent."""
    pos = start
    while pos + 8 <= end:
        size, typ, head = int.from_bytes(buf[pos:pos + 4], "big"), bytes(buf[pos + 4:pos + 8]), 8
        if size == 1:
            size, head = int.from_bytes(buf[pos + 8:pos + 16], "big"), 16
        elif size == 0:
            size = end - pos
        if size < head or pos + size > end:
            raise ValueError(f"box {typ!r} in {where} runs past its end")
        yield typ, pos + head, pos + size
        pos += size


def _child(buf: bytes, start: int, end: int, path: tuple[bytes, ...]):
    """(payload start, end) of the first box along ``path`` below buf[start:end], or None."""
    for name in path:
        for typ, s, e in _boxes(buf, start, end, name.decode("latin-1")):
            if typ == name:
                start, end = s, e
                break
        else:
            return None
    return start, end


def read_mp4_index(path: str | Path) -> Mp4Index | None:
    """The GPMF-relevant part of an MP4/MOV's index (see :class:`Mp4Index`); None where the file
    does not start like an ISO-BMFF file (not an MP4: another reader's business).

    FootageError naming the file where it is an MP4 without its index (``moov``) — a recording cut
    short (GoPro cameras write the index last) or an incomplete copy. A file cut after its index
    passes: FFmpeg reads the packets that are left.
    """
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(8)
        if len(head) < 8 or head[4:8] not in (b"ftyp", b"moov", b"mdat", b"free", b"skip", b"wide"):
            return None
        pos, moov, seen, cut = 0, None, [], None
        while pos + 8 <= size:
            fh.seek(pos)
            h = fh.read(16)
            box, typ, hlen = int.from_bytes(h[:4], "big"), h[4:8], 8
            if box == 1:
                box, hlen = int.from_bytes(h[8:16], "big"), 16
            elif box == 0:
                box = size - pos
            if box < hlen:
                raise FootageError(f"{path}: damaged MP4 (box {typ!r} at byte {pos} has size {box}); copy the file "
                                   f"again from the camera's card")
            seen.append(typ)
            if pos + box > size:  # cut short; with the index before the cut, FFmpeg reads what is left
                cut = f"; its {typ.decode('latin-1')!r} box needs {pos + box} bytes and the file has {size}"
                break
            if typ == b"moov":
                fh.seek(pos + hlen)
                moov = fh.read(box - hlen)
            pos += box
    if moov is None:
        raise FootageError(f"{path}: the MP4 has no index (moov box; boxes: "
                           f"{', '.join(t.decode('latin-1') for t in seen)}{cut or ''}): the recording was cut short "
                           f"or the copy is incomplete; copy the whole file again from the camera's card (or repair an "
                           f"interrupted recording, e.g. with untrunc and a good clip from the same camera)")
    index = Mp4Index()
    try:
        for typ, s, e in _boxes(moov, 0, len(moov), "moov"):
            if typ == b"udta":
                g = _child(moov, s, e, (b"GPMF",))
                if g is not None:
                    index.udta_gpmf = bytes(moov[g[0]:g[1]])
            elif typ == b"trak":
                tkhd = _child(moov, s, e, (b"tkhd",))
                stsd = _child(moov, s, e, (b"mdia", b"minf", b"stbl", b"stsd"))
                if tkhd is None or stsd is None or stsd[1] - stsd[0] < 16:
                    continue
                version = moov[tkhd[0]]
                id_at = tkhd[0] + (20 if version == 1 else 12)
                # stsd: version/flags, entry count, then sample entries (size, type, ...)
                if moov[stsd[0] + 12:stsd[0] + 16] == GPMF_SAMPLE_TYPE:
                    index.gpmd_tracks.append(int.from_bytes(moov[id_at:id_at + 4], "big"))
    except ValueError as exc:
        raise FootageError(f"{path}: damaged MP4 index ({exc}); copy the file again from the camera's card") from None
    return index


def has_gpmf_track(path: str | Path) -> bool:
    """Whether ``path`` is an MP4/MOV with a GPMF (``gpmd``) telemetry track — a GoPro recording as the
    camera wrote it. FootageError for an MP4 cut short (:func:`read_mp4_index`)."""
    index = read_mp4_index(path)
    return bool(index and index.gpmd_tracks)


# ----------------------------------------------------------------------------- GPMF
def _parser():
    try:
        import py_gpmf_parser as pg
    except ImportError:
        raise FootageError(GPMF_INSTALL_HINT) from None
    return pg


def _value(pg, ms, type_char: str):
    """A property's value: text for 'c'/'U' (several strings joined by ", "), a float or an array for
    fixed-size numbers, else None."""
    raw = pg.GPMF_RawData(ms)
    if type_char in "cU":
        size, repeat = pg.GPMF_StructSize(ms), pg.GPMF_Repeat(ms)
        parts = [raw[i * size:(i + 1) * size] for i in range(repeat)] if size > 1 and repeat > 1 else [raw]
        return ", ".join(p.split(b"\0", 1)[0].decode("latin-1").strip() for p in parts)
    dt = _DTYPES.get(type_char)
    if dt is None or len(raw) < np.dtype(dt).itemsize:
        return None
    v = np.frombuffer(raw[:len(raw) // np.dtype(dt).itemsize * np.dtype(dt).itemsize], dt).astype(float)
    return float(v[0]) if v.size == 1 else v


def _error_name(pg, ret) -> str:
    """gpmf-parser's name of an error code (its functions return the enum or a bare int)."""
    try:
        return pg.GPMF_ERROR(int(ret)).name
    except (ValueError, TypeError):
        return f"error {int(ret)}"


def decode_gpmf(payload: bytes, keys=DATA_KEYS) -> list[dict]:
    """Every occurrence of a data key of ``keys`` in one GPMF payload, decoded by gpmf-parser.

    Returns dicts {key, device (DVID), data (n, m) float64 scaled by SCAL and put in the ORIO
    order where ORIN/ORIO or MTRX say so, properties {ORIN, ORIO, MTRX, TIMO, STNM, SIUN, UNIT,
    GPSF, GPSP: the stream's values before the key}}. ValueError where the payload's structure is
    damaged (the message says how).
    """
    pg = _parser()
    ok = int(pg.GPMF_ERROR.GPMF_OK)
    ends = (int(pg.GPMF_ERROR.GPMF_ERROR_BUFFER_END), int(pg.GPMF_ERROR.GPMF_ERROR_LAST))
    if len(payload) < 8 or payload[:4] != b"DEVC":
        raise ValueError(f"not GPMF (starts {payload[:4]!r}, not DEVC)")
    words = np.frombuffer(payload + b"\0" * (-len(payload) % 4), dtype=np.uint32)  # gpmf-parser swaps the bytes
    ret, ms = pg.GPMF_Init(words, len(payload))
    if int(ret) != ok:
        raise ValueError(f"gpmf-parser cannot start on it ({_error_name(pg, ret)})")
    found, device, props = [], None, {}
    while True:
        key = pg.fourCC_to_string(pg.GPMF_Key(ms))
        tc = chr(pg.GPMF_Type(ms) or 0)
        if key == "DEVC":
            device, props = None, {}
        elif key == "DVID":
            device = _value(pg, ms, tc)
        elif key == "STRM":
            props = {}
        elif key in STICKY_KEYS:
            props[key] = _value(pg, ms, tc)
        elif key in keys:
            n, m = pg.GPMF_Repeat(ms), pg.GPMF_ElementsInStruct(ms)
            data = np.zeros((0, m))
            if n and m:
                ret, values = pg.GPMF_ScaledData(ms, n * m * 8, 0, n, pg.GPMF_SampleType.DOUBLE)
                if int(ret) != ok:
                    raise ValueError(f"gpmf-parser cannot scale {key} ({_error_name(pg, ret)})")
                data = np.asarray(values[:n * m], float).reshape(n, m)
            found.append(dict(key=key, device=device, data=data, props=dict(props)))
        ret = int(pg.GPMF_Next(ms, pg.GPMF_RECURSE_LEVELS))
        if ret in ends:
            return found
        if ret != ok:
            raise ValueError(f"damaged structure after {key} ({_error_name(pg, ret)})")


def decode_settings(payload: bytes | None) -> dict:
    """The camera's settings from the ``udta`` GPMF block: {four-character key: text or number}
    (MINF model, FMWR firmware, EISE/EISA stabilisation, VFOV/ZFOV lens, OREN orientation, ...);
    {} where there is none or it cannot be read (the settings are informative only)."""
    if not payload or payload[:4] != b"DEVC":
        return {}
    pg = _parser()
    words = np.frombuffer(payload + b"\0" * (-len(payload) % 4), dtype=np.uint32)
    ret, ms = pg.GPMF_Init(words, len(payload))
    out = {}
    if int(ret) != int(pg.GPMF_ERROR.GPMF_OK):
        return out
    while True:
        key = pg.fourCC_to_string(pg.GPMF_Key(ms))
        tc = chr(pg.GPMF_Type(ms) or 0)
        if tc != "\0" and key not in out:
            v = _value(pg, ms, tc)
            if isinstance(v, (str, float)):
                out[key] = v
        if int(pg.GPMF_Next(ms, pg.GPMF_RECURSE_LEVELS)) != int(pg.GPMF_ERROR.GPMF_OK):
            return out


@dataclass
class Stream:
    """One GPMF stream over the whole file: times (n,) s on the video's clock, data (n, m) as
    gpmf-parser scaled it, the channel order the data is in (ACCL/GYRO: e.g. "ZXY"), its name and
    units, and the properties of its first packet."""

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
    """All kept GPMF streams of a GoPro MP4, on the video's clock.

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
    model = str(settings.get("MINF", ""))
    out = {}
    for key, parts in chunks.items():
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
            continue
        t = np.concatenate(times)
        bad = np.flatnonzero(~(np.diff(t) > 0))
        if not np.all(np.isfinite(t)) or bad.size:
            at = t[bad[0]] if bad.size else float("nan")
            raise FootageError(f"{path}: the {key} samples' times do not increase (at {at:.3f} s): the MP4's sample "
                               f"table for the telemetry track is damaged; copy the file again from the camera's card")
        out[key] = Stream(key, t, np.concatenate(data), order=order, name=str(props.get("STNM") or ""),
                          units=str(props.get("SIUN") or props.get("UNIT") or ""), props=props,
                          per_packet_fix=np.concatenate(fix) if key == "GPS5" else None,
                          per_packet_dop=np.concatenate(dop) if key == "GPS5" else None)
    return out, settings, (spans[0][0], spans[-1][1], len(spans))


# ----------------------------------------------------------------------------- GPS and stabilisation
def gps_samples(streams: dict[str, Stream]) -> dict[str, np.ndarray] | None:
    """The GPS samples of GPS9 (preferred: per-sample fix and DOP) or GPS5 (the packet's GPSF/GPSP):
    {time_s, lat_deg, lon_deg, alt_m, speed_2d_m_s, speed_3d_m_s, fix, dop, source}; None without GPS."""
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


def stabilisation(settings: dict, streams: dict[str, Stream]) -> dict:
    """Electronic stabilisation (HyperSmooth/EIS) as the metadata tell it:
    {electronic: True/False/None (unknown), setting: EISA text or None, source: where it was read,
    image_orientation_max_deg / _mean_deg: IORI's angle from the camera body where the file has IORI}."""
    out = dict(electronic=None, setting=None, source="none in the file", image_orientation_max_deg=None,
               image_orientation_mean_deg=None)
    eise, eisa = settings.get("EISE"), settings.get("EISA")
    if isinstance(eisa, str) and eisa:
        out["setting"] = eisa
    if isinstance(eise, str) and eise[:1] in ("Y", "N"):
        out["electronic"], out["source"] = eise[:1] == "Y", "camera settings (EISE/EISA)"
    elif out["setting"] is not None:
        out["electronic"], out["source"] = out["setting"].upper() not in ("N/A", "OFF", "N"), "camera settings (EISA)"
    if "IORI" in streams and len(streams["IORI"].data):
        ang = quaternion_angle_deg(streams["IORI"].data[:, :4])
        out["image_orientation_max_deg"] = round(float(ang.max()), 3)
        out["image_orientation_mean_deg"] = round(float(ang.mean()), 3)
        if out["electronic"] is None:
            out["electronic"] = bool(ang.max() > IORI_STABILISED_DEG)
            out["source"] = "image orientation (IORI) against the camera body"
    return out


# ----------------------------------------------------------------------------- footage
class GoProFootage(VideoFootage):
    """A GoPro MP4: frames decoded from the video, IMU and GPS truth from its GPMF track.

    Beside the :class:`~lobula.readers.core.Footage` fields: ``telemetry`` (a JSON-able summary:
    model, firmware, stabilisation, lens, streams), ``gps`` (every GPS sample, with or without a fix;
    :func:`gps_samples`) and ``orientation`` ({"CORI", "IORI", "GRAV": (time_s (n,), values)} where
    the file has them, in GoPro's own frame, unrotated). ``camera`` is None only where the footage
    was opened without intrinsics (``lobula info``).
    """

    telemetry: dict
    gps: dict | None
    orientation: dict
    nominal_fps: float

    def provenance(self) -> dict:
        out = super().provenance()
        stab = self.telemetry.get("stabilisation", {})
        out.update(truth_source=self.telemetry.get("truth_source", "none"),
                   gopro_model=self.telemetry.get("model") or "unknown",
                   gopro_firmware=self.telemetry.get("firmware") or "unknown",
                   electronic_stabilisation={True: "on", False: "off"}.get(stab.get("electronic"), "unknown")
                   + (f" ({stab['setting']})" if stab.get("setting") else "")
                   + f"; from {stab.get('source', 'none')}")
        return out


def _camera_file(path: Path, camera_json: str | Path | None) -> Path | None:
    if camera_json is not None:
        return Path(camera_json)
    for p in (path.with_name(f"{path.stem}.camera.json"), path.with_name("camera.json")):
        if p.exists():
            return p
    return None


def open_gopro(path: str | Path, require_imu: bool = True, camera_json: str | Path | None = None,
               require_camera: bool = True) -> GoProFootage:
    """Open a GoPro MP4 as the camera wrote it (module doc): frames, IMU in the camera frame, GPS truth.

    camera_json: intrinsics (``--camera FILE``); else ``CLIP.camera.json`` or ``camera.json`` beside
    the clip. Its optional imu_to_camera is applied after the GPMF axis mapping, as a correction in
    the camera frame. require_imu: FootageError when the telemetry has no accelerometer (False:
    ``imu=None``). require_camera: FootageError without a camera file (False: ``camera=None``,
    for ``lobula info``). Every bad input is one FootageError naming the file and the fix.
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
    cam_path = _camera_file(path, camera_json)
    camera = None
    if cam_path is not None:
        camera = read_camera_json(cam_path)
        if (w, h) != (camera.width, camera.height):
            raise FootageError(f"{path}: video is {w}x{h} but {cam_path} says {camera.width}x{camera.height}; give "
                               f"the intrinsics of this resolution")
    elif require_camera:
        fov = settings.get("VFOV")
        raise FootageError(f"{path}: a GoPro MP4 does not carry its lens intrinsics (fx, fy, cx, cy; the lens is a "
                           f"wide-angle fisheye), and none is assumed; pass --camera FILE with a camera.json from a "
                           f"calibration of this camera at {w}x{h}" + (f" in lens mode {fov!r}" if fov else "")
                           + f", or put {path.stem}.camera.json beside the clip")
    notes = [("" if model.upper().startswith("GOPRO") else "GoPro ") + (model or "camera")
             + (f" (firmware {firmware})" if firmware else "")
             + f": video {len(times)} frames ({w}x{h}, {codec}) with its GPMF telemetry track: {packets} packets "
             f"covering {t0:.3f}..{t1:.3f} s of the video's clock"]
    if times[-1] > t1 + 0.5 / max(fps, 1.0) or times[0] < t0 - 1e-6:
        notes.append(f"the telemetry covers {t0:.3f}..{t1:.3f} s and the frames {times[0]:.3f}..{times[-1]:.3f} s: "
                     f"frames outside it have no IMU samples around them")
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
    gps = gps_samples(streams)
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
    stab = stabilisation(settings, streams)
    if stab["electronic"]:
        notes.append(f"electronic stabilisation on ({stab['setting'] or 'HyperSmooth'}; from {stab['source']}): the "
                     f"image is warped against the gyro's frame, so image rotation is not the camera body's")
    distortion = dict(model="GoPro wide-angle (fisheye) lens; the file gives no intrinsics or distortion, and the "
                            "pipeline treats the image as a pinhole camera's", removed=False)
    if settings.get("VFOV"):
        distortion["fov_mode"] = settings["VFOV"]
    if isinstance(settings.get("ZFOV"), float):
        distortion["diagonal_fov_deg"] = round(settings["ZFOV"], 3)
    orientation = {k: (streams[k].time_s, streams[k].data) for k in ("CORI", "IORI", "GRAV") if k in streams}
    stream_list = [dict(stream="video", codec=codec, frames=len(times), nominal_fps=round(fps, 3))]
    for k, s in sorted(streams.items()):
        entry = dict(stream=k, name=s.name, samples=int(len(s.time_s)), rate_hz=round(s.rate_hz or 0.0, 3),
                     units=s.units, axes=_axes_text(s) if s.order else None)
        stream_list.append({a: v for a, v in entry.items() if v not in (None, "")})
    telemetry = dict(
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
    footage = GoProFootage(path, camera, times, [], imu, truth, kind="gopro", notes=notes, distortion=distortion,
                           imu_to_camera=(GOPRO_XYZ_TO_CAMERA if r_extra is None else r_extra @ GOPRO_XYZ_TO_CAMERA)
                           if imu is not None else None, streams=stream_list)
    footage.telemetry, footage.gps, footage.orientation, footage.nominal_fps = telemetry, gps, orientation, fps
    return footage


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
                  else ""))
    lens = t.get("lens") or {}
    if lens.get("fov_mode") or lens.get("diagonal_fov_deg"):
        out.append(f"  lens:     field of view mode {lens.get('fov_mode') or '-'}"
                   + (f", {lens['diagonal_fov_deg']:.1f} deg diagonal"
                      if isinstance(lens.get("diagonal_fov_deg"), float) else "") + "; no intrinsics in the file")
    out.append(f"  truth:    {t['truth_source']}")
    return out
