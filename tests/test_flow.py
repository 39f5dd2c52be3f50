"""lobula.flow's fast paths against plain reference computations (the same results, faster)."""
import numpy as np
from scipy.spatial.transform import Rotation

from lobula.camera import PinholeCamera
from lobula.flow import compose_homography, pixel_to_angular


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
