"""Faults a user meets on real machines and recordings: each is one line naming the real file and the fix.

Every test reproduces its fault on a tiny synthetic input and checks the line on stderr (exactly one,
"lobula COMMAND: error: …", no traceback), the exit status, and that no output and no temporary
(hidden ``.NAME.lobula-tmp-…`` file, ``.NAME.partial-…`` folder) is left behind. Read-only and full
file systems are tmpfs mounts where the test may mount them (root; skipped with the reason elsewhere),
beside tests that make the same write fail by monkeypatching, which run everywhere.
"""
from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
import xarray as xr

from experiments.cli import main
from experiments.store import TEMP_TAG
from lobula.readers import open_footage
from stimuli.footage_writer import RUN_START, remove_stale
from stimuli.scene import SceneConfig
from stimuli.track import TrackRunConfig, make_track_run

REPO = Path(__file__).resolve().parents[1]
ACCEL = "/device_0/sensor_1/Accel_0/imu/data"


# ---------------------------------------------------------------------------------------------- helpers
@pytest.fixture(scope="module")
def run2(tmp_path_factory) -> Path:
    """2 s of a small (160×120) synthetic run in motion, with exact truth and an IMU."""
    cfg = TrackRunConfig(profile=None, start_s=6.0, duration_s=2.0, scale=0.25, scene=SceneConfig(seed=2))
    return make_track_run(tmp_path_factory.mktemp("run2") / "run", cfg, progress=False)


def cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def lobula(*argv, timeout=300):
    """`lobula ARGV` in a fresh process: (exit status, stdout, stderr)."""
    r = subprocess.run([sys.executable, "-m", "experiments.cli", *map(str, argv)], cwd=REPO, capture_output=True,
                       text=True, timeout=timeout)
    return r.returncode, r.stdout, r.stderr


def one_error(err: str, command: str, *needles: str) -> str:
    """The one line of stderr, checked: "lobula COMMAND: error: …" holding every needle, no traceback."""
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"lobula {command}: error: "), lines[0]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def entries(folder: Path) -> set[str]:
    """Every name in ``folder``, hidden ones too."""
    return {p.name for p in Path(folder).iterdir()}


@contextmanager
def tmpfs(path: Path, size: str = "64k", readonly: bool = False):
    """A tmpfs of ``size`` mounted at ``path`` (read-only if asked); skips where mounting is not permitted."""
    path.mkdir(parents=True, exist_ok=True)
    opts = f"size={size}" + (",ro" if readonly else "")
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)], capture_output=True, text=True)
    except FileNotFoundError:
        pytest.skip("no mount command here")
    if r.returncode:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {r.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


@contextmanager
def read_only_folder(path: Path):
    """A folder nothing can be written into: a read-only tmpfs as root (who ignores permissions), else mode 0555."""
    if os.geteuid() == 0:
        with tmpfs(path, readonly=True) as p:
            yield p
        return
    path.mkdir(parents=True)
    path.chmod(0o555)
    try:
        yield path
    finally:
        path.chmod(0o755)


def dead_pid() -> int:
    """The id of a process that has ended."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def write_db3(run: Path, folder: Path, empty_frame: int | None = None, garbage_frame: int | None = None,
              imu_shift_s: float = 0.0, camera_info: bool = True) -> Path:
    """A RealSense-style rosbag2 .db3 of a footage folder (colour PNGs, device-clock metadata, accelerometer and
    gyroscope in the camera frame), as librealsense ≥ 2.58 records one; frames may be empty or garbage, the IMU's
    stamps shifted by ``imu_shift_s``, the CameraInfo left out."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    fo = open_footage(run)
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    colour, t0 = "/device_0/sensor_0/Color_0", 1_000_000_000

    def header(ns):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id="x")

    def meta(t_s):
        return ts.serialize_cdr(T["std_msgs/msg/String"](
            data=f"timestamp_domain=Global Time;timestamp={5000.0 + t_s * 1e3:.6f};"), "std_msgs/msg/String")

    def vec(v):
        return T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    msgs = []   # (record ns, topic, raw)
    for i, t, img in fo.frames():
        ns = t0 + round(t * 1e9)
        png = np.frombuffer(cv2.imencode(".png", cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_GRAY2BGR))[1], np.uint8)
        if i == empty_frame:
            png = np.zeros(0, np.uint8)
        if i == garbage_frame:
            png = np.frombuffer(b"\x89PNG\r\n\x1a\n" + b"garbage" * 30, np.uint8)
        msgs.append((ns, f"{colour}/image/data/compressed", ts.serialize_cdr(T["sensor_msgs/msg/CompressedImage"](
            header=header(ns), format="rgb8; png compressed bgr8", data=png), "sensor_msgs/msg/CompressedImage")))
        msgs.append((ns, f"{colour}/image/metadata", meta(t)))
        if i == 0 and camera_info:
            c = fo.camera
            roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
            msgs.append((ns, f"{colour}/image/camera_info", ts.serialize_cdr(T["sensor_msgs/msg/CameraInfo"](
                header=header(ns), height=c.height, width=c.width, distortion_model="plumb_bob", d=np.zeros(5),
                k=np.array([c.fx, 0, c.cx, 0, c.fy, c.cy, 0, 0, 1.0]), r=np.eye(3).ravel(), p=np.zeros(12),
                binning_x=0, binning_y=0, roi=roi), "sensor_msgs/msg/CameraInfo")))
    imu = fo.imu
    for t, a, g in zip(imu.time_s + imu_shift_s, imu.accel, imu.gyro):
        ns = t0 + round(t * 1e9)
        for kind, lin, ang in (("Accel_0", a, np.zeros(3)), ("Gyro_0", np.zeros(3), g)):
            raw = ts.serialize_cdr(T["sensor_msgs/msg/Imu"](
                header=header(ns), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9), angular_velocity=vec(ang), angular_velocity_covariance=np.zeros(9),
                linear_acceleration=vec(lin), linear_acceleration_covariance=np.zeros(9)), "sensor_msgs/msg/Imu")
            msgs.append((ns, f"/device_0/sensor_1/{kind}/imu/data", raw))
            msgs.append((ns, f"/device_0/sensor_1/{kind}/imu/metadata", meta(t)))
    types = {"compressed": "sensor_msgs/msg/CompressedImage", "camera_info": "sensor_msgs/msg/CameraInfo",
             "metadata": "std_msgs/msg/String", "data": "sensor_msgs/msg/Imu"}
    with Writer(folder, version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        conns = {}
        for ns, topic, raw in sorted(msgs, key=lambda m: m[0]):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, types[topic.rsplit("/", 1)[1]], typestore=ts)
            w.write(conns[topic], ns, raw)
    return next(folder.glob("*.db3"))


