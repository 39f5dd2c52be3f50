"""Shared fixtures: the real D435i sample (skipped when ../shared is absent) and synthetic replays.

Replays are rendered once per test session into a temporary folder; each is a full
footage folder, read back through the same reader users use.

`make test` runs the suite on pytest-xdist workers (``-n auto --dist loadgroup``): each test
file is one group, so its module fixtures are built once, and every test that uses the 30 s
replay joins one group, so it is rendered once (see :func:`pytest_collection_modifyitems`).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

import pytest

from stimuli.scene import SceneConfig
from stimuli.track import REAL_PROFILE, TrackRunConfig, make_track_run

# Every NetCDF or Zarr store any test writes is walked for CF-1.10 metadata (experiments.store.cf_ready):
# a variable without long_name or units fails the test that wrote it (subprocesses inherit this too).
os.environ.setdefault("LOBULA_STRICT_CF", "1")

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "flivver_d435i"
# Synthetic scenes follow the built-in velocity profile whether or not ../shared is beside the checkout,
# so the suite renders the same worlds and gives the same verdict on every machine; a test that needs the
# recorded profile asks for it (the real_profile fixture) and skips where it is absent.
os.environ["LOBULA_PROFILE"] = "builtin"
REPLAY_FIXTURES = {"make_replay", "replay_rates", "emd_replay"}


def pytest_configure(config):
    """On an xdist worker, the cores are shared among the workers: torch and OpenCV get their share of
    threads, not each all of them (two workers on two cores would otherwise run four threads)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if workers > 1:
        import cv2
        import torch

        threads = max(1, (os.cpu_count() or 1) // workers)
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)


def pytest_collection_modifyitems(config, items):
    """Groups for ``--dist loadgroup``: the tests that use the test session's 30 s replay run on one worker
    (it is rendered once), every other test with the rest of its file (module fixtures once)."""
    for item in items:
        uses_replay = REPLAY_FIXTURES & set(getattr(item, "fixturenames", ()))
        item.add_marker(pytest.mark.xdist_group("replay" if uses_replay else item.path.name))


@pytest.fixture(scope="session")
def d435i() -> Path:
    if not (SHARED / "velocity.csv").exists():
        pytest.skip(f"real D435i footage not found at {SHARED} (../shared/data is beside the repo in CI)")
    return SHARED


@pytest.fixture(scope="session")
def real_profile() -> str:
    if not REAL_PROFILE.exists():
        pytest.skip(f"real velocity profile not found at {REAL_PROFILE}")
    return str(REAL_PROFILE)


@pytest.fixture(scope="session")
def make_replay(tmp_path_factory, real_profile):
    """Render (once per test session) a replay of the real trajectory: make_replay(start, duration, **scene)."""
    cache = {}

    def make(start=0.0, duration=30.0, **scene_kwargs):
        key = (start, duration, tuple(sorted(scene_kwargs.items())))
        if key not in cache:
            folder = tmp_path_factory.mktemp("replay") / "track"
            cfg = TrackRunConfig(profile=real_profile, start_s=start, duration_s=duration, scale=0.5,
                                 scene=SceneConfig(**scene_kwargs))
            cache[key] = make_track_run(folder, cfg, progress=False)
        return cache[key]

    return make


@pytest.fixture(scope="session")
def replay_rates(make_replay):
    """Field rates of the 0–30 s replay with the default DIS front end, and what a readout needs."""
    from experiments.velocity import field_rates, forward_accel_at
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage

    fo = open_footage(make_replay(0.0, 30.0))
    cfg = VelocityConfig()
    rates = field_rates(fo, cfg, progress=False)
    a, _ = forward_accel_at(fo, rates.t, cfg)
    v_true = np.interp(rates.t, fo.truth["time_s"], fo.truth["v_forward_m_s"])
    return rates, a, v_true


@pytest.fixture(scope="session")
def emd_replay(make_replay):
    """The 0–30 s replay through the EMD front end (uncalibrated) and the default readout."""
    from experiments.velocity import estimate_velocity
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage

    return estimate_velocity(open_footage(make_replay(0.0, 30.0)), VelocityConfig(front_end="emd"), progress=False)
