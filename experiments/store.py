"""Atomic output: write to a temporary name beside the target, then rename.

A crash or a bad input mid-run leaves no file under the final name, so nothing
half-written ever looks complete. The temporary is a hidden name beside the output,
``.<name>.lobula-tmp-<pid>-<random><suffix>``: removed when the block raises (a signal that
``lobula`` catches raises too, see :func:`experiments.cli.main`), and, where a run was killed
outright (SIGKILL, power loss), by the next run that writes the same output
(:func:`stimuli.footage_writer.remove_stale`). Inside :func:`all_or_nothing` several outputs
appear together or none of them. A full disk, a read-only folder or a refused permission
raise :class:`OutputError`, whose message names the output, never its temporary.

Every NetCDF (and Zarr) store the project writes follows the CF-1.10 conventions: the
writers here set ``Conventions`` and walk each variable and coordinate with
:func:`cf_problems` (a ``long_name`` on all, UDUNITS ``units`` on the numeric ones).
"""
from __future__ import annotations

import errno
import json
import os
import re
import shutil
import signal
import tempfile
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from contextvars import ContextVar
from pathlib import Path
from typing import TYPE_CHECKING

from lobula.version import provenance, provenance_attrs  # noqa: F401  (provenance: re-exported for the commands)
from stimuli.footage_writer import remove_stale

if TYPE_CHECKING:  # xarray is imported where a Dataset is written: the command line's error handling needs none
    import xarray as xr


#: what every temporary name of :func:`atomic_path` holds between the output's name and the writer's pid
TEMP_TAG = "lobula-tmp"

#: the outputs :func:`atomic_path` has put in place in this process, in order
WRITTEN: list[Path] = []

# The open all_or_nothing() group of this thread of control: (temporary, output) pairs to rename at its end.
_GROUP: ContextVar[list | None] = ContextVar("lobula_output_group", default=None)


class OutputError(OSError):
    """An output that cannot be written: a full disk, a read-only folder, a refused permission.

    ``problem`` names the output (never its temporary) and what is wrong; ``fix`` says what to
    do; ``str()`` is both, one line. ``filename`` is the output's path.
    """

    def __init__(self, code: int, path: str | Path, problem: str, fix: str = "choose another place for it"):
        super().__init__(code, problem, str(path))
        self.problem, self.fix = problem, fix

    def __str__(self) -> str:
        return f"{self.problem}; {self.fix}"


_NO_SPACE = (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC))


def output_error(exc: OSError, path: str | Path) -> OSError:
    """``exc`` as an :class:`OutputError` naming ``path`` where it says the output cannot be written
    (no space, read-only, no permission, too large); any other OSError is returned as it is."""
    if isinstance(exc, OutputError):
        return exc
    path = Path(path)
    if exc.errno in _NO_SPACE:
        return OutputError(exc.errno, path, f"no space left on device writing {path}",
                           "free some space or choose another place for it")
    if exc.errno == errno.EROFS:
        return OutputError(exc.errno, path, f"cannot write {path}: folder is read-only")
    if exc.errno in (errno.EACCES, errno.EPERM):
        return OutputError(exc.errno, path, f"cannot write {path}: no permission to write in {path.parent}")
    if exc.errno == errno.EFBIG:
        return OutputError(exc.errno, path, f"cannot write {path}: too large for its file system")
    return exc


def output_of(path: str | Path) -> Path:
    """The output a hidden temporary name stands for (:func:`atomic_path`'s, a partial or rendering folder's,
    one inside another); any other path as it is."""
    path = Path(path)
    while m := re.fullmatch(rf"\.(.+)\.(?:{TEMP_TAG}-\d+-.*|partial-\d+|track-\d+)", path.name, re.S):
        path = path.with_name(m.group(1))
    return path