def write_camera_json(path: Path, run: Path, **change) -> Path:
    cam = json.loads((run / "camera.json").read_text())
    cam.update(change)
    path.write_text(json.dumps(cam))
    return path


# ------------------------------------------------------------------ 1. a zero-byte or corrupt frame in a .db3
def test_empty_or_corrupt_db3_frame_is_one_line_or_skipped(run2, tmp_path, capsys):
    db3 = write_db3(run2, tmp_path / "bag", empty_frame=10, garbage_frame=20)
    out = tmp_path / "o" / "v.nc"
    code, _, err = cli(capsys, "velocity", db3, "--out", out, "--quiet")
    assert code == 2
    one_error(err, "velocity", str(db3), "frame 10", "empty (0 bytes", "--skip-bad-frames")
    assert not out.parent.exists() or entries(out.parent) == set()
    code, text, err = cli(capsys, "velocity", db3, "--out", out, "--quiet", "--skip-bad-frames")
    assert code == 0, err
    assert err == ""                                   # nor OpenCV's own log of the damaged PNG
    assert "left out 2 frame(s) that could not be decoded (--skip-bad-frames): 10, 20" in text
    with xr.open_dataset(out) as ds:
        assert int(ds.attrs["frames_skipped"]) == 2 and json.loads(ds.attrs["frames_skipped_indices"]) == [10, 20]
        # the filter ran through the skipped frames: its posterior holds on every frame
        assert ds.attrs["footage_layout"] == "realsense-db3" and bool(np.isfinite(ds.posterior_std).all())
    assert entries(out.parent) == {"v.nc"}


# ------------------------------------------------------------------ 2. a read-only output folder
def test_read_only_output_is_refused_before_the_run(run2, tmp_path, capsys, monkeypatch):
    import experiments.velocity as velocity

    def never(*a, **k):
        raise AssertionError("the run started although its output cannot be written")

    monkeypatch.setattr(velocity, "estimate_velocity", never)
    with read_only_folder(tmp_path / "ro") as ro:
        code, out, err = cli(capsys, "velocity", run2, "--out", ro / "o.nc", "--quiet")
        assert code == 2 and out == ""
        line = one_error(err, "velocity")
        want = f"lobula velocity: error: cannot write {ro / 'o.nc'}: folder is read-only; choose another --out"
        assert line == want or (os.geteuid() != 0 and "no permission to write" in line
                                and "choose another --out" in line), line
        # --plot into the read-only folder, --out elsewhere: refused before the run, and no .nc either
        nc = tmp_path / "ok" / "o.nc"
        code, out, err = cli(capsys, "velocity", run2, "--out", nc, "--plot", ro / "o.png", "--quiet")
        assert code == 2 and out == ""
        one_error(err, "velocity", f"cannot write {ro / 'o.png'}", "choose another --plot")
        assert not nc.parent.exists()
        assert entries(ro) == set()
        # every command's outputs are checked: a CSV of compare, a suite's folder, a scene's folder
        code, _, err = cli(capsys, "compare", run2, "--out", nc, "--csv", ro / "t.csv", "--quiet")
        assert code == 2
        one_error(err, "compare", f"cannot write {ro / 't.csv'}", "choose another --csv")
        code, _, err = cli(capsys, "suite", "--out", ro / "suite", "--families", "rest", "--seeds", "1")
        assert code == 2
        one_error(err, "suite", f"cannot write {ro / 'suite'}", "choose another --out")
        code, _, err = cli(capsys, "scene", ro / "sc", "--duration", "1", "--scale", "0.25", "--builtin-profile")
        assert code == 2
        one_error(err, "scene", f"cannot write {ro / 'sc'}", "choose another OUT")
        assert entries(ro) == set()
    # an output named like an existing folder is refused the same way
    (tmp_path / "isdir.nc").mkdir()
    code, _, err = cli(capsys, "velocity", run2, "--out", tmp_path / "isdir.nc", "--quiet")
    assert code == 2
    one_error(err, "velocity", "a folder of that name exists", "give a file name")


