"""``rmse_vs_tau_contrast_noise``: EMD velocity RMSE against delay τ and stimulus contrast, with the
camera's sensor noise added *after* the contrast change.

The committed ``rmse_vs_tau_contrast`` rescales frames that already carry the renderer's pixel
noise and 8-bit quantisation, so noise shrinks with the signal and a linear front end is
contrast-invariant by construction. Here each replay is rendered noise-free (``noise_grey = 0``),
its frames are rescaled about their mean, I' = m + c·(I − m), and only then the sensor noise
(Gaussian, σ = the scene's default ``noise_grey`` grey levels, seeded per frame) and 8-bit
rounding are applied, so the signal-to-noise ratio falls with contrast as it does for a camera.
(The noise-free render is itself 8-bit: quantisation before the contrast change remains, a step
of 1/c grey levels after it, far below σ·√12 for c ≥ 0.25.) Over ``seeds`` replays (scene seeds),
mean and min–max shown.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["NoisyContrastFootage", "contrast_noise_numbers", "figure_contrast_noise"]


class NoisyContrastFootage:
    """A noise-free footage seen at contrast c with sensor noise added afterwards (grey levels)."""

    def __init__(self, footage, contrast: float, noise_grey: float, seed: int):
        self.__dict__.update(footage.__dict__)
        self._footage, self.contrast, self.noise_grey, self.seed = footage, contrast, noise_grey, seed

    def __len__(self):
        return len(self._footage)

    def frames(self, *a, **k):
        for i, t, img in self._footage.frames(*a, **k):
            x = img.astype(float)
            m = x.mean()
            x = m + self.contrast * (x - m)
            if self.noise_grey > 0:
                x = x + np.random.default_rng([self.seed, 7, int(i)]).normal(0.0, self.noise_grey, x.shape)
            yield i, t, np.clip(np.round(x), 0, 255).astype(np.uint8)

    def depth_map(self, i):
        return self._footage.depth_map(i)


def _clean_replay(cache: Path, start_s: float, duration_s: float, seed: int) -> Path:
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, make_track_run, recorded_profile

    real = recorded_profile()
    folder = cache / f"replay_clean_{'real' if real else 'builtin'}_{start_s:g}_{duration_s:g}_seed{seed}"
    if not (folder / "frames.csv").exists():
        cfg = TrackRunConfig(profile=str(real) if real else None, start_s=start_s, duration_s=duration_s,
                             scale=0.5, scene=SceneConfig(seed=seed, noise_grey=0.0))
        make_track_run(folder, cfg, progress=False)
    return folder


def contrast_noise_numbers(cache, seeds=(0, 1, 2), taus=(0.005, 0.01, 0.035), contrasts=(1.0, 0.25, 0.1, 0.05),
                           start_s: float = 5.0, duration_s: float = 10.0) -> dict:
    """RMSE (after 2 s) of the EMD front end per seed, contrast and τ: {"rmse_m_s": (S, C, T) list, ...}."""
    from dataclasses import replace

    from experiments.velocity import score
    from lobula.velocity import estimate_velocity
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage
    from stimuli.scene import SceneConfig

    sigma = SceneConfig().noise_grey
    grid = np.full((len(seeds), len(contrasts), len(taus)), np.nan)
    for s, seed in enumerate(seeds):
        fo = open_footage(_clean_replay(Path(cache), start_s, duration_s, seed))
        for i, c in enumerate(contrasts):
            foot = NoisyContrastFootage(fo, c, sigma, seed)
            for j, tau in enumerate(taus):
                cfg = VelocityConfig(front_end="emd")
                cfg.emd.emd = replace(cfg.emd.emd, tau_s=tau)
                grid[s, i, j] = score(estimate_velocity(foot, cfg, progress=False), 2.0)["rmse_m_s"]
    return dict(seeds=list(seeds), tau_s=list(taus), contrast=list(contrasts), noise_grey=sigma,
                start_s=start_s, duration_s=duration_s, rmse_m_s=grid.tolist())


def figure_contrast_noise(out_dir, cache, seeds=(0, 1, 2), **kw) -> tuple[Path, dict]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    from experiments.store import save_figure

    res = contrast_noise_numbers(cache, seeds, **kw)
    g = np.array(res["rmse_m_s"])
    taus = np.array(res["tau_s"]) * 1000
    fig, ax = plt.subplots(figsize=(6.4, 4.2), layout="constrained")
    for i, c in enumerate(res["contrast"]):
        m = g[:, i].mean(0)
        ax.errorbar(taus * (1 + 0.03 * (i - 1.5)), m, yerr=[m - g[:, i].min(0), g[:, i].max(0) - m], marker="o",
                    capsize=3, label=f"contrast ×{c:g}")
    ax.set_xscale("log")
    ax.set_xticks(taus, [f"{x:g}" for x in taus])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set(xlabel="EMD delay τ (ms)", ylabel="velocity RMSE after 2 s (m/s)")
    ax.set_title(f"EMD front end: contrast changed, then sensor noise σ = {res['noise_grey']:g} grey level(s)\n"
                 f"({len(seeds)} replays: mean, bars min–max; {res['duration_s']:g} s each)", fontsize=9)
    ax.legend(fontsize=8)
    png = Path(out_dir) / "rmse_vs_tau_contrast_noise.png"
    save_figure(fig, png, dpi=150)
    plt.close(fig)
    return png, res
