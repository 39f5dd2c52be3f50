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
                                         ("accel_noise", -0.01), ("order", 0), ("stagger", 0), ("paper_order", 0),
                                         ("coupling_window_s", 0.0), ("shared_error_s", -3.0), ("bias_walk", -0.002),
                                         ("kappa_rel_error", -0.25), ("coupling_z", -1.0), ("adapt_s", -1.0),
                                         ("min_valid_fraction", 0.0), ("shared_error_frac", 1.5),
                                         ("paper_wn", 1.0), ("depth_min_m", 3000.0)])
def test_readout_values_the_filter_cannot_use_are_refused(name, value):
    with pytest.raises(ValueError, match=f"ReadoutConfig.{name} must be"):
        dataclasses.replace(ReadoutConfig(), **{name: value})


def test_zero_turns_a_readout_term_off_and_is_accepted():
    dataclasses.replace(ReadoutConfig(), coupling_z=0.0, bias_walk=0.0, kappa_rel_error=0.0, shared_error_frac=0.0,
                        adapt_s=0.0)


@pytest.mark.parametrize("kw, match", [(dict(gap=0), "gap"), (dict(threads=-1), "threads"),
                                       (dict(dis_grid_px=-160), "dis_grid_px"), (dict(dis_preset="slow"), "dis_preset")])
def test_flow_values_that_pair_nothing_are_refused(kw, match):
    from lobula.flow import FlowConfig

    with pytest.raises(ValueError, match=f"FlowConfig.{match} must be"):
        FlowConfig(**kw)


@pytest.mark.parametrize("kw, match", [(dict(size_deg=-3.0), "size_deg"), (dict(spacing_deg=0.0), "spacing_deg"),
                                       (dict(margin_deg=-1.0), "margin_deg"), (dict(shape="disc"), "shape"),
                                       (dict(pooling="max"), "pooling")])
def test_field_values_that_tile_nothing_are_refused(kw, match):
    with pytest.raises(ValueError, match=f"FieldConfig.{match}"):
        FieldConfig(**kw)


@pytest.mark.parametrize("make, match", [
    (lambda: VelocityConfig(gyro_bias_prior_deg_s="1.0"), "VelocityConfig.gyro_bias_prior_deg_s must be a number, got str"),
    (lambda: VelocityConfig(derotate="no"), "VelocityConfig.derotate must be True or False, got str"),
    (lambda: ReadoutConfig(coupling_window_s="4"), "ReadoutConfig.coupling_window_s must be a number, got str"),
    (lambda: ReadoutConfig(stagger=4.0), "ReadoutConfig.stagger must be a whole number, got float"),
    (lambda: ReadoutConfig(reversal="False"), "ReadoutConfig.reversal must be True or False"),
    (lambda: ReadoutConfig(accel_turn_rate_max="1"), "ReadoutConfig.accel_turn_rate_max must be a number or None"),
    (lambda: FieldConfig(size_deg="5"), "FieldConfig.size_deg must be a number, got str"),
])
def test_values_of_the_wrong_type_are_refused_naming_the_field(make, match):
    """A string for a number or a flag is refused by the configuration itself (a string "no" is not read as True)."""
    with pytest.raises(TypeError, match=match):
        make()


def test_nan_in_any_number_and_a_dict_for_the_configuration_are_refused():
    with pytest.raises(ValueError, match="ReadoutConfig.coupling_z must be a number, got NaN"):
        ReadoutConfig(coupling_z=float("nan"))
    cfg = VelocityConfig()
    cfg.readout.kappa_rel_error = float("nan")
    with pytest.raises(ValueError, match="ReadoutConfig.kappa_rel_error must be a number, got NaN"):
        cfg.validate()
    from lobula.readers.core import Footage
    from lobula.velocity import estimate_velocity

    footage = Footage(camera=None, times=[], imu=None, truth=None, path=".", kind="folder", files=[])
    with pytest.raises(TypeError, match="config must be a VelocityConfig .*got dict"):
        estimate_velocity(footage, {"front_end": "dis"}, progress=False)