def test_outputs_that_cannot_all_be_written_are_refused_before_the_run(run2, tmp_path, capsys, monkeypatch):
    """Two options naming one file (one would overwrite the other), a figure in a format not drawn, and a device or
    pipe where a file is asked for (the output would be renamed onto it, replacing it): one line each, before the
    run, nothing made."""
    import experiments.velocity as velocity

    def never(*a, **k):
        raise AssertionError("the run started although its outputs cannot all be written")

    monkeypatch.setattr(velocity, "estimate_velocity", never)
    out = tmp_path / "out"
    out.mkdir()
    for argv, needles in (
            (["--out", out / "o.nc", "--tum", out / "o.nc"], ("--out and --tum both name", "give each its own file")),
            (["--out", out / "o.nc", "--plot", out / "o.nc"], ("--out and --plot both name",)),
            (["--out", out / "o.nc", "--plot", out / "o.xyz"], ("--plot", "use a .png, .pdf or .svg file")),
            (["--out", out / "o.txt"], ("--out", "lobula velocity writes NetCDF; give a name ending in .nc"))):
        code, printed, err = cli(capsys, "velocity", run2, *argv, "--quiet")
        assert code == 2 and printed == ""
        one_error(err, "velocity", *needles)
    code, _, err = cli(capsys, "compare", run2, "--out", out / "c.nc", "--csv", out / "c.nc", "--quiet")
    assert code == 2
    one_error(err, "compare", "--out and --csv both name")
    code, _, err = cli(capsys, "ephys", "looming", "--out", out / "l.nc", "--plot", out / "l.svg")
    assert code == 2  # ephys draws a PNG and a PDF beside it
    one_error(err, "ephys", "--plot", "use a .png or .pdf file")
    fifo = out / "pipe.nc"
    os.mkfifo(fifo)
    code, _, err = cli(capsys, "velocity", run2, "--out", fifo, "--quiet")
    assert code == 2
    one_error(err, "velocity", "it is a device or a pipe, not a file")
    assert entries(out) == {"pipe.nc"} and fifo.is_fifo()


def test_a_refused_option_is_one_line_that_names_it(capsys):
    """argparse's refusal without its usage block: the option, why, and where the options are told."""
    code, printed, err = cli(capsys, "velocity", "x", "--out", "o.nc", "--gap", "0")
    assert code == 2 and printed == ""
    one_error(err, "velocity", "argument --gap", "(options: lobula velocity --help)")
    code, _, err = cli(capsys, "scene", "x", "--scale", "50")
    assert code == 2
    one_error(err, "scene", "argument --scale", "(0, 4]")


def test_an_interrupt_before_the_run_begins_is_one_line(capsys, monkeypatch):
    """SIGINT while the command line is still being read (its imports, its parser): one line, the signal's code."""
    import experiments.cli as cli_module

    def interrupted(argv):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_module, "build_parser", interrupted)
    code, printed, err = cli(capsys, "velocity", "x", "--out", "o.nc")
    assert code == 130 and printed == ""
    assert err.strip() == "lobula velocity: interrupted; nothing written"


def test_values_a_run_cannot_use_are_refused_before_its_work(run2, tmp_path, capsys):
    """A torch device this machine lacks, a sweep scheduler that is neither local nor an address, a scene too short
    for two frames or whose rolling shutter outlasts a frame, a suite into a footage folder: one line, nothing made."""
    code, _, err = cli(capsys, "depth", run2, "--method", "tv", "--device", "foo", "--out", tmp_path / "d.nc")
    assert code == 2
    one_error(err, "depth", "--device 'foo' is not a torch device")
    for argv, needle in ((["--out", tmp_path / "s.zarr", "--scheduler", "foo"], "tcp://HOST:PORT"),
                         (["--out", tmp_path / "s.nc"], "a sweep is a Zarr store"),
                         (["--out", tmp_path / "s.zarr", "--base-duration", "1.6"], "leave nothing to score")):
        code, _, err = cli(capsys, "sweep", "--param", "readout.cutoff_hz=1,2", "--builtin-profile", *argv)
        assert code == 2
        one_error(err, "sweep", needle)
    for argv, needle in ((["--duration", "0.01"], "holds 1 frame(s) at 30 Hz"),
                         (["--duration", "0.5", "--rolling-shutter", "0.05"], "reads out longer than a frame lasts")):
        code, _, err = cli(capsys, "scene", tmp_path / "sc", "--scale", "0.25", "--builtin-profile", *argv, "--quiet")
        assert code == 2
        one_error(err, "scene", needle)
    code, _, err = cli(capsys, "suite", "--out", run2, "--families", "rest", "--seeds", "1")
    assert code == 2
    one_error(err, "suite", "is a footage folder (camera.json)")
    assert entries(tmp_path) == set()
    assert not (run2 / "results").exists() and not (run2 / "scenes").exists()


