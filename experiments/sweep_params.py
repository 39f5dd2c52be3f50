"""Swept parameters: dotted paths into a run's two configurations, their values, and grid keys.

A path names a leaf of the velocity configuration (:class:`lobula.config.VelocityConfig`, e.g.
``fields.size_deg``) or of the synthetic run (:class:`stimuli.track.TrackRunConfig`, e.g.
``scene.noise_grey``), optionally prefixed ``velocity.`` or ``run.``; ``seed`` sets both seeds.
Values are converted to the type of the field's default. Nested (frozen) dataclasses are
replaced, never mutated, so configurations derived from one base never share state.
"""
from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
from dataclasses import dataclass

import numpy as np

from lobula.config import VelocityConfig
from lobula.front_ends import get_front_end
from stimuli.track import TrackRunConfig

ALIASES = {"seed": ("run.scene.seed", "run.imu.seed")}
SWEEP_FRONT_ENDS = ("dis", "farneback", "emd")


class SweepError(ValueError):
    """A bad sweep specification (unknown path, bad value); the message says which and what to do."""


# ---------------------------------------------------------------------- paths into configurations
def _is_dc(x) -> bool:
    return dataclasses.is_dataclass(x) and not isinstance(x, type)


def list_paths(obj, prefix: str = "") -> dict:
    """Every leaf path of a (nested) dataclass instance and its value."""
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        p = f"{prefix}{f.name}"
        if _is_dc(v):
            out.update(list_paths(v, p + "."))
        else:
            out[p] = v
    return out


