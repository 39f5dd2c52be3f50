"""`lobula.config.VelocityConfig` and its parts: values a run cannot use are refused, naming the field."""
import dataclasses

import pytest

from lobula.config import VelocityConfig
from lobula.readout import ReadoutConfig
from lobula.receptive_field import FieldConfig


def test_a_field_set_after_construction_is_checked_before_a_run(tmp_path):
    """Scientists set fields on the default (``cfg.readout.filter = "causal"``): a typo there is refused when the
    run starts, not run as a mix of both filters."""
    from lobula.readers.core import Footage
    from lobula.velocity import estimate_velocity

    cfg = VelocityConfig()
    cfg.readout.filter = "casual"
    with pytest.raises(ValueError, match="unknown filter kind 'casual'"):
        cfg.validate()
    footage = Footage(camera=None, times=[], imu=None, truth=None, path=tmp_path, kind="folder", files=[])
    with pytest.raises(ValueError, match="unknown filter kind 'casual'"):
        estimate_velocity(footage, cfg, progress=False)
    cfg.readout.filter = "causal"
    assert cfg.validate() is cfg


def test_parts_of_the_wrong_kind_and_a_path_for_footage_are_refused_naming_them():
    with pytest.raises(TypeError, match="VelocityConfig.readout must be a ReadoutConfig, got dict"):
        VelocityConfig(readout={"filter": "causal"})
    from lobula.velocity import estimate_velocity

    with pytest.raises(TypeError, match=r"takes a Footage \(lobula.readers.open_footage\(path\)\), got str"):
        estimate_velocity("/some/folder")


@pytest.mark.parametrize("name, value", [("v_prior_m_s", 0.0), ("max_std_m_s", -1.0), ("cutoff_hz", float("nan")),
                                         ("accel_noise", -0.01), ("order", 0), ("stagger", 0)])
def test_readout_values_the_filter_cannot_use_are_refused(name, value):
    with pytest.raises(ValueError, match=f"ReadoutConfig.{name} must be"):
        dataclasses.replace(ReadoutConfig(), **{name: value})


@pytest.mark.parametrize("kw, match", [(dict(size_deg=-3.0), "size_deg"), (dict(spacing_deg=0.0), "spacing_deg"),
                                       (dict(margin_deg=-1.0), "margin_deg"), (dict(shape="disc"), "shape"),
                                       (dict(pooling="max"), "pooling")])
def test_field_values_that_tile_nothing_are_refused(kw, match):
    with pytest.raises(ValueError, match=f"FieldConfig.{match}"):
        FieldConfig(**kw)
