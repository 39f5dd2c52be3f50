"""lobula.lens and the readers' lens removal: rays through a Kannala–Brandt or radial–tangential lens, the
maps onto a pinhole, and a fisheye footage's velocity against the same footage read as a pinhole."""
import json

import numpy as np
import pytest

from lobula.camera import PinholeCamera
from lobula.lens import LensDistortion, distort, pixel_rays, undistortion_maps

CAM = PinholeCamera(640, 480, 300.0, 300.0, 319.5, 239.5, 30.0)


@pytest.mark.parametrize("lens", [LensDistortion("kannala-brandt", (0.05, -0.01, 0.002, 0.0)),
                                  LensDistortion("radtan", (-0.2, 0.05, 0.001, -0.001, 0.01))])
def test_rays_and_distortion_are_inverse(lens):
    u, v = np.meshgrid(np.linspace(0, 639, 9), np.linspace(0, 479, 7))
    x, y = pixel_rays(CAM, lens, u, v)
    xd, yd = distort(x, y, lens)
    np.testing.assert_allclose(CAM.fx * xd + CAM.cx, u, atol=1e-9)
    np.testing.assert_allclose(CAM.fy * yd + CAM.cy, v, atol=1e-9)


def test_an_equidistant_lens_sees_the_angle_its_radius_says():
    """Kannala–Brandt with no coefficients: a pixel r px from the centre sees θ = r/f from the axis."""
    lens = LensDistortion("equidistant", (0, 0, 0, 0))
    r = np.array([0.0, 100.0, 250.0, 400.0])
    x, y = pixel_rays(CAM, lens, CAM.cx + r, np.full(4, CAM.cy))
    np.testing.assert_allclose(np.arctan(np.hypot(x, y)), r / CAM.fx, atol=1e-12)
    assert np.all(y == 0)


def test_optimal_target_keeps_the_whole_width_and_same_k_the_centre():
    lens = LensDistortion("kannala-brandt", (0, 0, 0, 0))
    maps, same = undistortion_maps(CAM, lens, "same-k")
    assert same == CAM and maps[0].shape == (480, 640)
    assert abs(maps[0][240, 320] - 320.0) < 1e-3  # the centre maps onto itself
    _, wide = undistortion_maps(CAM, lens, "optimal")
    half = np.arctan(320 / wide.fx)
    assert half == pytest.approx(min(320 / CAM.fx, np.radians(75)), rel=1e-6)


def test_bad_lens_descriptions_are_refused():
    with pytest.raises(ValueError, match="unknown lens model"):
        LensDistortion("barrel", (0.1,))
    with pytest.raises(ValueError, match="takes 4 finite coefficients"):
        LensDistortion.parse("kannala-brandt:0.1,0.2")


def test_a_fisheye_footage_is_read_through_its_lens(fisheye_run, tmp_path):
    """The lens in camera.json is removed on reading (the same K, or a wider pinhole keeping 131°); read as a
    pinhole instead, the same footage's velocity errs ≥ 4× more."""
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage
    from lobula.velocity import estimate_velocity

    def rmse(fo):
        ds = estimate_velocity(fo, VelocityConfig(), progress=False)
        keep = (ds.time > ds.time[0] + 1.5).values & ds.observable.values
        return float(np.sqrt(np.mean((ds.v_hat - ds.v_true).values[keep] ** 2)))

    fo = open_footage(fisheye_run)
    assert fo.lens_maps is not None and fo.distortion["model"] == "kannala-brandt"
    assert any("lens distortion" in n for n in fo.notes)
    wide = open_footage(fisheye_run, undistort="optimal")
    assert wide.camera.fx < fo.camera.fx
    d = json.loads((fisheye_run / "camera.json").read_text())
    d.pop("distortion")
    (tmp_path / "pinhole.json").write_text(json.dumps(d))
    as_pinhole = open_footage(fisheye_run, camera=tmp_path / "pinhole.json")
    assert as_pinhole.lens_maps is None
    good, good_wide, bad = rmse(fo), rmse(wide), rmse(as_pinhole)
    print(f"\nfisheye RMSE: same-k {good:.4f}, optimal {good_wide:.4f}, read as a pinhole {bad:.4f} m/s")
    assert good < 0.03 and good_wide < 0.03
    assert bad > 4 * max(good, good_wide)


def test_a_malformed_lens_names_its_file(fisheye_run, tmp_path):
    from lobula.readers import open_footage
    from lobula.readers.core import FootageError

    d = json.loads((fisheye_run / "camera.json").read_text())
    d["distortion"] = {"model": "kannala-brandt", "coeffs": [0.1]}
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(d))
    with pytest.raises(FootageError, match=f"{bad}: its \"distortion\" must be"):
        open_footage(fisheye_run, camera=bad)


def test_gopro_hint_is_an_equidistant_lens_whose_diagonal_sees_the_stated_view():
    """The GoPro reader's error offers a camera.json: its corner pixel's ray is half the diagonal view off the axis."""
    from lobula.readers.gopro import equidistant_hint

    hint = equidistant_hint(848, 480, 29.97, 137.4)
    cam_d = json.loads(hint[hint.index("{"):])
    cam = PinholeCamera(**{k: cam_d[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "frame_rate_hz")})
    lens = LensDistortion(**cam_d["distortion"])
    x, y = pixel_rays(cam, lens, np.array([-0.5]), np.array([-0.5]))
    assert np.degrees(np.arctan(np.hypot(x, y)))[0] == pytest.approx(137.4 / 2, abs=0.05)
    assert equidistant_hint(848, 480, 29.97, None) == ""
