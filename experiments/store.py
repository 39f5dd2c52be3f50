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

from lobula import __version__


def provenance(config_json: str, **extra) -> dict:
    """Attributes every output carries: the package version and the full configuration (JSON)."""
    attrs = {"lobula_version": __version__, "config": config_json}
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
