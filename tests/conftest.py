"""Shared fixtures: the real D435i sample (skipped when ../shared is absent) and synthetic replays.

Replays are rendered once per test session into a temporary folder; each is a full
footage folder, read back through the same reader users use.

`make test` runs the suite on pytest-xdist workers (``-n auto --dist loadgroup``): each test
file is one group, so its module fixtures are built once, and every test that uses the 30 s
replay joins one group, as does every test that uses the fisheye footage, so each is rendered once
(see :func:`pytest_collection_modifyitems`).
The groups that take longest are handed out first (``LONGEST_GROUPS``), so that the workers
finish together.
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
#: fixtures built once per test run that several test files share: their tests join one xdist group, so it is built once
SHARED_GROUPS = {"fisheye_run": "fisheye"}


def pytest_configure(config):
    """On an xdist worker, the cores are shared among the workers: torch and OpenCV get their share of
    threads, not each all of them (two workers on two cores would otherwise run four threads).

    Under ``--dist loadgroup`` the controller hands the groups out in the order of the collection
    (which :func:`pytest_collection_modifyitems` sorts longest first), not by their number of tests:
    by that count the replay (seven tests, the second longest group) would follow every many-test
    file, start last and run alone."""
    if getattr(config.option, "dist", None) == "loadgroup":
        config.option.loadscopereorder = False
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if workers > 1:
        import cv2
        import torch

        threads = max(1, (os.cpu_count() or 1) // workers)
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)


# The groups with the most CPU time, longest first (measured on two workers with ../shared present; the
# families take about an eighth of the suite's time, the others here 25-80 s each, the real GoPro clips a few
# seconds without ../shared). Under --dist loadgroup they are handed out before the rest, so that a short
# group, not a long one, is the last to finish; a group missing here only starts later (it changes no result).
LONGEST_GROUPS = ("test_families.py", "replay", "test_gopro.py", "test_streaming.py", "test_tutorials.py", "fisheye",
                  "test_depth_cli.py", "test_compound_eye.py", "test_nwb.py", "test_faults.py")


def _xdist_group(item) -> str:
    """The test's ``--dist loadgroup`` group: "replay" for the tests that use the test session's 30 s
    replay (rendered once), "fisheye" for those that use the fisheye footage (test_lens.py's and
    test_focal_length.py's, rendered once), otherwise its file (module fixtures built once)."""
    names = set(getattr(item, "fixturenames", ()))
    if REPLAY_FIXTURES & names:
        return "replay"
    return next((group for fixture, group in SHARED_GROUPS.items() if fixture in names), item.path.name)


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(config, items):
    """Groups for ``--dist loadgroup`` (see :func:`_xdist_group`), longest first on a worker.

    xdist reads the ``xdist_group`` marker and sends each group to one worker by a ``@group`` suffix it
    writes on the test's node id; pytest 9.2 (constraints.txt) keeps the node id in ``item._id`` (a
    ``NodeId``), where xdist's write does not reach, so the suffix is written here where it is missing.
    Without it every test is scheduled on its own and each worker builds the replays and module
    fixtures again."""
    for item in items:
        item.add_marker(pytest.mark.xdist_group(_xdist_group(item)))
    result = yield
    if getattr(config.option, "loadgroup", False):  # an xdist worker under --dist loadgroup
        rank = {group: i for i, group in enumerate(LONGEST_GROUPS)}
        items.sort(key=lambda item: rank.get(_xdist_group(item), len(rank)))  # stable: file order kept
        for item in items:
            suffix = "@" + _xdist_group(item)
            if not item.nodeid.endswith(suffix) and hasattr(item, "_id"):
                item._id = type(item._id).parse(item.nodeid + suffix)
    return result


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
def family_footage(tmp_path_factory):
    """make(family, duration_s, scale, seed=0): a scene of one of the suite's families
    (experiments.suite.family_config), rendered once per test session, opened."""
    from experiments import suite
    from lobula.readers import open_footage
    from stimuli.track import make_track_run

    cache = {}

    def make(family, duration_s, scale, seed=0):
        key = (family, duration_s, scale, seed)
        if key not in cache:
            folder = tmp_path_factory.mktemp(f"{family}{seed}") / "run"
            make_track_run(folder, suite.family_config(family, seed, duration_s, scale), progress=False)
            cache[key] = open_footage(folder)
        return cache[key]

    return make


@pytest.fixture(scope="session")
def fisheye_run(tmp_path_factory):
    """A 131° equidistant fisheye turning on three axes, heading 8° off its axis: where the lens matters."""
    import json

    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, make_track_run

    tmp = tmp_path_factory.mktemp("fisheye")
    cam = tmp / "cam.json"
    cam.write_text(json.dumps(dict(width=640, height=480, fx=280.0, fy=280.0, cx=319.5, cy=239.5, frame_rate_hz=30.0)))
    cfg = TrackRunConfig(start_s=3.0, duration_s=6.0, scale=0.5, camera_json=str(cam), lens="kannala-brandt:0,0,0,0",
                         scene=SceneConfig(seed=2, rotation3_amp_deg=(5.0, 5.0, 5.0), off_axis_yaw_deg=8.0))
    return make_track_run(tmp / "run", cfg, progress=False)


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
    """Field rates of the 0–30 s replay with the default DIS front end, and what a readout needs: the forward
    acceleration, the truth, and the acceleration averaged over each pair's frames as the rates are (``a_rates``)."""
    from lobula.velocity import field_rates
    from lobula.velocity.inertial import forward_accel_at
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage

    fo = open_footage(make_replay(0.0, 30.0))
    cfg = VelocityConfig()
    rates = field_rates(fo, cfg, progress=False)
    a, _ = forward_accel_at(fo, rates.t, cfg)
    a_rates, _ = forward_accel_at(fo, rates.t, cfg, window_s=rates.span)
    v_true = np.interp(rates.t, fo.truth["time_s"], fo.truth["v_forward_m_s"])
    return rates, a, v_true, a_rates


@pytest.fixture(scope="session")
def emd_replay(make_replay):
    """The 0–30 s replay through the EMD front end (uncalibrated) and the default readout."""
    from lobula.velocity import estimate_velocity
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage

    return estimate_velocity(open_footage(make_replay(0.0, 30.0)), VelocityConfig(front_end="emd"), progress=False)