def get_path(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def set_path(obj, path: str, value):
    """A copy of ``obj`` with the leaf at ``path`` set, via dataclasses.replace at every level
    (works for frozen dataclasses and re-runs their validation)."""
    head, _, rest = path.partition(".")
    if not rest:
        return dataclasses.replace(obj, **{head: value})
    return dataclasses.replace(obj, **{head: set_path(getattr(obj, head), rest, value)})


def _resolve(path: str, velocity: VelocityConfig, run: TrackRunConfig) -> tuple[str, ...]:
    """Targets ("velocity.x.y" / "run.x.y") of a user path; raises SweepError for unknown paths."""
    if path in ALIASES:
        return ALIASES[path]
    leaves = {f"velocity.{k}": v for k, v in list_paths(velocity).items()}
    leaves.update({f"run.{k}": v for k, v in list_paths(run).items()})
    candidates = [path] if path.startswith(("velocity.", "run.")) else [f"velocity.{path}", f"run.{path}"]
    hits = [c for c in candidates if c in leaves]
    if len(hits) == 1:
        return (hits[0],)
    if len(hits) > 1:
        raise SweepError(f"--param {path}: ambiguous; write velocity.{path} or run.{path}")
    branches = {p.rsplit(".", 1)[0] for p in leaves} | {".".join(p.split(".")[:k]) for p in leaves for k in (2, 3)}
    if any(c in branches for c in candidates):
        raise SweepError(f"--param {path}: a group of settings, not one value; name a field inside it "
                         f"(see lobula sweep --list-params)")
    short = [p.split(".", 1)[1] for p in leaves] + list(ALIASES)
    near = difflib.get_close_matches(path.split(".", 1)[1] if path.startswith(("velocity.", "run.")) else path,
                                     short, n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(near)}?" if near else "; lobula sweep --list-params lists them"
    raise SweepError(f"--param {path}: not a field of the velocity or run configuration{hint}")


def _coerce(text, default, label: str):
    """Convert one value (text, or a JSON-decoded object) to the type of the field's default."""
    if not isinstance(text, str):
        v = text
        if isinstance(default, tuple) and isinstance(v, list):
            return tuple(v)
        if isinstance(default, float) and isinstance(v, int) and not isinstance(v, bool):
            return float(v)
        return v
    t = text.strip()
    low = t.lower()
    try:
        if isinstance(default, bool):
            if low in ("true", "1", "yes", "on"):
                return True
            if low in ("false", "0", "no", "off"):
                return False
            raise ValueError("expected true or false")
        if low in ("none", "null"):
            return None
        if isinstance(default, int):
            f = float(t)
            if not f.is_integer():
                raise ValueError("expected an integer")
            return int(f)
        if isinstance(default, float):
            return float(t)
        if isinstance(default, (tuple, list)):
            return tuple(json.loads(t))
        for conv in (int, float):
            try:
                return conv(t)
            except ValueError:
                pass
        return t
    except (ValueError, TypeError) as exc:
        raise SweepError(f"--param {label}: cannot use {t!r} ({exc}; the default is {default!r})") from None


def _split_values(text: str):
    t = text.strip()
    if t.startswith("["):
        try:
            vals = json.loads(t)
        except ValueError as exc:
            raise SweepError(f"bad JSON list {t!r}: {exc}") from None
        if not isinstance(vals, list):
            raise SweepError(f"{t!r}: expected a JSON list")
        return vals
    if t.startswith(("lin:", "log:")):
        try:
            kind, a, b, n = t.split(":")
            a, b, n = float(a), float(b), int(n)
        except ValueError:
            raise SweepError(f"{t!r}: ranges are lin:START:STOP:N or log:START:STOP:N") from None
        vals = np.linspace(a, b, n) if kind == "lin" else np.geomspace(a, b, n)
        return [float(f"{v:.12g}") for v in vals]
    return [v for v in t.split(",") if v.strip()]


@dataclass
class Param:
    """One swept parameter: its name (the dim), the configuration fields it sets, its values."""

    name: str
    targets: tuple[str, ...]
    values: list

    def to_dict(self) -> dict:
        return dict(name=self.name, targets=list(self.targets), values=[jsonable(v) for v in self.values])


def jsonable(v):
    return list(v) if isinstance(v, tuple) else v


def parse_param(text: str, velocity: VelocityConfig | None = None, run: TrackRunConfig | None = None) -> Param:
    """``PATH=V1,V2,...`` → :class:`Param`, with values converted to the field's type."""
    velocity = velocity or VelocityConfig()
    run = run or TrackRunConfig()
    path, eq, values = text.partition("=")
    path = path.strip()
    if not eq or not path or not values.strip():
        raise SweepError(f"--param {text!r}: write PATH=V1,V2,... (e.g. fields.size_deg=3,5,10)")
    targets = _resolve(path, velocity, run)
    default = _target_value(targets[0], velocity, run)
    vals = [_coerce(v, default, path) for v in _split_values(values)]
    if not vals:
        raise SweepError(f"--param {text!r}: no values")
    keys = [json.dumps(jsonable(v)) for v in vals]
    if len(set(keys)) != len(keys):
        raise SweepError(f"--param {path}: a value is listed twice ({values})")
    if path in ("front_end", "velocity.front_end"):
        bad = [v for v in vals if v not in SWEEP_FRONT_ENDS]
        if bad:
            raise SweepError(f"--param front_end: {bad} cannot be swept; choose from {', '.join(SWEEP_FRONT_ENDS)} "
                             f"(flo needs precomputed flow for each render)")
    return Param(path, targets, vals)


def _target_value(target: str, velocity, run):
    side, _, sub = target.partition(".")
    return get_path(velocity if side == "velocity" else run, sub)


def apply_value(target: str, value, velocity, run):
    side, _, sub = target.partition(".")
    if side == "velocity":
        if sub == "front_end":   # with the front end's own epipole and readout defaults, as `lobula compare` runs it
            return velocity.for_front_end(value), run
        return set_path(velocity, sub, value), run
    return velocity, set_path(run, sub, value)


# ---------------------------------------------------------------------- the grid
def config_hash(obj, n: int = 20) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:n]


def effective_velocity(cfg: VelocityConfig) -> dict:
    """The part of a velocity configuration a run depends on (for deduplicating points):
    each front end reads only its own sections (lobula.front_ends.FrontEnd.sections: a flow front end
    ignores ``emd``, the EMD ``flow``); ``flow.method`` follows ``front_end``."""
    d = cfg.to_dict()
    sections = get_front_end(cfg.front_end).sections
    for section in ("flow", "emd"):
        if section not in sections:
            d.pop(section, None)
    d.get("flow", {}).pop("method", None)   # the front end sets it
    return d


def run_key(run: TrackRunConfig) -> str:
    return config_hash(run.to_dict(), 16)


def run_config_from_dict(d: dict) -> TrackRunConfig:
    """A :class:`TrackRunConfig` from its ``to_dict()`` (or a render's ``scene.json`` ``config``)."""
    from stimuli.imu import IMUConfig
    from stimuli.scene import SceneConfig

    d = dict(d)
    scene, imu = dict(d.pop("scene", None) or {}), dict(d.pop("imu", None) or {})
    if "texture_wavelengths_m" in scene:
        scene["texture_wavelengths_m"] = tuple(scene["texture_wavelengths_m"])
    try:
        return TrackRunConfig(**d, scene=SceneConfig(**scene), imu=IMUConfig(**imu))
    except TypeError as exc:
        raise SweepError(f"not a TrackRunConfig: {exc}") from None
