"""experiments.store: what a figure file carries of where it came from."""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import pytest

from experiments.store import figure_metadata, save_figure
from lobula.version import __version__, git_commit


@pytest.fixture
def figure():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2, 2))
    ax.plot([0, 1], [1, 0])
    yield fig
    plt.close(fig)


def test_a_png_carries_version_commit_command_line_and_the_outputs_configuration(tmp_path, figure):
    from PIL import Image

    config = json.dumps({"readout": {"filter": "causal"}})
    path = save_figure(figure, tmp_path / "f.png", {"config": config, "seed": 3}, dpi=50)
    with Image.open(path) as im:
        info = dict(im.info)
    assert info["lobula_version"] == __version__ and info["git_commit"] == git_commit()
    assert info["config"] == config and info["seed"] == "3" and info["command_line"] and info["created"]
    assert info["Software"] == f"lobula {__version__} ({git_commit()})"


def test_pdf_and_svg_carry_the_same_record_as_json(tmp_path, figure):
    save_figure(figure, tmp_path / "f.svg", {"config": "{}"})
    root = ET.parse(tmp_path / "f.svg").getroot()
    described = [e.text for e in root.iter("{http://purl.org/dc/elements/1.1/}description")]
    record = json.loads(described[0])
    assert record["git_commit"] == git_commit() and record["config"] == "{}"
    save_figure(figure, tmp_path / "f.pdf", {"config": "{}"})
    assert git_commit().encode() in (tmp_path / "f.pdf").read_bytes()            # its info dictionary
    keywords = json.loads(figure_metadata(".pdf", {"config": "{}"})["Keywords"])
    assert keywords["git_commit"] == git_commit() and keywords["config"] == "{}" and keywords["command_line"]


def test_a_format_without_metadata_is_saved_without_it(tmp_path, figure):
    assert figure_metadata(".jpg") is None
    assert save_figure(figure, tmp_path / "f.jpg", dpi=30).stat().st_size > 0
