"""Atomic output: write to a temporary name beside the target, then rename.

A crash or a bad input mid-run leaves no file under the final name, so nothing
half-written ever looks complete.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import xarray as xr

from lobula.version import provenance_attrs


def provenance(config_json: str, **extra) -> dict:
    """Attributes every output carries: the full configuration (JSON), the package version, the git
    commit (or "unknown"), the command line and the creation time; ``extra`` adds more (non-strings as JSON)."""
    attrs = {**provenance_attrs(), "config": config_json}
    attrs.update({k: (v if isinstance(v, (str, int, float)) else json.dumps(v, default=str))
                  for k, v in extra.items()})
    return attrs


@contextmanager
def atomic_path(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary name beside ``path`` to write to: renamed onto ``path`` when the block ends
    normally, removed when it raises. ``suffix`` ends the temporary name (some writers choose the
    format from it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        if Path(tmp).is_file():
            # mkstemp makes the file private (0600); the output gets the mode an ordinary open() gives it.
            mask = os.umask(0)
            os.umask(mask)
            os.chmod(tmp, 0o666 & ~mask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def compressed_encoding(ds: xr.Dataset, level: int = 4, min_size: int = 1024) -> dict:
    """NetCDF-4 encoding that deflates every numeric variable of at least ``min_size`` values.

    Recordings are mostly repeated values (spike rasters of 0/1, constants), so zlib at a
    moderate level shrinks them many-fold at little cost; readers decompress transparently.
    Variables that already carry an encoding (chunks, compression) keep theirs.
    """
    enc = {}
    for name, var in ds.variables.items():
        if var.dtype.kind in "biuf" and var.size >= min_size and not ({"zlib", "compression", "chunksizes"}
                                                                       & set(var.encoding)):
            enc[name] = {"zlib": True, "complevel": level}
    return enc


def write_netcdf(ds: xr.Dataset, path: str | Path) -> Path:
    """Write ``ds`` to NetCDF (h5netcdf engine) atomically, numeric variables deflated (:func:`compressed_encoding`)."""
    with atomic_path(path) as tmp:
        ds.to_netcdf(tmp, engine="h5netcdf", encoding=compressed_encoding(ds))
    return Path(path)


def write_text(path: str | Path, text: str) -> Path:
    """Write text (UTF-8, newlines as given) atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8", newline="")
    return Path(path)


def write_csv(rows: list[dict], path: str | Path) -> Path:
    """Write rows (dicts sharing the first row's keys) as CSV with a header, atomically."""
    import csv

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return Path(path)


def seed_summary(values, name: str) -> dict:
    """``{name}_mean``, ``{name}_sd`` (ddof 1; NaN below two) and ``{name}_n`` of the finite values:
    how the suites report a metric over seeds."""
    import numpy as np

    x = np.asarray(values, float).ravel()
    x = x[np.isfinite(x)]
    return {f"{name}_mean": float(x.mean()) if x.size else float("nan"),
            f"{name}_sd": float(x.std(ddof=1)) if x.size > 1 else float("nan"),
            f"{name}_n": int(x.size)}


def save_figure(fig, path: str | Path, **kwargs) -> Path:
    """Save a matplotlib figure atomically (format from the suffix)."""
    with atomic_path(path, suffix=Path(path).suffix) as tmp:
        fig.savefig(tmp, **kwargs)
    return Path(path)


# ----------------------------------------------------------------------------- streamed outputs
class MemorySink:
    """Collects per-time records; builds the Dataset at the end and writes it atomically as NetCDF
    (or no file). ``maps``: variables over (time, y, x), stored as one compressed chunk per map."""

    def __init__(self, maps: tuple[str, ...] = ()):
        self.records: list[dict] = []
        self.maps = maps

    def add(self, rec: dict) -> None:
        self.records.append(rec)

    def finish(self, build, extra_vars: dict, attrs: dict, out: Path | None) -> xr.Dataset:
        ds = build(self.records)
        ds = ds.assign(extra_vars)
        ds.attrs.update(attrs)
        H, W = ds.sizes["y"], ds.sizes["x"]
        for k in self.maps:
            ds[k].encoding.update(zlib=True, complevel=1, chunksizes=(1, H, W))
        if out is not None:
            write_netcdf(ds, out)
        return ds


# Zarr format 2: its string arrays (the ring labels) and consolidated metadata are part of
# the specification there, not yet in format 3.
ZARR_KW = dict(zarr_format=2)


class ZarrSink:
    """Appends batches of per-time records to a Zarr store in a temporary directory, renamed into
    place only when complete. ``maps``: variables over (time, y, x), one chunk per map; ``static``:
    coordinates written with the first batch only."""

    def __init__(self, out: Path, batch: int, maps: tuple[str, ...] = (), static: tuple[str, ...] = ()):
        import zarr  # noqa: F401  (fail early with ImportError if absent)

        self.out, self.batch = Path(out), max(1, int(batch))
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = self.out.parent / f".{self.out.name}.partial-{os.getpid()}"
        shutil.rmtree(self.tmp, ignore_errors=True)
        self.pending: list[dict] = []
        self.started = False
        self.build = None
        self.maps, self.static = maps, static

    def add(self, rec: dict) -> None:
        self.pending.append(rec)
        if len(self.pending) >= self.batch:
            self._flush()

    def _flush(self) -> None:
        if not self.pending:
            return
        ds = self.build(self.pending)
        if self.started:
            ds.drop_vars([v for v in self.static if v in ds.variables]) \
              .to_zarr(self.tmp, append_dim="time", consolidated=False, **ZARR_KW)
        else:
            H, W = ds.sizes["y"], ds.sizes["x"]
            enc = {k: {"chunks": (1, H, W)} for k in self.maps}
            ds.to_zarr(self.tmp, mode="w-", encoding=enc, consolidated=False, **ZARR_KW)
            self.started = True
        self.pending = []

    def finish(self, build, extra_vars: dict, attrs: dict, out) -> xr.Dataset:
        import zarr

        try:
            self._flush()
            if not self.started:
                raise ValueError(f"{self.out}: nothing to write")
            if extra_vars:
                xr.Dataset(extra_vars).to_zarr(self.tmp, mode="a", consolidated=False, **ZARR_KW)
            g = zarr.open_group(str(self.tmp), mode="r+")
            g.attrs.update({k: v for k, v in attrs.items()})
            zarr.consolidate_metadata(str(self.tmp))
            trash = None
            if self.out.exists():
                trash = self.out.parent / f".{self.out.name}.old-{os.getpid()}"
                self.out.rename(trash)
            self.tmp.rename(self.out)
            if trash is not None:
                shutil.rmtree(trash, ignore_errors=True)
        except BaseException:
            self.abort()
            raise
        return xr.open_zarr(self.out)

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)