def writable_problem(path: str | Path, folder: bool = False) -> OutputError | None:
    """Why ``path`` cannot be written, checked before a run, or None where it can.

    folder: ``path`` is an output folder (its entries are made in it) rather than a file
    (made beside it, in its parent). The nearest folder that exists is where a file is made
    (missing parents are created); an empty temporary file is made and removed there, so a
    read-only mount, a refused permission and a full disk are all found, as root too.
    """
    path = Path(path)
    if not folder and path.is_dir():
        return OutputError(errno.EISDIR, path, f"cannot write {path}: a folder of that name exists",
                           "give a file name")
    if not folder and path.exists() and not path.is_file():
        # A device or a pipe would be replaced by a file of that name (the output is renamed onto it).
        return OutputError(errno.EEXIST, path, f"cannot write {path}: it is a device or a pipe, not a file",
                           "give a file name")
    d = path if folder else path.parent
    d = Path(os.path.abspath(d))
    while not d.exists() and d != d.parent:
        d = d.parent
    if not d.is_dir():
        return OutputError(errno.ENOTDIR, path, f"cannot write {path}: {d} is a file, not a folder")
    probe = None
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{TEMP_TAG}-check-{os.getpid()}-", dir=d)
        os.close(fd)
        os.unlink(probe)
        probe = None
        st = os.statvfs(d)
        if st.f_bavail == 0 and st.f_blocks > 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    except OSError as exc:
        err = output_error(exc, path)
        if isinstance(err, OutputError):
            return err
        return OutputError(exc.errno or errno.EIO, path, f"cannot write {path}: {exc.strerror or exc}")
    finally:
        if probe is not None:  # interrupted between making the probe and removing it
            with suppress(OSError):
                os.unlink(probe)
    return None


def remove_empty_folders(roots: dict, since: float) -> list[Path]:
    """After a run that failed or was stopped: remove the empty folders it made under each output folder.

    roots: {output folder: whether the run made it}; a folder is the run's when its entries changed at or
    after ``since`` (s, the epoch; its status change time); a root the run made goes too once empty.
    Folders holding anything are kept. Returns the folders removed, deepest first."""
    removed = []
    for root, made in roots.items():
        root = Path(root)
        if not root.is_dir() or root.is_symlink():
            continue
        for d, subdirs, files in os.walk(root, topdown=False):
            d = Path(d)
            if d == root and not made:
                continue
            with suppress(OSError):
                if not any(d.iterdir()) and (d == root or d.stat().st_ctime >= since):
                    d.rmdir()
                    removed.append(d)
    return removed