def test_an_input_file_that_is_not_what_its_option_needs_is_named(run2, tmp_path, capsys):
    """A configuration with a key it does not have or a field size below 0, a velocity run that is no NetCDF: one
    line naming the file, before any work."""
    bad = tmp_path / "bad.json"
    for text, needle in (('{"nonsense_key": 1}', "no field 'nonsense_key'"), ("[1, 2]", "a JSON object is needed"),
                         ('{"fields": {"size_deg": -3}}', "FieldConfig.size_deg must be")):
        bad.write_text(text)
        code, _, err = cli(capsys, "compare", run2, "--out", tmp_path / "c.nc", "--config", bad, "--quiet")
        assert code == 2
        one_error(err, "compare", f"{bad}: not a VelocityConfig JSON", needle)
    not_nc = tmp_path / "run.nc"
    not_nc.write_text("not a NetCDF\n")
    code, _, err = cli(capsys, "depth", run2, "--velocity-run", not_nc, "--out", tmp_path / "d.nc", "--quiet")
    assert code == 2
    one_error(err, "depth", f"{not_nc}: not a readable NetCDF velocity run")
    assert entries(tmp_path) == {"bad.json", "run.nc"}


def test_outputs_of_a_run_appear_together_or_not_at_all(run2, tmp_path, capsys, monkeypatch):
    """The figure fails after the NetCDF is written (a disk that fills between the two): neither is kept."""
    from matplotlib.figure import Figure

    def full(self, fname, **kw):
        Path(fname).write_bytes(b"\x89PNG half")        # what a writer leaves when the disk fills
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Figure, "savefig", full)
    out, png = tmp_path / "o" / "v.nc", tmp_path / "o" / "v.png"
    code, _, err = cli(capsys, "velocity", run2, "--out", out, "--plot", png, "--quiet")
    assert code == 2
    one_error(err, "velocity", f"no space left on device writing {png}", "choose another --plot",
              f"{out} not kept")
    assert entries(out.parent) == set()


# ------------------------------------------------------------------ 3. a full disk
def test_full_disk_while_writing_is_one_line(run2, tmp_path, capsys, monkeypatch):
    """The NetCDF's bytes meet a full disk half-way (monkeypatched: runs everywhere)."""
    real = Path.write_bytes

    def full(self, data):
        if TEMP_TAG in self.name:
            real(self, bytes(data)[:100])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", full)
    out = tmp_path / "o" / "v.nc"
    code, _, err = cli(capsys, "velocity", run2, "--out", out, "--quiet")
    assert code == 2
    assert one_error(err, "velocity") == (f"lobula velocity: error: no space left on device writing {out}; "
                                          f"free some space or choose another --out")
    assert entries(out.parent) == set()


def test_full_tmpfs_is_one_line_no_crash_no_temporary(run2, tmp_path):
    """A real full file system (a 64 KiB tmpfs): one line and exit status 2, no traceback, no crash at exit
    (HDF5 writing onto the full disk itself ends in a segmentation fault, rc 139), nothing left."""
    with tmpfs(tmp_path / "full", "64k") as full:
        code, _, err = lobula("velocity", run2, "--out", full / "v.nc", "--quiet")
        assert code == 2
        one_error(err, "velocity", f"no space left on device writing {full / 'v.nc'}", "choose another --out")
        assert entries(full) == set()
        code, _, err = lobula("scene", full / "sc", "--duration", "2", "--scale", "0.25", "--builtin-profile",
                              "--quiet")
        assert code == 2
        one_error(err, "scene", f"no space left on device writing {full / 'sc'}", "choose another OUT")
        assert entries(full) == set()


# ------------------------------------------------------------------ 4. signals
#: runs `lobula ARGV[2:]` with the figure held: a marker file (ARGV[1]) says the run has reached it, with the
#: NetCDF written under its temporary name and waiting for the figure (the run's outputs appear together)
HELD_AT_FIGURE = """
import sys, time
import experiments.velocity as v
def held(*a, **k):
    open(sys.argv[1], "w").close()
    time.sleep(120)
v.velocity_figure = held
from experiments.cli import main
sys.exit(main(sys.argv[2:]))
"""


