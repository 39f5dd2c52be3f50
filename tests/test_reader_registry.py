"""The footage readers' registry (lobula.readers): priority order, registering a layout, unknown paths."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import lobula.readers as readers
from lobula.camera import PinholeCamera
from lobula.readers import READERS, Reader, known_layouts, open_footage, register_reader
from lobula.readers.core import IMU, Footage, FootageError

CAMERA = PinholeCamera(width=8, height=6, fx=10.0, fy=10.0, cx=4.0, cy=3.0, frame_rate_hz=5.0)


@pytest.fixture
def registry(monkeypatch):
    """READERS as shipped, restored after the test whatever it registers."""
    monkeypatch.setattr(readers, "READERS", list(READERS))
    return readers.READERS


def _toy_open(seen: list):
    """A reader of ``.toy`` files: 3 frames at 0, 0.2, 0.4 s and an IMU at 0..0.4 s; remembers its options."""
    def open_toy(path, **options):
        seen.append((Path(path), options))
        t = np.linspace(0.0, 0.4, 5)
        imu = IMU(t, np.tile([0.0, -9.81, 1.0], (5, 1)), np.zeros((5, 3)), source=str(path))
        return Footage(Path(path), CAMERA, np.array([0.0, 0.2, 0.4]), [path] * 3, imu, None, kind="toy")
    return open_toy


def test_readers_are_asked_in_priority_order():
    # Bags and videos before folders, the single-video folder last: a folder holding frames.csv and a
    # video is a footage folder, and a .bag is never taken for anything else. A camera's own motion log is
    # asked before the video layout, which claims every video (and says what is missing beside it).
    assert [r.name for r in READERS] == ["realsense-bag", "rosbag2", "gopro", "camera-telemetry", "video", "folder",
                                         "d435i-sample", "euroc", "video-folder"]


def test_a_registered_reader_opens_its_extension(registry, tmp_path):
    seen = []
    toy = register_reader(Reader("toy", lambda p: p.is_file() and p.suffix == ".toy", _toy_open(seen),
                                 "a toy recording (.toy)"))
    assert registry[-1] is toy
    path = tmp_path / "run.toy"
    path.write_text("toy")
    fo = open_footage(path, require_imu=False, clock_offset=0.05)
    assert fo.kind == "toy" and len(fo) == 3 and fo.camera == CAMERA
    ((opened, options),) = seen
    assert opened == path and options["require_imu"] is False and options["camera"] is None
    # What open_footage does for every reader is done for this one too: the IMU moved onto the frames' clock.
    np.testing.assert_allclose(fo.imu.time_s, np.linspace(0.05, 0.45, 5))
    assert fo.clock_offset_s == 0.05 and fo.clock_offset_source == "given"
    # An option the toy layout has no use for is refused, as for the built-in layouts.
    with pytest.raises(FootageError, match=r"--stream .* this is a toy footage"):
        open_footage(path, stream="Color_0")


def test_a_reader_registered_before_another_wins(registry, tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "frames.csv").write_text("frame,time_s,file\n")
    seen = []
    register_reader(Reader("toy-folder", lambda p: p.is_dir() and (p / "frames.csv").exists(), _toy_open(seen)),
                    before="folder")
    assert [r.name for r in registry].index("toy-folder") == [r.name for r in registry].index("folder") - 1
    assert open_footage(folder).kind == "toy" and seen[0][0] == folder
    with pytest.raises(ValueError, match="no reader named 'nothing'"):
        register_reader(Reader("x", lambda p: False, _toy_open([])), before="nothing")


def test_an_unknown_path_names_itself_and_the_known_layouts(registry, tmp_path):
    odd = tmp_path / "notes.xyz"
    odd.write_text("not footage")
    with pytest.raises(FootageError) as err:
        open_footage(odd)
    msg = str(err.value)
    assert msg.startswith(f"{odd}: no reader recognises it")
    for r in registry:
        assert r.describe() in msg
    register_reader(Reader("toy", lambda p: p.suffix == ".toy", _toy_open([]), "a toy recording (.toy)"))
    with pytest.raises(FootageError, match=r"toy \(a toy recording \(\.toy\)\)"):
        open_footage(odd)
    with pytest.raises(FootageError, match=r"absent\.toy: not found .*toy \(a toy recording"):
        open_footage(tmp_path / "absent.toy")


def test_an_empty_folder_is_no_layout(tmp_path):
    with pytest.raises(FootageError, match=f"{tmp_path}: no reader recognises it; the layouts known: "
                                           f"realsense-bag"):
        open_footage(tmp_path)
    assert known_layouts().split("; ")[-1] == "video-folder (a folder holding one video)"


def test_a_bad_camera_json_is_named_before_the_layout_is_looked_for(tmp_path):
    bad = tmp_path / "camera.json"
    bad.write_text(json.dumps({"width": 8}))
    with pytest.raises(FootageError, match=r"camera\.json: missing height"):
        open_footage(tmp_path, camera=bad)
