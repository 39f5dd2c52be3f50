"""torch is the `bio` extra: the camera pipeline installs and runs without it, the biological front end says
how to get it.

Each test runs Python in a subprocess whose import system finds no torch (a ``sys.meta_path`` finder
installed before anything else is imported), as on ``pip install lobula`` without extras; the
tests' own environment has torch, so these are the only tests that see the package without it.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from stimuli.track import TrackRunConfig, make_track_run

#: prepended to every subprocess's code: torch is not installed there
NO_TORCH = '''
import sys


class _NoTorch:
    """The import system's first finder: torch and its submodules are found nowhere."""

    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


sys.meta_path.insert(0, _NoTorch())
try:
    import torch  # noqa: F401
except ModuleNotFoundError:
    pass
else:
    raise SystemExit("torch is still importable")
'''

INSTALL = "pip install 'lobula[bio]'"


def run_without_torch(code: str, cwd, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", NO_TORCH + code], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


def last_json(proc: subprocess.CompletedProcess) -> dict:
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_camera_pipeline_renders_estimates_compares_and_ranges_without_torch(tmp_path):
    # lobula scene, velocity (DIS), compare (Farnebäck), depth (ratio), info: the camera pipeline end to end.
    code = '''
import json
import numpy as np
import xarray as xr
from experiments.cli import main
from lobula._optional import optional_torch

rc = {}
rc["scene"] = main(["scene", "track", "--duration", "2", "--scale", "0.25", "--builtin-profile", "--start", "4",
                    "--quiet"])
rc["velocity"] = main(["velocity", "track", "--front-end", "dis", "--out", "run.nc", "--plot", "run.png", "--quiet",
                       "--speed-prior", "1", "--coupling", "0"])
rc["compare"] = main(["compare", "track", "--front-ends", "farneback", "--out", "compare.nc", "--quiet"])
rc["depth"] = main(["depth", "track", "--method", "ratio", "--velocity", "truth", "--every", "20",
                    "--out", "depth.nc", "--quiet"])
rc["info"] = main(["info", "track"])
with xr.open_dataset("run.nc") as ds:
    keep = ds.observable.values.astype(bool) & (ds.time.values - ds.time.values[0] > 0.5)
    err = ds.v_hat.values[keep] - ds.v_true.values[keep]
    velocity = dict(rmse=float(np.sqrt(np.mean(err ** 2))), observable=float(keep.mean()), n=int(keep.sum()),
                    speed=float(np.abs(ds.v_true.values).max()))
with xr.open_dataset("compare.nc") as ds:
    compare = dict(rmse=float(ds.rmse_m_s.sel(front_end="farneback")),
                   observable=float(ds.observable_fraction.sel(front_end="farneback")))
with xr.open_dataset("depth.nc") as ds:
    depth = dict(abs_rel=float(ds.pooled_abs_rel.sel(ring="all")),
                 coverage=float(ds.pooled_valid_fraction.sel(ring="all")), ranged=int(ds.ranged.values.sum()))
print(json.dumps(dict(rc=rc, velocity=velocity, compare=compare, depth=depth, torch_loaded="torch" in sys.modules,
                      optional_torch=repr(optional_torch()))))
'''
    out = last_json(run_without_torch(code, tmp_path))
    assert out["rc"] == dict(scene=0, velocity=0, compare=0, depth=0, info=0)
    assert not out["torch_loaded"] and out["optional_torch"] == "None"
    # Known answers: the pipelines measure, they do not merely finish.
    v = out["velocity"]
    assert v["n"] >= 20 and v["observable"] >= 0.5 and v["speed"] > 0.3
    assert v["rmse"] < 0.05, v                       # m/s, on a run reaching 0.3-0.5 m/s
    assert out["compare"]["rmse"] < 0.05 and out["compare"]["observable"] >= 0.5, out["compare"]
    d = out["depth"]
    assert d["ranged"] >= 2 and d["coverage"] > 0.3 and d["abs_rel"] < 0.3, d
    assert (tmp_path / "run.png").stat().st_size > 10_000


def test_every_command_parses_and_shows_help_without_torch(tmp_path):
    code = '''
import contextlib, io, json
from experiments.cli import COMMANDS, main

