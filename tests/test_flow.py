"""lobula.flow's fast paths against plain reference computations (the same results, faster)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lobula.camera import PinholeCamera
from lobula.flow import FlowConfig, compose_homography, make_flow_fn, pixel_to_angular


def test_compose_homography_equals_pointwise_reference():
    # W(p + δ) − p for every pixel, written out point by point in float64, NaN where the
    # composed point leaves the image (or the flow was already NaN).
    cam = PinholeCamera().scaled(0.25)
    h, w = cam.height, cam.width
    rng = np.random.default_rng(0)
    flow = rng.normal(0.0, 3.0, (2, h, w)).astype(np.float32)
    hom = cam.rotation_homography(Rotation.from_rotvec([0.05, -0.08, 0.03]).as_matrix().T)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    p = np.stack([(u.astype(np.float32) + flow[0]).astype(np.float64),       # the points in float32, as
                  (v.astype(np.float32) + flow[1]).astype(np.float64), np.ones_like(u)])  # the flow is
    x, y = p[0], p[1]
    iz = 1.0 / (x * hom[2, 0] + y * hom[2, 1] + hom[2, 2])
    mu = ((x * hom[0, 0] + y * hom[0, 1] + hom[0, 2]) * iz).astype(np.float32)   # the moved points, float32
    mv = ((x * hom[1, 0] + y * hom[1, 1] + hom[1, 2]) * iz).astype(np.float32)
    ref = np.stack([mu - u.astype(np.float32), mv - v.astype(np.float32)])
    gone = ~((mu >= 0) & (mu <= w - 1) & (mv >= 0) & (mv <= h - 1))
    ref[:, gone] = np.nan
    out = compose_homography(flow, hom)
    assert out.shape == (2, h, w) and out.dtype == np.float32
    assert 0 < gone.sum() < gone.size // 2                        # the turn pushes a border out of view
    np.testing.assert_array_equal(np.isnan(out), np.isnan(ref))
    np.testing.assert_allclose(out[~np.isnan(out)], ref[~np.isnan(ref)], rtol=0, atol=1e-3)


def test_pixel_to_angular_equals_the_camera_conversion():
    cam = PinholeCamera().scaled(0.25)
    rng = np.random.default_rng(1)
    px = rng.normal(0.0, 3.0, (cam.height, cam.width, 2)).astype(np.float32).transpose(2, 0, 1)  # a strided view
    ref = np.stack(cam.flow_px_to_normalised(px[0], px[1], 0.2)).astype(np.float32)
    np.testing.assert_array_equal(pixel_to_angular(px, cam, 0.2), ref)          # bit for bit
    px64 = px.astype(np.float64)
    np.testing.assert_array_equal(pixel_to_angular(px64, cam, 0.2),
                                  np.stack(cam.flow_px_to_normalised(px64[0], px64[1], 0.2)).astype(np.float32))


def test_dis_finest_level_keeps_a_160_pixel_grid():
    from lobula.flow import dis_finest_scale

    assert dis_finest_scale(2, 640, 160) == 2      # the preset as it is at 640×480
    assert dis_finest_scale(2, 320, 160) == 1
    assert dis_finest_scale(2, 160, 160) == 0
    assert dis_finest_scale(2, 1280, 160) == 2     # never coarser than the preset
    assert dis_finest_scale(2, 320, 0) == 2        # 0: the preset at every size


def test_dis_flow_at_320x240_keeps_the_growth_of_r_at_speed():
    """At constant speed ṙ = r² exactly (a = 0): the growth of each field's r̄ between two pairs 0.4 s
    apart, from DIS at 320×240 and 1 m/s toward panels, against the same from the exact flow. On the
    fast preset's own 80×60 grid (dis_grid_px 0) the growth comes out a third short (gain 0.68:
    vision reads a deceleration that is not there); on a 160-px grid (the default) within 10 %."""
    from lobula.receptive_field import gap_correction, pool_fields, tile_fields
    from tests.test_scene import CAM, constant_scene

    scene = constant_scene(v=1.0, noise_grey=1.0)
    fields = tile_fields(CAM)

    def growth(flow_of):
        r = [gap_correction(*pool_fields(flow_of(t0), fields), 1.0)[0] / 0.2 for t0 in (1.0, 1.4)]
        return (r[1] - r[0]) / 0.4

    exact = growth(lambda t0: scene.flow(t0, t0 + 0.2))
    gains = {}
    for grid in (160, 0):
        fn = make_flow_fn(FlowConfig(dis_grid_px=grid))
        g = growth(lambda t0: pixel_to_angular(fn(scene.render(t0), scene.render(t0 + 0.2)), CAM, 0.2) * 0.2)
        k = np.isfinite(g) & np.isfinite(exact) & (np.abs(exact) > 0)
        gains[grid] = np.median(g[k] / exact[k])
    print(f"\nṙ̄ gain DIS/exact at 320×240, 1 m/s: 160-px grid {gains[160]:.3f}, preset's grid {gains[0]:.3f}")
    assert abs(gains[160] - 1.0) < 0.1
    assert gains[0] < 0.8


def test_velocity_dis_options_set_the_flow_or_fail_loudly():
    import argparse

    import pytest

    from experiments.velocity import apply_velocity_options
    from lobula.config import VelocityConfig

    cfg = apply_velocity_options(VelocityConfig(), argparse.Namespace(dis_grid_px=160, dis_preset="medium"))
    assert (cfg.flow.dis_grid_px, cfg.flow.dis_preset) == (160, "medium")
    for front_end in ("farneback", "emd"):
        with pytest.raises(ValueError, match="--dis-grid-px sets the DIS flow"):
            apply_velocity_options(VelocityConfig(front_end=front_end), argparse.Namespace(dis_grid_px=160))
    with pytest.raises(ValueError, match="--dis-preset sets the DIS flow"):
        apply_velocity_options(VelocityConfig(front_end="farneback"), argparse.Namespace(dis_preset="fast"))
    with pytest.raises(ValueError, match="≥ 0"):
        apply_velocity_options(VelocityConfig(), argparse.Namespace(dis_grid_px=-1))


def test_compose_flows_adds_displacements_along_the_path():
    from lobula.flow import compose_flows

    h, w = 40, 60
    first = np.zeros((2, h, w), np.float32)
    first[0] = 3.0                                   # 3 px right everywhere
    second = np.zeros((2, h, w), np.float32)
    second[1] = np.arange(w, dtype=np.float32)[None, :] * 0.1   # down by 0.1 × the column reached
    total = compose_flows(first, second)
    np.testing.assert_allclose(total[0, :, :50], 3.0)
    np.testing.assert_allclose(total[1, :, :50], np.broadcast_to(0.1 * (np.arange(50) + 3.0), (h, 50)), rtol=1e-5)
    assert np.isnan(total[:, :, -2:]).all()          # the intermediate point left the image: unknown
    second[0, 5, 13] = np.nan
    assert np.isnan(compose_flows(first, second)[:, 5, 10]).all()


def _approach_gains(v, **flow_kw):
    """Median gain (DIS along exact / exact²) of each staggered pair, 320×240, toward a corridor at v m/s."""
    from lobula.flow import StaggeredFlow
    from tests.test_scene import CAM, constant_scene

    scene = constant_scene(v=v, duration=3.0, world="corridor", noise_grey=1.0, seed=5)
    frames = [(i, t, scene.render(t)) for i, t in enumerate(1.0 + np.arange(12) / 30.0)]
    gains, flows = [], []
    for s in StaggeredFlow(CAM, FlowConfig(**flow_kw)).run(frames):
        ex = scene.flow(s.t0, s.t1) / s.dt
        m = np.hypot(*ex)
        k = np.isfinite(m) & np.all(np.isfinite(s.flow), 0) & (m * s.dt * CAM.fx > 3)
        gains.append(np.median((s.flow[0][k] * ex[0][k] + s.flow[1][k] * ex[1][k]) / m[k] ** 2))
        flows.append(s.flow)
    return np.array(gains), flows


def test_a_fast_approach_is_followed_through_the_frames_between():
    """2 m/s down a corridor at 320×240 moves the image ~25 px over a 6-frame pair and magnifies near
    walls 1.5×: DIS in one step reads 0.63–0.93 of the exact flow; through the frames between, from
    the very first pair (a failed flow hides itself, so the first pair is always checked), within 1 %."""
    one, _ = _approach_gains(2.0, chain_fraction=0.0)
    chained, _ = _approach_gains(2.0)
    print(f"\nflow gain at 2 m/s: one step {np.round(one, 3)}, chained {np.round(chained, 3)}")
    assert np.all(np.abs(chained - 1.0) < 0.01)
    assert np.median(one) < 0.95


def test_a_slow_flow_is_computed_in_one_step():
    """At 1 m/s (~12 px) the checks (the first pair, then every chain_check-th) find nothing that moves far:
    every pair's flow is the single step's, as without chaining."""
    _, plain = _approach_gains(1.0, chain_fraction=0.0)
    _, default = _approach_gains(1.0, chain_check=2)
    for a, b in zip(plain, default):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="chain_fraction"):
        FlowConfig(chain_fraction=-0.1)
