"""GPMF, GoPro's key–length–value telemetry format, decoded by GoPro's own gpmf-parser.

:func:`decode_gpmf` turns one telemetry packet into its data streams (scaled, in the stored axis
order the stream's ORIN/ORIO/MTRX give) with the properties each stream carries;
:func:`decode_settings` reads the camera's settings block. The binding ``py-gpmf-parser`` is
imported only when a payload is decoded (:data:`GPMF_INSTALL_HINT` says how to install it).
"""
from __future__ import annotations

import numpy as np

from .core import FootageError

#: GPMF streams this reader keeps (data keys) and the per-stream properties it reads beside them.
DATA_KEYS = ("ACCL", "GYRO", "GPS5", "GPS9", "CORI", "IORI", "GRAV")
STICKY_KEYS = ("ORIN", "ORIO", "MTRX", "TIMO", "STNM", "SIUN", "UNIT", "GPSF", "GPSP")

#: GPMF type characters of fixed-size numbers, as big-endian numpy dtypes.
_DTYPES = {"b": ">i1", "B": ">u1", "s": ">i2", "S": ">u2", "l": ">i4", "L": ">u4", "f": ">f4", "d": ">f8",
           "j": ">i8", "J": ">u8"}

GPMF_INSTALL_HINT = ("reading GoPro telemetry needs py-gpmf-parser (GoPro's gpmf-parser; wheels for Linux x86-64, "
                     "Python 3.8–3.12): pip install 'py-gpmf-parser>=0.1.1,<1'")


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
    """The camera's settings from ``payload``, the ``udta`` GPMF block (bytes, or None): {four-character key:
    text or number}
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