def _interruptible():
    """In the child: SIGINT as a terminal gives it. A suite started in the background (``make test &``) runs
    with SIGINT ignored, which the CLI, like any program, leaves ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_held(run2, tmp_path):
    marker, out = tmp_path / "marker", tmp_path / "o" / "v.nc"
    p = subprocess.Popen([sys.executable, "-c", HELD_AT_FIGURE, str(marker), "velocity", str(run2), "--out", str(out),
                          "--plot", str(out.with_suffix(".png")), "--quiet"], cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, preexec_fn=_interruptible)
    deadline = time.monotonic() + 240
    while not marker.exists():
        assert p.poll() is None, p.communicate()
        assert time.monotonic() < deadline, "the run never reached its figure"
        time.sleep(0.05)
    temps = [n for n in entries(out.parent) if n.startswith(f".v.nc.{TEMP_TAG}-{p.pid}-")]
    assert len(temps) == 1, entries(out.parent)    # the moment a signal would have left it behind
    return p, out


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_and_sigint_remove_temporaries_and_say_so(run2, tmp_path, sig):
    p, out = _start_held(run2, tmp_path)
    p.send_signal(sig)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 128 + sig, (p.returncode, err)
    assert "Traceback" not in err and err.strip().splitlines() == ["lobula velocity: interrupted; nothing written"]
    assert entries(out.parent) == set()


#: runs `lobula ARGV[1:]` with a Ctrl-C that lands while the NWB file object is finalised (its ``__del__``),
#: where Python would ignore the KeyboardInterrupt ("Exception ignored in …") and the run would go on
INTERRUPTED_IN_NWB_FINALISER = """
import os, signal, sys
import pynwb
def landing(self):
    os.kill(os.getpid(), signal.SIGINT)
pynwb.NWBFile.__del__ = landing
from experiments.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_an_interrupt_while_the_nwb_objects_are_finalised_ends_the_run(tmp_path):
    out = tmp_path / "o" / "rec.nwb"
    p = subprocess.run([sys.executable, "-c", INTERRUPTED_IN_NWB_FINALISER, "ephys", "looming", "--l-over-v", "0.04",
                        "--duration", "0.3", "--dphi", "4", "--field-size", "20", "--out", str(out),
                        str(out.with_suffix(".nc")), "--quiet"], cwd=REPO, capture_output=True, text=True,
                       timeout=300, preexec_fn=_interruptible)
    assert p.returncode == 128 + signal.SIGINT, (p.returncode, p.stderr)
    assert "Traceback" not in p.stderr and "Exception ignored" not in p.stderr, p.stderr
    assert p.stderr.strip().splitlines() == ["lobula ephys: interrupted; nothing written"]
    assert not out.parent.exists() or entries(out.parent) == set()


def test_the_next_run_removes_what_sigkill_left(run2, tmp_path):
    p, out = _start_held(run2, tmp_path)
    p.kill()
    p.communicate(timeout=60)
    assert p.returncode == -signal.SIGKILL
    left = entries(out.parent)
    assert len(left) == 1 and left.pop().startswith(f".v.nc.{TEMP_TAG}-{p.pid}-")  # SIGKILL cannot be caught
    code, _, err = lobula("velocity", run2, "--out", out, "--quiet")
    assert code == 0, err
    assert entries(out.parent) == {"v.nc"}


def test_remove_stale_spares_live_and_new_temporaries(tmp_path):
    gone, live = dead_pid(), os.getppid()
    old = RUN_START - 60
    names = {"stale": f".o.nc.{TEMP_TAG}-{gone}-abc.tmp", "live": f".o.nc.{TEMP_TAG}-{live}-def.tmp",
             "new": f".o.nc.{TEMP_TAG}-{gone}-ghi.tmp", "other": f".p.nc.{TEMP_TAG}-{gone}-jkl.tmp",
             "plain": "o.nc", "folder": f".o.nc.{TEMP_TAG}-{gone}-mno"}
    for k, n in names.items():
        if k == "folder":
            (tmp_path / n).mkdir()
        else:
            (tmp_path / n).write_text(k)
        if k != "new":
            os.utime(tmp_path / n, (old, old))
    removed = remove_stale(tmp_path, f".o.nc.{TEMP_TAG}-")
    assert sorted(p.name for p in removed) == sorted([names["stale"], names["folder"]])
    assert entries(tmp_path) == {names[k] for k in ("live", "new", "other", "plain")}