seen = {}
for name in COMMANDS:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        try:
            main([name, "--help"])
        except SystemExit as exc:
            seen[name] = [exc.code, buf.getvalue().startswith(f"usage: lobula {name}")]
print(json.dumps(dict(seen=seen, torch_loaded="torch" in sys.modules)))
'''
    out = last_json(run_without_torch(code, tmp_path))
    from experiments.cli import COMMANDS

    assert out["seen"] == {name: [0, True] for name in COMMANDS}
    assert not out["torch_loaded"]


@pytest.fixture(scope="module")
def short_track(tmp_path_factory):
    """Half a second of a synthetic run, enough for the EMD front end to be reached."""
    cfg = TrackRunConfig(profile=None, start_s=4.0, duration_s=0.5, scale=0.25)
    return make_track_run(tmp_path_factory.mktemp("packaging") / "track", cfg, progress=False)


@pytest.mark.parametrize("argv, what", [
    (["ephys", "tf-tuning", "--out", "rec.nc"], "virtual electrophysiology"),
    (["velocity", "{track}", "--front-end", "emd", "--out", "emd.nc", "--quiet"], "the EMD front end"),
    (["calibrate-emd", "{track}", "--out", "gains.json"], "the EMD front end"),
])
def test_a_biological_command_without_torch_says_how_to_install_it(tmp_path, short_track, argv, what):
    argv = [a.format(track=short_track) for a in argv]
    proc = run_without_torch(f"from experiments.cli import main\nsys.exit(main({argv!r}))", tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines() == [
        f"lobula {argv[0]}: error: {what} needs torch, which is not installed: {INSTALL}"]
    assert not any(tmp_path.iterdir())                   # nothing half-written


def test_configurations_load_and_the_models_raise_the_extras_error_without_torch(tmp_path):
    code = '''
import json
import numpy as np
from lobula._optional import MissingExtraError
from lobula.camera import PinholeCamera
from lobula.config import VelocityConfig

text = VelocityConfig(front_end="emd").to_json()   # the EMD front end's configuration, round trip
cfg = VelocityConfig.from_json(text)
errors = {}
cam = PinholeCamera().scaled(0.05)
from lobula.depth import depth_ratio, depth_tv
flow = np.zeros((2, cam.height, cam.width), np.float32)
ratio = depth_ratio(flow, cam, 1.0, (0.0, 0.0))
try:
    depth_tv(flow, cam, 1.0, (0.0, 0.0))
except MissingExtraError as exc:
    errors["depth_tv"] = [str(exc), isinstance(exc, ImportError), exc.name]
from lobula.emd_front_end import EMDFrontEnd
from lobula.receptive_field import tile_fields
try:
    EMDFrontEnd(cam, tile_fields(cam, cfg.fields), cfg.emd)
except MissingExtraError as exc:
    errors["emd"] = [str(exc), isinstance(exc, ImportError), exc.name]
print(json.dumps(dict(front_end=cfg.front_end, same=cfg.to_json() == text, ratio_valid=int(ratio.valid.sum()),
                      errors=errors, torch_loaded="torch" in sys.modules)))
'''
    out = last_json(run_without_torch(code, tmp_path))
    assert out["front_end"] == "emd" and out["same"]
    assert out["ratio_valid"] == 0                        # zero flow: no depth anywhere, and no error
    assert out["errors"] == {
        "depth_tv": [f"TV depth needs torch, which is not installed: {INSTALL}", True, "torch"],
        "emd": [f"this needs torch, which is not installed: {INSTALL}", True, "torch"],
    }
    assert not out["torch_loaded"]


def test_torch_is_the_bio_extra_and_the_wheel_holds_every_package():
    tomllib = pytest.importorskip("tomllib")
    root = Path(__file__).resolve().parents[1]
    meta = tomllib.loads((root / "pyproject.toml").read_text())
    assert not [d for d in meta["project"]["dependencies"] if d.startswith("torch")]
    assert [d for d in meta["project"]["optional-dependencies"]["bio"] if d.startswith("torch")]
    # setuptools installs only the packages listed (a non-editable install lacks an unlisted subpackage)
    listed = meta["tool"]["setuptools"]["packages"]
    found = {".".join(p.parent.relative_to(root).parts) for top in ("lobula", "stimuli", "experiments")
             for p in (root / top).rglob("__init__.py")}
    assert sorted(listed) == sorted(found)
