"""The box index of an MP4/MOV as far as a GoPro recording needs it, read from the box headers alone.

:func:`read_mp4_index` walks the top-level boxes and the ``moov`` box for the tracks whose sample
type is ``gpmd`` (GPMF telemetry) and the GPMF settings block in ``moov/udta``; no decoder is
started, so :func:`has_gpmf_track` is cheap enough for the readers' registry to ask of every MP4.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from .core import FootageError

#: Sample-description type of the MP4 track that holds GPMF.
GPMF_SAMPLE_TYPE = b"gpmd"


@dataclass
class Mp4Index:
    """What the MP4's box headers say: ``gpmd_tracks``, the track IDs whose sample type is ``gpmd``, and
    ``udta_gpmf``, the GPMF settings block of ``moov/udta`` (bytes, or None where the file has none)."""

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
    """The GPMF-relevant part of the index of the MP4/MOV at ``path`` (see :class:`Mp4Index`); None where the file
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