@contextmanager
def atomic_path(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary name beside ``path`` to write to: renamed onto ``path`` when the block ends
    normally (inside :func:`all_or_nothing`: when the group ends), removed when it raises.
    ``suffix`` ends the temporary name (some writers choose the format from it).

    Temporaries of ``path`` that a killed run left (their process gone, older than this one)
    are removed first. An OSError saying the output cannot be written (no space, read-only,
    no permission) is raised as :class:`OutputError` naming ``path``. A symbolic link is written
    through: its target gets the output and the link stays.
    """
    path = Path(path)
    if path.is_symlink():
        path = Path(os.path.realpath(path))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale(path.parent, f".{path.name}.{TEMP_TAG}-")
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{TEMP_TAG}-{os.getpid()}-", suffix=suffix, dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise output_error(exc, path) from None
    try:
        yield Path(tmp)
        if Path(tmp).is_file():
            # mkstemp makes the file private (0600); the output gets the mode an ordinary open() gives it.
            mask = os.umask(0)
            os.umask(mask)
            os.chmod(tmp, 0o666 & ~mask)
        group = _GROUP.get()
        if group is not None:
            group.append((Path(tmp), path))
        else:
            os.replace(tmp, path)
            WRITTEN.append(path)
    except BaseException as exc:
        _remove(Path(tmp))
        if isinstance(exc, OSError):
            raise output_error(exc, path) from None
        raise


def _remove(p: Path) -> None:
    """Remove a temporary file or folder, whichever it is (some writers make a folder of the name)."""
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


@contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM held while the block runs, and handed to their handlers when it ends.

    For a block that runs other code's finalisers (``__del__``, run when the last reference goes or by
    ``gc.collect``): Python ignores an exception raised inside a finaliser ("Exception ignored in …"), so an
    interrupt whose handler ran there would be lost and the run would go on. Only signals with a Python
    handler are held (the default SIGTERM ends the process anyway); in a thread other than the main one,
    where handlers cannot be changed, the block runs as it is.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = {s: h for s in (signal.SIGINT, signal.SIGTERM) if callable(h := signal.getsignal(s))}
    caught: list[int] = []
    for s in held:
        signal.signal(s, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for s, h in held.items():
            signal.signal(s, h)
        if caught:
            held[caught[0]](caught[0], None)


@contextmanager
def all_or_nothing() -> Iterator[list]:
    """Outputs written with :func:`atomic_path` inside the block appear together when it ends normally,
    or none of them: each stays under its temporary name until then, and all are removed if the block
    raises (a signal included) or one cannot be put in place. Yields the list of (temporary, output)
    pairs waiting. Only the thread (context) that opens the group defers; outputs written by other
    threads are put in place at once."""
    group: list = []
    token = _GROUP.set(group)
    try:
        yield group
    except BaseException:
        for tmp, _ in group:
            _remove(tmp)
        raise
    finally:
        _GROUP.reset(token)
    placed = []
    try:
        for tmp, path in group:
            os.replace(tmp, path)
            placed.append(path)
    except BaseException as exc:
        for tmp, _ in group:
            _remove(tmp)
        for path in placed:  # new outputs only: what they replaced is gone either way
            _remove(path)
        if isinstance(exc, OSError):
            raise output_error(exc, path) from None
        raise
    WRITTEN.extend(placed)


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


# ----------------------------------------------------------------------------- CF metadata
#: the CF version every output declares in its ``Conventions`` attribute
CF_CONVENTIONS = "CF-1.10"
#: environment variable: when set (not "", "0", "false", "no"), an output with CF problems raises
#: instead of warning; the test suite sets it (tests/conftest.py), so every file a test writes is walked
STRICT_CF_ENV = "LOBULA_STRICT_CF"

# The UDUNITS-2 names the outputs use (a subset of its database; each checked against UDUNITS-2
# itself). SI symbols take an SI prefix ("ms", "km"); the others are whole names.
_SI_SYMBOLS = {"m", "s", "g", "rad", "sr", "Hz", "K", "N", "J", "W", "Pa", "V", "A", "C", "mol", "cd", "lm", "lx",
               "meter", "metre", "second", "radian", "hertz"}
_WHOLE_UNITS = {"1", "degree", "degrees", "arcdeg", "arc_degree", "degrees_north", "degrees_east", "degree_C",
                "percent", "count", "min", "h", "day"}
_SI_PREFIXES = ("da", "Y", "Z", "E", "P", "T", "G", "M", "k", "h", "d", "c", "m", "u", "µ", "n", "p", "f", "a", "z", "y")
_UNIT_TOKEN = re.compile(r"\s*(?:(?P<num>[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?)"
                         r"|(?P<sym>[A-Za-zµ_]+)(?:\^?(?P<exp>[-+]?\d+))?|(?P<op>[./*·]))\s*")


def _known_unit(symbol: str) -> bool:
    if symbol in _SI_SYMBOLS or symbol in _WHOLE_UNITS:
        return True
    return any(symbol.startswith(p) and symbol[len(p):] in _SI_SYMBOLS for p in _SI_PREFIXES)


def units_problem(units) -> str | None:
    """Why ``units`` is not a UDUNITS-2 string the project uses, or None when it is.

    Accepts products, quotients and powers of known names (``"m/s"``, ``"m s-1"``,
    ``"1/s2"``, ``"rad s-1"``, ``"ms"``, ``"degree"``, ``"1"``); rejects what UDUNITS
    cannot parse ("deg", "pixel", "px") and empty strings.
    """
    if not isinstance(units, str) or not units.strip():
        return f"units {units!r} is not a non-empty string"
    pos, text = 0, units.strip()
    while pos < len(text):
        m = _UNIT_TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            return f"units {units!r}: cannot parse {text[pos:]!r}"
        if m.group("sym") and not _known_unit(m.group("sym")):
            return f"units {units!r}: {m.group('sym')!r} is not a UDUNITS unit"
        pos = m.end()
    return None


def cf_problems(ds: xr.Dataset) -> list[str]:
    """What keeps ``ds`` from being self-describing CF-1.10 (empty list: nothing).

    Checked: the Dataset's ``Conventions`` names CF; every variable and coordinate has a
    non-empty ``long_name``; every numeric or boolean one has ``units`` that UDUNITS-2
    parses (:func:`units_problem`; "1" for dimensionless numbers, counts, indices and
    booleans), or, for a flag, ``flag_values`` with ``flag_meanings``. Strings need no
    units; datetimes and timedeltas take theirs from xarray's encoding.

    A stack of metrics in different units along one dimension (``lobula suite``'s
    ``value``) has no single CF ``units``: it names instead, in ``units_coordinate``, a
    string coordinate along one of its dimensions holding each element's units, each of
    which must parse.

    Parameters
    ----------
    ds : xarray.Dataset
        the Dataset as it is to be written.

    Returns
    -------
    list of str
        one sentence per problem, naming the variable.
    """
    problems = []
    conventions = ds.attrs.get("Conventions")
    if not (isinstance(conventions, str) and conventions.startswith("CF-")):
        problems.append(f"Dataset: no Conventions attribute naming CF (want {CF_CONVENTIONS!r})")
    for name, var in ds.variables.items():
        what = f"{'coordinate' if name in ds.coords else 'variable'} {name!r}"
        long_name = var.attrs.get("long_name")
        if not (isinstance(long_name, str) and long_name.strip()):
            problems.append(f"{what}: no long_name")
        if var.dtype.kind in "biufc":
            if "units" in var.attrs:
                why = units_problem(var.attrs["units"])
                if why:
                    problems.append(f"{what}: {why}")
            elif "units_coordinate" in var.attrs:
                per = ds.variables.get(var.attrs["units_coordinate"])
                if per is None or per.ndim != 1 or per.dims[0] not in var.dims or per.dtype.kind not in "OUS":
                    problems.append(f"{what}: units_coordinate {var.attrs['units_coordinate']!r} is not a string "
                                    f"coordinate along one of its dimensions {var.dims}")
                else:
                    problems += [f"{what}: {why}" for why in map(units_problem, per.values.tolist()) if why]
            elif not {"flag_values", "flag_meanings"} <= set(var.attrs):
                problems.append(f"{what}: no units (\"1\" if dimensionless; flag_values and flag_meanings for a flag)")
    return problems


def strict_cf() -> bool:
    """Whether :data:`STRICT_CF_ENV` asks outputs with CF problems to raise."""
    return os.environ.get(STRICT_CF_ENV, "").strip().lower() not in ("", "0", "false", "no")


def cf_ready(ds: xr.Dataset, path: str | Path) -> xr.Dataset:
    """``ds`` (a shallow copy) with ``Conventions`` set to :data:`CF_CONVENTIONS`, checked by :func:`cf_problems`.

    Problems raise ValueError when :func:`strict_cf` (the test suite), else they warn
    (UserWarning) and the file is written anyway: incomplete metadata never costs a user
    a run's results.
    """
    ds = ds.assign_attrs(Conventions=CF_CONVENTIONS)
    problems = cf_problems(ds)
    if problems:
        msg = f"{path}: metadata not CF-1.10 (describe these where the Dataset is built): " + "; ".join(problems)
        if strict_cf():
            raise ValueError(msg)
        warnings.warn(msg, UserWarning, stacklevel=3)
    return ds


def write_netcdf(ds: xr.Dataset, path: str | Path) -> Path:
    """Write ``ds`` to NetCDF (h5netcdf engine) atomically, numeric variables deflated (:func:`compressed_encoding`).

    The file declares ``Conventions = "CF-1.10"``; its variables and coordinates are walked
    by :func:`cf_problems` first (:func:`cf_ready`: a warning, or with ``LOBULA_STRICT_CF=1``
    a ValueError and no file). ``ds`` itself is not modified. The encoded file is built in memory
    (as large as the compressed output) and then written in one go.
    """
    ds = cf_ready(ds, path)
    enc = compressed_encoding(ds)
    for name in ds.dims:
        # CF: coordinate variables have no missing values, so they carry no _FillValue either.
        if name in ds.variables and ds[name].dtype.kind == "f" and "_FillValue" not in ds[name].encoding:
            enc.setdefault(name, {})["_FillValue"] = None
    # HDF5 writes into memory and the bytes go to disk with an ordinary write, so a full disk is one clean
    # OSError: HDF5 writing the file itself fails on every object it closes and crashes the interpreter at exit.
    data = ds.to_netcdf(engine="h5netcdf", encoding=enc)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
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


def figure_metadata(suffix: str, attrs: dict | None = None) -> dict | None:
    """What a figure file of this format (``suffix``: ".png", ".pdf", ".svg") carries of where it came from: the
    version, commit, command line and creation time (:func:`lobula.version.provenance_attrs`) and whatever
    ``attrs`` adds (an output's own attributes, e.g. its ``config``). PNG keeps each as a text chunk under its
    attribute's name; PDF and SVG, whose metadata keys are fixed, keep them as one JSON in ``Keywords`` /
    ``Description``. None for a format that carries none."""
    from lobula.version import provenance_attrs

    # The figure's own version, commit and command line win over those of the data it draws.
    prov = {**{k: v if isinstance(v, str) else json.dumps(v, default=str) for k, v in (attrs or {}).items()},
            **provenance_attrs()}
    creator = f"lobula {prov['lobula_version']} ({prov['git_commit']})"
    suffix = suffix.lower()
    if suffix == ".png":
        return {"Software": creator, **prov}
    if suffix == ".pdf":
        return {"Creator": creator, "Subject": prov["command_line"], "Keywords": json.dumps(prov)}
    if suffix == ".svg":
        return {"Creator": creator, "Description": json.dumps(prov)}
    return None


def save_figure(fig, path: str | Path, provenance: dict | None = None, **kwargs) -> Path:
    """Save a matplotlib figure atomically (format from the suffix), carrying the version, commit, command
    line and creation time in its metadata, with ``provenance`` (an output's attributes, e.g. its ``config``)
    beside them (:func:`figure_metadata`)."""
    metadata = figure_metadata(Path(path).suffix, provenance)
    if metadata is not None:
        kwargs.setdefault("metadata", metadata)
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
        for kind in ("partial", "old"):  # what a killed run left of this store
            remove_stale(self.out.parent, f".{self.out.name}.{kind}-")
        self.tmp = self.out.parent / f".{self.out.name}.partial-{os.getpid()}"
        shutil.rmtree(self.tmp, ignore_errors=True)
        self.pending: list[dict] = []
        self.started = False
        self.build = None
        self.maps, self.static = maps, static

    def add(self, rec: dict) -> None:
        self.pending.append(rec)
        if len(self.pending) >= self.batch:
            try:
                self._flush()
            except BaseException as exc:  # a full disk mid-run: no half-written store left behind
                self.abort()
                if isinstance(exc, OSError):
                    raise output_error(exc, self.out) from None
                raise

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
        import xarray as xr
        import zarr

        try:
            self._flush()
            if not self.started:
                raise ValueError(f"{self.out}: nothing to write")
            if extra_vars:
                xr.Dataset(extra_vars).to_zarr(self.tmp, mode="a", consolidated=False, **ZARR_KW)
            g = zarr.open_group(str(self.tmp), mode="r+")
            g.attrs.update({k: v for k, v in attrs.items()})
            g.attrs["Conventions"] = CF_CONVENTIONS
            zarr.consolidate_metadata(str(self.tmp))
            with xr.open_zarr(self.tmp, decode_times=False, decode_timedelta=False) as done:
                cf_ready(done, self.out)
            trash = None
            if self.out.exists():
                trash = self.out.parent / f".{self.out.name}.old-{os.getpid()}"
                self.out.rename(trash)
            self.tmp.rename(self.out)
            if trash is not None:
                shutil.rmtree(trash, ignore_errors=True)
        except BaseException as exc:
            self.abort()
            if isinstance(exc, OSError):
                raise output_error(exc, self.out) from None
            raise
        WRITTEN.append(self.out)
        return xr.open_zarr(self.out)

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)
