"""The tutorials run, end to end, on tiny inputs (LOBULA_TUTORIAL_QUICK=1), so they cannot rot."""
import runpy
from pathlib import Path

import pytest

TUTORIALS = sorted((Path(__file__).resolve().parents[1] / "tutorials").glob("[0-9][0-9]_*.py"))


@pytest.mark.parametrize("path", TUTORIALS, ids=[p.stem for p in TUTORIALS])
def test_tutorial_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("LOBULA_TUTORIAL_QUICK", "1")
    monkeypatch.chdir(tmp_path)
    runpy.run_path(str(path), run_name="__main__")
    pngs = list((tmp_path / "tutorial_output").glob("*.png"))
    assert pngs and all(p.stat().st_size > 5_000 for p in pngs)
