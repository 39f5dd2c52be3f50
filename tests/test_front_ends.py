"""The velocity front ends' registry (lobula.front_ends): its entries, what the pipeline reads from them,
and a front end added as one factory and one entry."""
from types import SimpleNamespace

import numpy as np
import pytest

from experiments import parsers
from lobula.velocity import estimate_velocity, field_rates
from lobula.camera import PinholeCamera
from lobula.config import VelocityConfig
from lobula.flow import FlowSample
from lobula.front_ends import (FRONT_ENDS, FieldSample, FrontEnd, FrontEndStream, get_front_end,
                               register_front_end)
from lobula.readout import ReadoutConfig


def test_the_command_line_offers_the_registered_front_ends():
    import argparse

    from experiments import compare

    assert parsers.FRONT_END_NAMES == tuple(FRONT_ENDS) == ("dis", "farneback", "flo", "emd")
    assert sorted(compare.DEFAULT_FRONT_ENDS) == sorted(FRONT_ENDS) == sorted(parsers.COMPARE_FRONT_ENDS)
    sub = argparse.ArgumentParser().add_subparsers()
    action = next(a for a in parsers.add_velocity_parser(sub)._actions if a.dest == "front_end")
    assert tuple(action.choices) == tuple(FRONT_ENDS)


def test_an_unknown_front_end_is_refused_naming_the_known_ones():
    with pytest.raises(ValueError, match="unknown front end 'emdd'; the front ends known: dis, farneback, flo, emd"):
        get_front_end("emdd")
    with pytest.raises(ValueError, match="unknown front end 'optical'"):
        VelocityConfig(front_end="optical")


def test_the_emd_entry_carries_its_epipole_and_readout_defaults():
    emd, dis = get_front_end("emd"), get_front_end("dis")
    assert emd.needs_torch and not any(f.needs_torch for n, f in FRONT_ENDS.items() if n != "emd")
    assert emd.epipoles == ("principal",) and not emd.estimates_epipole and dis.epipoles[0] == "estimate"
    assert emd.kappa_errors == ReadoutConfig.EMD_KAPPA_ERRORS != dis.kappa_errors
    assert (emd.yields, emd.derotation, emd.live) == ("fields", "gaze", False)
    assert [n for n, f in FRONT_ENDS.items() if f.live] == ["dis", "farneback"]
    # what VelocityConfig takes from the entries
    cfg = VelocityConfig(front_end="emd")
    assert cfg.readout == ReadoutConfig.emd() and cfg.epipole == "principal"
    assert VelocityConfig().readout == ReadoutConfig() and VelocityConfig().epipole == "estimate"
    assert cfg.for_front_end("farneback").readout == ReadoutConfig()
    assert VelocityConfig().for_front_end("emd").readout == ReadoutConfig.emd()


class _Footage(SimpleNamespace):
    def __len__(self):
        return len(self.times)


def _footage(n=8, rate=30.0):
    """Footage as the pipeline reads it, with no frames, IMU or truth: the toy front ends make their own."""
    cam = PinholeCamera(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5, frame_rate_hz=rate)
    return _Footage(camera=cam, times=np.arange(n) / rate, imu=None, truth=None, path="toy", kind="toy", files=[])


@pytest.fixture
def registered():
    """Register entries for one test, leaving the registry as it was."""
    added = []

    def add(front_end):
        added.append(front_end.name)
        return register_front_end(front_end)

    yield add
    for name in added:
        FRONT_ENDS.pop(name, None)


def test_a_front_end_added_as_one_entry_runs_through_the_pipeline(registered):
    """A flow front end of pure expansion at k = 0.7 1/s about the principal point (flow k·(x, y)):
    every field reads r = k; one that pools its own fields hands its rates through unchanged."""
    k, fo = 0.7, _footage()
    x, y = fo.camera.normalised_grid(np.float64)

    def expanding(inp):
        gap = inp.config.flow.gap
        pairs = (FlowSample(i, fo.times[i], fo.times[i + gap], np.stack([k * x, k * y]))
                 for i in range(len(fo.times) - gap))
        return FrontEndStream(pairs, len(fo.times) - gap)

    registered(FrontEnd("expanding", "pure expansion", expanding, epipoles=("principal",), kappa_errors=(0.3, 0.6)))
    cfg = VelocityConfig(front_end="expanding")
    assert cfg.epipole == "principal" and (cfg.readout.kappa_rel_error, cfg.readout.shared_error_frac) == (0.3, 0.6)
    cfg.flow.gap, cfg.fields.gap_correction = 2, False
    rates = field_rates(fo, cfg, progress=False)
    assert rates.r.shape[0] == len(fo.times) - 2 and rates.material is None and rates.known is None
    finite = np.isfinite(rates.r)
    assert finite.sum() > 5
    np.testing.assert_allclose(rates.r[finite], k, rtol=1e-5)
    np.testing.assert_allclose(rates.t, 0.5 * (fo.times[:-2] + fo.times[2:]))
    cfg.epipole = "estimate"   # the entry runs with the principal point only
    with pytest.raises(ValueError, match="the expanding front end has no epipole estimate"):
        estimate_velocity(fo, cfg, progress=False)

    r = np.arange(len(fo.times) * 3, dtype=float).reshape(-1, 3)
    registered(FrontEnd("pooled", "its own fields", lambda inp: FrontEndStream(
        (FieldSample(t, r[i], r[i] ** 2) for i, t in enumerate(fo.times)), len(fo.times)), yields="fields"))
    rates = field_rates(fo, VelocityConfig(front_end="pooled"), progress=False)
    assert np.array_equal(rates.r, r) and np.array_equal(rates.r2, r ** 2) and np.array_equal(rates.t, fo.times)
    assert np.array_equal(rates.epipole, np.zeros((len(fo.times), 2)))


def test_an_entry_with_an_unknown_kind_is_refused():
    with pytest.raises(ValueError, match="yields must be 'flow' or 'fields'"):
        FrontEnd("x", "x", lambda inp: None, yields="spikes")
    with pytest.raises(ValueError, match="epipoles must be among"):
        FrontEnd("x", "x", lambda inp: None, epipoles=("centre",))