def test_suite_interrupted_or_killed_leaves_no_partial_scene(tmp_path):
    out = tmp_path / "suite"
    argv = [sys.executable, "-m", "experiments.cli", "suite", "--out", str(out), "--families", "rest", "--seeds", "1",
            "--duration", "3", "--skip", "1", "--scale", "0.25", "--configurations", "zero", "--quiet"]

    def partials():
        scenes = out / "scenes"
        return [n for n in (entries(scenes) if scenes.is_dir() else ()) if ".partial-" in n or ".track-" in n]

    def start_and_wait_for_render():
        p = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 240
        while not partials():
            assert p.poll() is None, p.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.01)
        return p

    p = start_and_wait_for_render()
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 143 and err.strip().splitlines() == ["lobula suite: interrupted; nothing written"], err
    assert partials() == []
    p = start_and_wait_for_render()
    p.kill()
    p.communicate(timeout=60)
    assert partials()                                   # SIGKILL cannot be caught
    ghost = out / "scenes" / f".ghost-s9.partial-{dead_pid()}"   # a scene this run does not render again
    ghost.mkdir()
    os.utime(ghost, (RUN_START, RUN_START))
    r = subprocess.run(argv[:-1], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "removed 2 partial scene folder(s) a stopped run left" in r.stdout
    assert partials() == [] and (out / "suite.nc").exists() and (out / "scenes" / "rest-s0" / "frames.csv").exists()


# ------------------------------------------------------------------ 5. misleading messages
def test_imu_overlap_names_the_real_imu_file(run2, tmp_path, capsys):
    db3 = write_db3(run2, tmp_path / "bag", imu_shift_s=5.0)
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", db3, "--out", out, "--quiet")
    assert code == 2
    one_error(err, "velocity", f"{db3}:{ACCEL}", "the IMU covers 5.00..7.00 s", "--clock-offset")
    assert "imu.csv" not in err and not out.exists()
    # a video with an IMU log beside it: the log is named, not "VIDEO/imu.csv"
    v = tmp_path / "v"
    v.mkdir()
    fo = open_footage(run2)
    video = v / "rec.avi"
    wr = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (fo.camera.width, fo.camera.height))
    for _, _, img in fo.frames():
        wr.write(cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_GRAY2BGR))
    wr.release()
    shutil.copy(run2 / "camera.json", v / "camera.json")
    rows = (run2 / "imu.csv").read_text().splitlines()
    shifted = [rows[0]] + [f"{float(r.split(',')[0]) + 5.0:.6f}," + r.split(",", 1)[1] for r in rows[1:]]
    (v / "imu.csv").write_text("\n".join(shifted) + "\n")
    code, _, err = cli(capsys, "velocity", video, "--out", out, "--quiet")
    assert code == 2
    one_error(err, "velocity", f"{v / 'imu.csv'}: the IMU covers 5.00..", "--clock-offset")
    assert f"{video}/imu.csv" not in err and not out.exists()


def test_duplicate_video_time_stamps_say_what_is_wrong(tmp_path, capsys):
    import fractions

    import av

    video = tmp_path / "dup.mkv"
    with av.open(str(video), "w") as c:
        s = c.add_stream("mjpeg", rate=30)
        s.width, s.height, s.pix_fmt, s.time_base = 32, 24, "yuvj420p", fractions.Fraction(1, 1000)
        stamps = [0, 33, 67, 67, 100, 133, 167, 200]              # frames 2 and 3 share a time stamp
        for k, pts in enumerate(stamps):
            f = av.VideoFrame.from_ndarray(np.full((24, 32, 3), 20 * k, np.uint8), format="rgb24")
            f.pts, f.time_base = k, fractions.Fraction(1, 30)
            for pkt in s.encode(f):
                pkt.pts = pkt.dts = pts
                pkt.time_base = s.time_base
                c.mux(pkt)
    (tmp_path / "camera.json").write_text(json.dumps(dict(width=32, height=24, fx=30.0, fy=30.0, cx=16.0, cy=12.0,
                                                          frame_rate_hz=30.0)))
    code, _, err = cli(capsys, "info", video)
    assert code == 2
    one_error(err, "info", str(video), "time stamps are broken", "frames 2 and 3, both at 0.067000 s",
              "re-encode", "ffmpeg")
    assert "sort the rows" not in err


def test_negative_focal_length_names_the_field(run2, tmp_path, capsys):
    bad = tmp_path / "bad"
    shutil.copytree(run2, bad)
    write_camera_json(bad / "camera.json", run2, fx=-500)
    code, _, err = cli(capsys, "info", bad)
    assert code == 2
    one_error(err, "info", f"{bad / 'camera.json'}: fx must be > 0, got -500")
    assert "PinholeCamera(" not in err
    neg = write_camera_json(tmp_path / "neg.json", run2, fy=0)
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", run2, "--camera", neg, "--out", out, "--quiet")
    assert code == 2
    one_error(err, "velocity", f"{neg}: fy must be > 0, got 0")
    assert not out.exists()


def test_a_walking_heading_without_the_heading_fit_names_the_footage(run2, tmp_path, capsys):
    """--heading-walk lets the joint heading-and-bias fit's heading walk; with the epipole held at the principal
    point (or without a gyro) that fit does not run, and the option is refused, not ignored."""
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", run2, "--heading-walk", "0.15", "--epipole", "principal", "--out", out, "--quiet")
    assert code == 2
    one_error(err, "velocity", f"{run2}: heading_walk", "drop --heading-walk")
    assert not out.exists()


def test_camera_option_gives_a_bag_its_intrinsics_on_every_reader_command(run2, tmp_path, capsys):
    db3 = write_db3(run2, tmp_path / "bag", camera_info=False)
    out = tmp_path / "o.nc"
    for command in ("info", "velocity", "compare", "depth"):
        argv = [command, db3] + (["--out", out] if command != "info" else [])
        code, _, err = cli(capsys, *argv)
        assert code == 2
        one_error(err, command, str(db3), "has no intrinsics", "--camera FILE")
        assert "camera=PinholeCamera" not in err
        neg = write_camera_json(tmp_path / "neg.json", run2, fx=-500)
        code, _, err = cli(capsys, *argv, "--camera", neg)         # the option is read on every command
        assert code == 2
        one_error(err, command, f"{neg}: fx must be > 0, got -500")
    cam = write_camera_json(tmp_path / "cam.json", run2, fx=150.0)
    code, text, err = cli(capsys, "info", db3, "--camera", cam, "--json")
    assert code == 0, err
    d = json.loads(text)
    assert d["intrinsics"]["fx"] == 150.0 and any(str(cam) in n for n in d["notes"])
    code, _, err = cli(capsys, "velocity", db3, "--camera", cam, "--out", out, "--quiet")
    assert code == 0, err
    with xr.open_dataset(out) as ds:
        assert json.loads(ds.attrs["camera_intrinsics"])["fx"] == 150.0


