"""`lobula figures` regenerates its figures deterministically (same seed, same numbers)."""
import json

from experiments.figures import run_figures


def test_figures_are_deterministic(tmp_path, real_profile):
    which = ("error_vs_acceleration", "rmse_vs_field_size")
    a = run_figures(tmp_path / "a", which, start_s=5.0, duration_s=6.0, seed=3, quick=True, progress=False)
    b = run_figures(tmp_path / "b", which, start_s=5.0, duration_s=6.0, seed=3, quick=True, progress=False)
    for name in which:
        ra = json.loads((tmp_path / "a" / f"{name}.json").read_text())["results"]
        rb = json.loads((tmp_path / "b" / f"{name}.json").read_text())["results"]
        assert ra == rb, name
        assert (tmp_path / "a" / f"{name}.png").stat().st_size > 10_000
        assert "lobula figures" in a[name]["command"]
