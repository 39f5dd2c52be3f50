"""Atomic output: write to a temporary name beside the target, then rename.

A crash or a bad input mid-run leaves no file under the final name, so nothing
half-written ever looks complete.
"""
from __future__ import annotations

import json
import os
import tempfile
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


def write_netcdf(ds: xr.Dataset, path: str | Path) -> Path:
    """Write ``ds`` to NetCDF (h5netcdf engine) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        ds.to_netcdf(tmp, engine="h5netcdf")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def save_figure(fig, path: str | Path, **kwargs) -> Path:
    """Save a matplotlib figure atomically (format from the suffix)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, **kwargs)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