def test_a_camera_files_imu_rotation_a_bag_would_not_apply_is_refused(run2, tmp_path, capsys):
    """A bag's own extrinsics put its IMU in the camera frame: a --camera file's imu_to_camera (or a Kalibr
    T_cam_imu) would be dropped without a word, so it is one line naming the file."""
    db3 = write_db3(run2, tmp_path / "bag")
    turned = write_camera_json(tmp_path / "turned.json", run2, imu_to_camera=[[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", db3, "--camera", turned, "--out", out)
    assert code == 2 and not out.exists()
    one_error(err, "velocity", f"{turned}: its IMU rotation", "is not applied to a realsense-db3 recording")
    assert open_footage(db3, camera=write_camera_json(tmp_path / "plain.json", run2)).kind == "realsense-db3"
    assert open_footage(run2, camera=turned).imu_to_camera is not None  # a folder applies it


def test_info_counts_nans_in_imu_and_truth(run2, tmp_path, capsys):
    run = tmp_path / "nan"
    shutil.copytree(run2, run)
    imu = (run / "imu.csv").read_text().splitlines()
    n_imu = len(imu) - 1
    for row, col, val in ((5, 1, "nan"), (7, 6, ""), (9, 1, "NaN")):      # data rows 5, 7, 9 (file rows 7, 9, 11)
        cells = imu[row + 1].split(",")
        cells[col] = val
        imu[row + 1] = ",".join(cells)
    (run / "imu.csv").write_text("\n".join(imu) + "\n")
    truth = (run / "truth.csv").read_text().splitlines()
    cells = truth[4].split(",")
    cells[1] = "nan"
    truth[4] = ",".join(cells)
    (run / "truth.csv").write_text("\n".join(truth) + "\n")
    code, text, err = cli(capsys, "info", run)
    assert code == 0 and err == ""
    assert "  gyro:     x " in text and "gyro:     none" not in text
    assert f"NaN:      accel_x 2, gyro_z 1 rows of {run / 'imu.csv'} are NaN or empty" in text
    assert "NaN:      v_forward_m_s 1 rows of the truth" in text
    code, text, _ = cli(capsys, "info", run, "--json")
    d = json.loads(text)
    assert d["imu"]["nan_rows"] == {"accel_x": 2, "gyro_z": 1} and d["imu"]["samples"] == n_imu
    assert d["truth"]["nan_rows"] == {"v_forward_m_s": 1}
    assert all(v is not None for v in d["imu"]["accel_range_m_s2"].values())
    out = tmp_path / "o.nc"
    code, _, err = cli(capsys, "velocity", run, "--out", out, "--quiet")
    assert code == 2
    one_error(err, "velocity", f"{run / 'imu.csv'}: NaN or missing values in accel_x, gyro_z (first at row 7)")
    assert not out.exists()


# ------------------------------------------------------------------ 6. why a run is never observable
def test_constant_velocity_run_says_why_it_is_never_observable(tmp_path, capsys):
    run = make_track_run(tmp_path / "cv", TrackRunConfig(constant_velocity_m_s=1.0, duration_s=3.0, scale=0.25),
                         progress=False)
    out = tmp_path / "cv.nc"
    code, text, err = cli(capsys, "velocity", run, "--out", out, "--quiet")
    assert code == 0, err
    why = [ln for ln in text.splitlines() if ln.startswith("never observable")]
    assert len(why) == 1, text
    assert why[0].startswith("never observable: the forward acceleration never exceeded the readout's "
                             "accel_min (0.03 m/s²; at most 0.0")
    assert "speed cannot be told from vision while it does not change; v̂ is NaN throughout" in why[0]
    with xr.open_dataset(out) as ds:
        assert not ds.observable.values.any()


def test_never_observable_reason_is_read_from_the_stored_run(run2, tmp_path, capsys):
    from experiments.velocity import never_observable_reason

    out = tmp_path / "o.nc"
    code, _, _ = cli(capsys, "velocity", run2, "--out", out, "--quiet")
    assert code == 0
    with xr.load_dataset(out) as ds:
        cfg = json.loads(ds.attrs["config"])
        ds["observable"] = ds.observable | (ds.time == ds.time[-1])  # observable somewhere: no reason to give
        assert never_observable_reason(ds) is None
        ds["observable"] = ds.observable * False                  # the same accelerations, never observable:
        ds["vision_locked"] = ds.vision_locked | True              # vision locked on, the posterior never sure
        ds["posterior_std"] = ds.posterior_std * 0 + 0.5
        why = never_observable_reason(ds)
        assert why.startswith(f"never observable: the posterior std of v̂ never fell below the readout's max_std "
                              f"({cfg['readout']['max_std_m_s']:g} m/s; at best 0.500 m/s)")
        ds["vision_locked"] = ds.vision_locked & False             # vision never locked on
        ds["vision_refuted"] = ds.vision_refuted & False
        assert "the image's expansion never followed the accelerometer" in never_observable_reason(ds)
        assert "refuted" not in never_observable_reason(ds)
        ds["vision_refuted"] = ds.vision_refuted | (ds.time >= ds.time[ds.sizes["time"] // 2])  # the second half
        assert "refuted on 50 % of the frames" in never_observable_reason(ds)
        ds["r"] = ds.r * np.nan
        assert "no receptive field measured an expansion rate" in never_observable_reason(ds)


def test_compare_without_truth_says_why_its_accuracy_is_empty(run2, tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(run2, run)
    (run / "truth.csv").unlink()
    code, text, err = cli(capsys, "compare", run, "--front-ends", "dis", "--out", tmp_path / "c.nc", "--quiet")
    assert code == 0, err
    assert f"{run} holds no truth: the accuracy columns are empty" in text
    # acceleration from a truth it lacks: one line before any front end runs, not one per front end
    code, _, err = cli(capsys, "compare", run, "--out", tmp_path / "c2.nc", "--accel-from-truth", "--quiet")
    assert code == 2
    one_error(err, "compare", f"{run / 'truth.csv'}: missing", "drop --accel-from-truth")


def test_a_warning_during_a_command_is_one_line_naming_it(capsys):
    """Python shows a warning as two lines (the file, then the source line that warned); a command shows one."""
    import warnings

    import experiments.cli as cli_module

    before = warnings.showwarning
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        with cli_module._one_line_warnings("suite"):
            warnings.warn("acceptance σ is 0.68 px on this camera", UserWarning)
    assert capsys.readouterr().err == "lobula suite: warning: acceptance σ is 0.68 px on this camera\n"
    assert warnings.showwarning is before


def test_options_of_another_front_end_are_refused_not_ignored(run2, tmp_path, capsys):
    """--dphi, --tau, --emd-calibration set the EMD front end and --flo-gap describes .flo files: with DIS they
    would change nothing the run reads while its stored configuration said they had."""
    for argv, needles in ((["--dphi", "1"], ("--dphi sets the EMD front end", "use --front-end emd")),
                          (["--emd-calibration", "g.json", "--tau", "0.02"], ("--tau, --emd-calibration set",)),
                          (["--flo-gap", "0.1"], ("--flo-gap describes the .flo files of --front-end flo",))):
        code, _, err = cli(capsys, "velocity", run2, "--out", tmp_path / "v.nc", *argv, "--quiet")
        assert code == 2
        one_error(err, "velocity", *needles)
    assert entries(tmp_path) == set()


def test_the_printed_score_is_the_one_the_stored_run_gives(run2, tmp_path, capsys):
    """A short clip is scored after a quarter of its length; the file keeps that skip, so the score read from the
    file is the line the console printed."""
    from experiments.velocity import score, score_line

    out = tmp_path / "v.nc"
    code, text, err = cli(capsys, "velocity", run2, "--out", out, "--quiet")
    assert code == 0, err
    with xr.open_dataset(out) as ds:
        skip = float(ds.attrs["scored_after_s"])
        assert 0 < skip < 2.0                        # a 2 s clip: a quarter of it, not the default 2 s
        assert score_line(score(ds), skip) in text


def test_a_fixed_lag_without_the_online_filter_says_which_option_to_give(run2, tmp_path, capsys):
    code, _, err = cli(capsys, "velocity", run2, "--out", tmp_path / "v.nc", "--lag", "1", "--quiet")
    assert code == 2
    one_error(err, "velocity", "--lag 1 is a fixed-lag smoother of the online filter", "give --filter causal")


def test_a_stopped_or_failed_run_leaves_no_empty_folders_it_made(tmp_path, capsys, monkeypatch):
    """What a folder command made and left empty when stopped (a figure's cache, a suite's scenes/) goes;
    folders that hold something, and those that were there before, stay."""
    import experiments.figures as figures

    def make_cache_then(exc):
        def run(out, *a, **k):
            (Path(out) / ".cache" / "eye_runs").mkdir(parents=True)
            raise exc
        return run

    monkeypatch.setattr(figures, "run_figures", make_cache_then(KeyboardInterrupt()))
    code, _, err = cli(capsys, "figures", "--only", "eye_rmse", "--out", tmp_path / "f")
    assert code == 130 and "interrupted; nothing written" in err
    assert not (tmp_path / "f").exists()
    kept = tmp_path / "kept"
    (kept / "old-empty").mkdir(parents=True)
    time.sleep(0.1)  # made before the run
    monkeypatch.setattr(figures, "run_figures", make_cache_then(ValueError("no such world")))
    code, _, err = cli(capsys, "figures", "--only", "eye_rmse", "--out", kept)
    assert code == 2 and "no such world" in err
    assert entries(kept) == {"old-empty"}
