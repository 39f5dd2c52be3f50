"""The contrast figure's footage: contrast changed first, then sensor noise of a fixed std (not scaled with it)."""
import numpy as np

from experiments.contrast_figure import NoisyContrastFootage


class _Frames:
    def __init__(self, img, n=4):
        self.img, self.n = img, n

    def __len__(self):
        return self.n

    def frames(self):
        for i in range(self.n):
            yield i, i / 30.0, self.img


def test_noise_is_added_after_the_contrast_change():
    rng = np.random.default_rng(0)
    clean = np.clip(np.round(128 + 40 * rng.standard_normal((120, 160))), 0, 255).astype(np.uint8)
    for c in (1.0, 0.25):
        f = NoisyContrastFootage(_Frames(clean), c, noise_grey=2.0, seed=1)
        frames = [img.astype(float) for _, _, img in f.frames()]
        target = clean.mean() + c * (clean.astype(float) - clean.mean())
        resid = np.concatenate([(x - target).ravel() for x in frames])
        # The noise keeps its std (2 grey levels, plus rounding's 1/12) at every contrast; the signal scales by c.
        assert abs(resid.std() - np.sqrt(4 + 1 / 12)) < 0.1, (c, resid.std())
        assert abs(np.std(np.mean(frames, 0)) / clean.std() - c) < 0.02
    # Seeded per frame: reproducible, and frames differ from each other.
    a = [img for _, _, img in NoisyContrastFootage(_Frames(clean), 0.5, 2.0, 3).frames()]
    b = [img for _, _, img in NoisyContrastFootage(_Frames(clean), 0.5, 2.0, 3).frames()]
    assert all(np.array_equal(x, y) for x, y in zip(a, b)) and not np.array_equal(a[0], a[1])
