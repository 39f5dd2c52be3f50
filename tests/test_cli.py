"""The command line: every subcommand's --help states each option's default once and truthfully,
bad values are refused at parse time with the option and its range named, --version, and parsing
imports nothing heavy."""
import argparse
import re
import subprocess
import sys
from pathlib import Path

import pytest

from experiments.cli import COMMANDS, build_parser, main
from experiments.parsers import Number


def _subparser(command: str) -> argparse.ArgumentParser:
    parser = build_parser([command])
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]


def _option_help(command: str) -> dict[str, str]:
    """Each option's help line as --help prints it (whitespace collapsed), by its first flag."""
    sub = _subparser(command)
    fmt = sub._get_formatter()
    return {a.option_strings[0]: " ".join(fmt._expand_help(a).split()) for a in sub._actions
            if a.option_strings and a.help not in (None, argparse.SUPPRESS)}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_option_states_its_default_exactly_once(command):
    """One "(default: …)" per option, never "None", no second default in other words; none on a required one."""
    sub = _subparser(command)
    helps = _option_help(command)
    for action in sub._actions:
        if not action.option_strings or action.dest == "help":
            continue
        flag = action.option_strings[0]
        assert action.help, f"lobula {command} {flag}: no help text (its default would not show)"
        text = helps[flag]
        words = re.findall(r"\bdefaults?\b", text, flags=re.IGNORECASE)
        if action.required:
            assert not words, f"lobula {command} {flag}: a required option shows a default: {text}"
            continue
        assert text.count("(default: ") == 1 and len(words) == 1, f"lobula {command} {flag}: {text}"
        assert "(default: None" not in text and "(default: [" not in text, f"lobula {command} {flag}: {text}"
    page = sub.format_help()
    assert "None" not in page and "not given" not in page


def test_flags_show_off_and_lists_show_as_typed():
    helps = _option_help("velocity")
    assert helps["--quiet"].endswith("(default: off)") and helps["--paper"].endswith("(default: off)")
    assert helps["--flo-size"].endswith("(default: 640 448)")
    assert helps["--front-end"].endswith("(default: dis)")
    assert helps["--mean-removal"].endswith("(default: space)") and helps["--epipole"].endswith(
        "(default: estimate; principal with --paper or --front-end emd)")


def test_help_defaults_written_in_the_text_are_the_codes():
    """Defaults the help writes itself (the option's own is None: the configuration decides) are the
    configuration's values, and the literal copies in experiments.parsers match their sources."""
    from dataclasses import fields

    import experiments.compare as compare
    import experiments.depth_stream as depth_stream
    import experiments.figures as figures
    import experiments.parsers as parsers
    from lobula.config import VelocityConfig
    from lobula.photoreceptor import MEAN_REMOVAL
    from lobula.readout_neuron import SPIKE_MODELS

    cfg, paper, emd = VelocityConfig(), VelocityConfig.paper(), VelocityConfig(front_end="emd")
    helps = _option_help("velocity")
    stated = {"--gap": cfg.flow.gap, "--dis-preset": cfg.flow.dis_preset, "--dis-grid-px": cfg.flow.dis_grid_px,
              "--dphi": cfg.emd.lattice.dphi_deg, "--emd-gaze": cfg.emd.gaze, "--lag": cfg.readout.lag_s,
              "--accel-scale-error": cfg.readout.accel_scale_error, "--field-size": cfg.fields.size_deg,
              "--tau": cfg.emd.emd.tau_s, "--epipole": cfg.epipole, "--filter": cfg.readout.filter,
              "--saccade-gate": cfg.saccade_gate_deg_s, "--heading-reset": cfg.heading_reset_deg,
              "--heading-walk": cfg.heading_walk}
    for flag, value in stated.items():
        shown = helps[flag].split("(default: ")[1].split(")")[0].split(",")[0].split(";")[0].split(" ")[0]
        assert shown == str(value) or (isinstance(value, (int, float)) and float(shown) == value), (flag, shown)
    assert cfg.emd.lattice.drho_deg is None and "(default: Δφ)" in helps["--drho"]
    assert paper.epipole == emd.epipole == "principal"
    assert cfg.emd.surround == MEAN_REMOVAL["space"][0]          # the camera's EMD columns: space
    assert parsers.MEAN_REMOVAL == tuple(sorted(MEAN_REMOVAL)) and parsers.SPIKE_MODELS == tuple(sorted(SPIKE_MODELS))
    assert (parsers.LOCK_TOL_M_S, parsers.LOCK_HOLD_S) == (compare.LOCK_TOL_M_S, compare.LOCK_HOLD_S)
    assert parsers.DEPTH_METHODS == depth_stream.METHODS and parsers.FOOTAGE_GAMMA == depth_stream.FOOTAGE_GAMMA
    run0 = depth_stream.DepthRunConfig()
    assert parsers.DEPTH_RUN_DEFAULTS == {k: getattr(run0, k) for k in parsers.DEPTH_RUN_DEFAULTS}
    assert {f.name for f in fields(run0)} >= set(parsers.DEPTH_RUN_DEFAULTS)
    assert (parsers.FIGURES, parsers.EXTRA_FIGURES) == (figures.FIGURES, figures.EXTRA_FIGURES)
    assert _subparser("compare").get_default("front_ends") == ",".join(compare.DEFAULT_FRONT_ENDS)


def test_top_level_help_is_plain_text_and_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "`" not in text and ":mod:" not in text and ":func:" not in text
    assert max(len(line) for line in text.splitlines()) <= 100   # wrapped, not one long paragraph
    for command, (_, help_) in COMMANDS.items():
        assert command in text


def test_version_names_the_package_version_and_the_commit(capsys):
    from lobula.version import __version__, git_commit

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out == f"lobula {__version__} (git commit {git_commit()})\n"


_LIGHT = """
import sys
from experiments.cli import COMMANDS, build_parser, main

for command in COMMANDS:
    build_parser([command]).format_help()
    try:
        main([command, "--help"])
    except SystemExit as exc:
        assert exc.code == 0, (command, exc.code)
assert main(["velocity", "x", "--out", "y.nc", "--frnt-end", "dis"]) == 2       # a mistyped option
assert main(["scene", "out", "--duration", "-1"]) == 2                        # a bad value
heavy = sorted(m for m in ("torch", "cv2", "xarray", "scipy", "pandas", "matplotlib", "dask", "zarr", "h5py")
               if m in sys.modules)
print(",".join(heavy) or "none")
"""


def test_parsing_imports_nothing_heavy():
    """Every subcommand's parser and --help, a mistyped option and a refused value: no torch, OpenCV,
    xarray, SciPy, pandas or matplotlib imported (they take seconds to load on a busy machine)."""
    res = subprocess.run([sys.executable, "-c", _LIGHT], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "none"
    assert "unrecognized arguments: --frnt-end dis" in res.stderr
    assert "argument --duration: must be a number > 0, got '-1'" in res.stderr


def test_parsed_arguments_pickle_with_their_command():
    """depth-suite hands its arguments to worker processes: the lazily imported command pickles."""
    import pickle

    args = build_parser(["depth-suite"]).parse_args(["depth-suite", "--out", "x"])
    again = pickle.loads(pickle.dumps(args))
    assert again == args and again.func.target == "experiments.depth_suite:run_depth_suite"


@pytest.mark.parametrize("spec, good, bad", [
    (Number(0, above=True), ["1e-9", "3"], ["0", "-1", "nan", "inf", "-inf", "x", ""]),
    (Number(0), ["0", "2.5"], ["-1e-9", "nan", "inf"]),
    (Number(0, 1), ["0", "1", "0.5"], ["-0.1", "1.01", "nan"]),
    (Number(0, 1, below=True), ["0", "0.99"], ["1"]),
    (Number(0, above=True, inf=True), ["inf", "0.2"], ["0", "-inf", "nan"]),
    (Number(1, integer=True), ["1", "12"], ["0", "-3", "1.5", "x"]),
    (Number(), ["-5", "0", "7"], ["nan", "inf"]),
])
def test_number_accepts_its_range_and_refuses_the_rest(spec, good, bad):
    for text in good:
        assert spec(text) == (int(text) if spec.integer else float(text))
    for text in bad:
        with pytest.raises(argparse.ArgumentTypeError, match=re.escape(f"must be {spec}, got {text!r}")):
            spec(text)


#: (command line, the option named, the range the message states); each refused before anything runs
_REFUSED = [
    (["scene", "OUT", "--duration", "-1"], "--duration", "a number > 0"),
    (["scene", "OUT", "--duration", "0"], "--duration", "a number > 0"),
    (["scene", "OUT", "--scale", "0"], "--scale", "a number in (0, 4]"),
    (["scene", "OUT", "--peak-speed", "-2"], "--peak-speed", "a number > 0"),
    (["scene", "OUT", "--speed-scale", "0"], "--speed-scale", "a number > 0"),
    (["scene", "OUT", "--start", "-1"], "--start", "a number ≥ 0"),
    (["scene", "OUT", "--seed", "-1"], "--seed", "a whole number ≥ 0"),
    (["scene", "OUT", "--rotation", "-3"], "--rotation", "a number ≥ 0"),
    (["scene", "OUT", "--rotation3", "1", "-1", "0"], "--rotation3", "a number ≥ 0"),
    (["scene", "OUT", "--rotation3-band", "0", "1"], "--rotation3-band", "a number > 0"),
    (["scene", "OUT", "--noise", "-1"], "--noise", "a number ≥ 0"),
    (["scene", "OUT", "--brightness", "0"], "--brightness", "a number > 0"),
    (["scene", "OUT", "--contrast", "-0.5"], "--contrast", "a number ≥ 0"),
    (["scene", "OUT", "--sky", "1.5"], "--sky", "a number in [0, 1]"),
    (["scene", "OUT", "--exposure", "-0.01"], "--exposure", "a number ≥ 0"),
    (["scene", "OUT", "--panels", "0"], "--panels", "a whole number ≥ 1"),
    (["scene", "OUT", "--off-axis-yaw", "nan"], "--off-axis-yaw", "a finite number"),
    (["scene", "OUT", "--dphi", "0.1"], "--dphi", "a number in [0.5, 30]"),
    (["scene", "OUT", "--rate-hz", "10"], "--rate-hz", "a number in [20, 5000]"),
    (["scene", "OUT", "--rays", "7"], "--rays", "a whole number in [0, 6]"),
    (["scene", "OUT", "--gaze-gain", "1.2"], "--gaze-gain", "a number in [0, 1]"),
    (["scene", "OUT", "--gaze-return", "0"], "--gaze-return", "a number > 0"),
    (["suite", "--out", "S", "--duration", "0"], "--duration", "a number > 0"),
    (["suite", "--out", "S", "--workers", "0"], "--workers", "a whole number ≥ 1"),
    (["suite", "--out", "S", "--seeds", "0"], "--seeds", "a positive count N"),
    (["velocity", "F", "--out", "o.nc", "--gap", "0"], "--gap", "a whole number ≥ 1"),
    (["velocity", "F", "--out", "o.nc", "--field-size", "-5"], "--field-size", "a number > 0"),
    (["velocity", "F", "--out", "o.nc", "--lag", "-1"], "--lag", "a number ≥ 0 (lobula.readout.ReadoutConfig.lag_s)"),
    (["velocity", "F", "--out", "o.nc", "--accel-scale-error", "1"], "--accel-scale-error", "a number in [0, 1)"),
    (["velocity", "F", "--out", "o.nc", "--dis-grid-px", "-1"], "--dis-grid-px", "a whole number ≥ 0"),
    (["velocity", "F", "--out", "o.nc", "--dphi", "60"], "--dphi", "a number in (0, 60)"),
    (["velocity", "F", "--out", "o.nc", "--tau", "0"], "--tau", "a number in [0.001, 1]"),
    (["velocity", "F", "--out", "o.nc", "--flo-gap", "0"], "--flo-gap", "a number > 0"),
    (["velocity", "F", "--out", "o.nc", "--flo-size", "640", "0"], "--flo-size", "a whole number ≥ 1"),
    (["velocity", "F", "--out", "o.nc", "--skip", "-2"], "--skip", "a number ≥ 0"),
    (["velocity", "F", "--out", "o.nc", "--saccade-gate", "0"], "--saccade-gate", "a number > 0 or none"),
    (["velocity", "F", "--out", "o.nc", "--heading-reset", "off"], "--heading-reset", "a number > 0 or none"),
    (["velocity", "F", "--out", "o.nc", "--membrane-noise", "-1"], "--membrane-noise", "a number ≥ 0"),
    (["velocity", "F", "--out", "o.nc", "--haltere-gain", "2"], "--haltere-gain", "(0, 1.5]"),
    (["eye-velocity", "F", "--out", "o.nc", "--tau", "-0.01"], "--tau", "a number in [0.001, 1]"),
    (["eye-velocity", "F", "--out", "o.nc", "--tau", "1e9"], "--tau", "a number in [0.001, 1] (s, lobula.emd"),
    (["eye-velocity", "F", "--out", "o.nc", "--field-size", "1e9"], "--field-size", "a number in [2, 120]"),
    (["eye-velocity", "F", "--out", "o.nc", "--haltere-gain", "strong"], "--haltere-gain", "'natural' or a number"),
    (["compare", "F", "--out", "o.nc", "--tol", "0"], "--tol", "a number > 0"),
    (["compare", "F", "--out", "o.nc", "--tau", "1e9"], "--tau", "a number in [0.001, 1]"),
    (["compare", "F", "--out", "o.nc", "--hold", "-1"], "--hold", "a number ≥ 0"),
    (["compare", "F", "--out", "o.nc", "--gap", "0"], "--gap", "a whole number ≥ 1"),
    (["sweep", "--base-duration", "0"], "--base-duration", "a number > 0"),
    (["sweep", "--workers", "0"], "--workers", "a whole number ≥ 1"),
    (["depth", "F", "--out", "o.nc", "--every", "0"], "--every", "a whole number ≥ 1"),
    (["depth", "F", "--out", "o.nc", "--max-scale-rel-std", "0"], "--max-scale-rel-std", "a number > 0 or inf"),
    (["depth", "F", "--out", "o.nc", "--average-frames", "-1"], "--average-frames", "a whole number ≥ 0"),
    (["depth", "F", "--out", "o.nc", "--max-range", "0"], "--max-range", "a number > 0"),
    (["depth", "F", "--out", "o.nc", "--gamma", "-1"], "--gamma", "a number ≥ 0"),
    (["depth-suite", "--out", "D", "--seeds", "1,x"], "--seeds", "a comma-separated list of seeds"),
    (["depth-suite", "--out", "D", "--scale", "0"], "--scale", "a number in (0, 4]"),
    (["ephys", "looming", "--out", "x.nc", "--trials", "0"], "--trials", "a whole number in [1, 10000]"),
    (["ephys", "looming", "--out", "x.nc", "--tau", "2"], "--tau", "a number in [0.001, 1]"),
    (["ephys", "tf-tuning", "--out", "x.nc", "--contrast", "0.5", "1.5"], "--contrast", "a number in (0, 1]"),
    (["ephys", "tf-tuning", "--out", "x.nc", "--tf", "0"], "--tf", "a number in (0, 500)"),
    (["ephys", "rf-map", "--out", "x.nc", "--directions", "2"], "--directions", "a whole number ≥ 3"),
    (["ephys", "looming", "--out", "x.nc", "--max-size", "181"], "--max-size", "a number in (0, 180]"),
    (["ephys", "looming", "--out", "x.nc", "--duration", "-1"], "--duration", "a number > 0"),
    (["figures", "--duration", "0"], "--duration", "a number > 0"),
    (["bench", "--frames", "0"], "--frames", "a whole number ≥ 1"),
    (["bench", "--scales", "1", "-0.5"], "--scales", "a number > 0"),
]


@pytest.mark.parametrize("argv, option, allowed", _REFUSED, ids=[" ".join(a[0][:1] + [a[1]]) for a in _REFUSED])
def test_a_bad_value_is_refused_at_parse_time_naming_the_option_and_its_range(argv, option, allowed, tmp_path,
                                                                              capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"lobula {argv[0]}: error: argument {option}")   # argparse's own one-line error
    assert allowed in err[-1].split(": must be ", 1)[1], err[-1]
    assert ", got '" in err[-1], err[-1]                                       # the refused value, quoted
    assert not list(tmp_path.iterdir())                                        # nothing ran, nothing written


def test_values_at_the_edge_of_their_range_parse():
    args = build_parser(["scene"]).parse_args(["scene", "OUT", "--duration", "0.1", "--sky", "0", "--rays", "0",
                                                "--gaze-gain", "1", "--start", "0", "--off-axis-yaw", "-7"])
    assert (args.duration, args.sky, args.rays, args.gaze_gain, args.off_axis_yaw) == (0.1, 0.0, 0, 1.0, -7.0)
    args = build_parser(["depth"]).parse_args(["depth", "F", "--out", "o.nc", "--max-scale-rel-std", "inf"])
    assert args.max_scale_rel_std == float("inf")
    args = build_parser(["velocity"]).parse_args(["velocity", "F", "--out", "o.nc", "--haltere-gain", "1.5"])
    assert args.haltere_gain == "1.5"
    for tau in ("0.001", "1"):  # an EMD delay's range, both ends allowed
        args = build_parser(["eye-velocity"]).parse_args(["eye-velocity", "F", "--out", "o.nc", "--tau", tau])
        assert args.tau == float(tau)


def test_scene_refuses_eye_options_without_the_fly_eye(tmp_path, capsys):
    from experiments.cli import main

    out = tmp_path / "run"
    assert main(["scene", str(out), "--duration", "0.2", "--scale", "0.1", "--dphi", "4", "--cast-rate-hz", "250",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--dphi, --cast-rate-hz apply only to compound-eye footage" in err and not out.exists()


def test_a_required_option_shows_no_default():
    parser = build_parser(["depth-suite"])
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["depth-suite"]
    text = sub.format_help()
    body = text[text.index("options:"):]
    out = body[body.index("--out OUT"):body.index("--families")]
    assert "output folder" in out and "default" not in out.lower(), out


def test_depth_suite_takes_the_suites_seed_list_and_refuses_a_bad_one(tmp_path, capsys):
    """`--seeds` means the same on `lobula suite` and `lobula depth-suite`: a count or a list."""
    from experiments.suite import parse_seeds

    for command in ("suite", "depth-suite"):
        args = build_parser([command]).parse_args([command, "--out", "x", "--seeds", "100,101"])
        assert parse_seeds(args.seeds) == [100, 101]
    out = tmp_path / "ds"
    assert main(["depth-suite", "--out", str(out), "--seeds", "1,x"]) == 2
    assert "argument --seeds: must be a positive count N (seeds 0..N-1) or a comma-separated list" in \
        capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("device, message", [("tpu", "is not a torch device"), ("cuda", "sees no CUDA device")])
def test_bench_refuses_a_device_it_cannot_use(device, message, capsys):
    """`lobula bench --device` names the device's problem instead of timing the CPU under a GPU's name."""
    import torch

    from experiments.cli import main

    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    assert main(["bench", "--device", device]) == 2
    assert message in capsys.readouterr().err


def test_bench_device_agreement_is_exact_on_the_same_device():
    """The CPU-vs-device check compares like with like: on the CPU against itself it reads zero."""
    from experiments.bench import agreement_on_device

    assert agreement_on_device("cpu", duration_s=0.02) == {"circuit_max_rel": 0.0, "tv_depth_median_rel": 0.0}


_FAULTS = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from experiments.cli import keep_freed_blocks
    assert keep_freed_blocks()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):  # a frame pair's maps (2.4 MB each, a 640x480 flow component): held together, then freed
    maps = [np.ones(600_000, np.float32) for _ in range(6)]
    del maps
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def test_the_command_line_keeps_freed_blocks_for_the_next_frame_pair():
    # glibc returns freed blocks of megabytes to the system and faults fresh pages in for the
    # next ones; `lobula` (experiments.cli.main) sets its allocator to keep them.
    import platform
    import subprocess
    import sys

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        pytest.skip("mallopt is glibc's; elsewhere keep_freed_blocks changes nothing")
    thp = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    if thp.exists() and "[always]" in thp.read_text():
        pytest.skip("transparent huge pages always on: a fresh block faults a few 2 MB pages, not 4 kB ones")
    faults = {mode: int(subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True,
                                       check=True).stdout) for mode in ("default", "keep")}
    assert faults["default"] > 20 * 6 * 586 // 2     # most pairs fault their 586-page maps in again
    assert faults["keep"] < faults["default"] / 5


def _velocity_run(duration_s=1.5, dt=1 / 30, front_end="dis"):
    """A velocity Dataset as `lobula velocity` stores it, with known errors: v̂ = truth + 0.01 m/s
    where observable, v_std 0.02 m/s (1σ), the last fifth unobservable."""
    import numpy as np
    import xarray as xr

    t = np.arange(0.1, 0.1 + duration_s, dt)
    v_true = 0.3 * np.sin(2 * np.pi * t / 1.2)                 # goes backwards half the time
    obs = np.arange(t.size) < int(0.8 * t.size)
    ds = xr.Dataset(dict(v_hat=("time", np.where(obs, v_true + 0.01, np.nan)), observable=("time", obs),
                         v_std=("time", np.full(t.size, 0.02)), v_true=("time", v_true),
                         accel=("time", np.gradient(v_true, t), {"source": "accelerometer (gravity and bias removed)"})),
                    coords=dict(time=t))
    ds.attrs.update(front_end=front_end, readout="kalman", filter="zero-phase")
    return ds


def test_velocity_figure_draws_truth_estimate_and_two_sigma_with_plain_labels():
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib.collections import PolyCollection

    from experiments.velocity import score, score_line, scoring_skip, velocity_figure

    ds = _velocity_run(duration_s=1.5)                          # shorter than the 2 s default skip
    fig = velocity_figure(ds)
    ax, ax2 = fig.axes[:2]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert {"truth", "v̂ estimate", "±2σ (2 × v_std)"} <= set(labels)
    assert not any("(dis" in s or "kalman" in s for s in labels)    # the run is named in the caption, in words
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    assert lines["truth"].get_zorder() > lines["v̂ estimate"].get_zorder()  # truth is not hidden under v̂
    band = next(c for c in ax.collections if isinstance(c, PolyCollection) and c.get_label().startswith("±2σ"))
    ys = np.concatenate([p.vertices[:, 1] for p in band.get_paths()])
    v, s = ds.v_hat.values, ds.v_std.values
    assert ys.max() == pytest.approx(np.nanmax(v + 2 * s)) and ys.min() == pytest.approx(np.nanmin(v - 2 * s))
    # A line at 0 and the axis says what below it means; units on every axis; `a` explained.
    assert any(np.allclose(np.asarray(ln.get_ydata(), float), 0) for ln in ax.get_lines())
    assert "(m/s)" in ax.get_ylabel() and "backwards" in ax.get_ylabel()
    assert ax2.get_xlabel() == "time (s)" and "m/s²" in ax2.get_ylabel()
    assert "forward acceleration" in ax2.get_title(loc="left") and "IMU" in ax2.get_title(loc="left")
    # The title's numbers are the console's, computed from the stored run, after the same skip.
    title = fig._suptitle.get_text()
    skip = scoring_skip(ds)
    assert skip == pytest.approx(0.25 * float(ds.time[-1] - ds.time[0]))
    sc = score(ds, skip)
    assert sc["rmse_m_s"] == pytest.approx(0.01) and sc["observable_fraction"] < 1
    assert score_line(sc, skip) in title and "nan" not in title.lower()
    assert "RMSE 0.0100 m/s" in title and f"observable {100 * sc['observable_fraction']:.1f} %" in title
    assert "dense optical flow" in title and "zero-phase" in title and "Kalman" in title
    plt.close(fig)


def test_velocity_command_prints_the_numbers_its_figure_titles(tmp_path, monkeypatch, capsys):
    import xarray as xr

    import experiments.store as store
    from experiments.cli import main
    from experiments.velocity import score, score_line, scoring_skip
    from stimuli.track import TrackRunConfig, make_track_run

    footage = make_track_run(tmp_path / "clip", TrackRunConfig(profile=None, start_s=5.0, duration_s=1.5, scale=0.25),
                             progress=False)
    titles = []
    save = store.save_figure
    monkeypatch.setattr(store, "save_figure",
                        lambda fig, path, **kw: (titles.append(fig._suptitle.get_text()), save(fig, path, **kw))[1])
    out, png = tmp_path / "run.nc", tmp_path / "run.png"
    assert main(["velocity", str(footage), "--out", str(out), "--plot", str(png), "--quiet"]) == 0
    printed = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("scored after")]
    assert len(printed) == 1 and len(titles) == 1 and png.stat().st_size > 10_000
    assert printed[0] in titles[0] and "nan" not in printed[0]
    with xr.open_dataset(out) as ds:                           # the stored run gives the same line
        assert score_line(score(ds, scoring_skip(ds)), scoring_skip(ds)) == printed[0]
        config = ds.attrs["config"]
    from PIL import Image
    with Image.open(png) as im:                                # the figure carries the run's configuration
        assert im.info["config"] == config and im.info["command_line"].startswith("lobula velocity ")


def test_saccade_gate_and_heading_reset_reach_the_configuration():
    """--saccade-gate, --heading-reset and --heading-walk set VelocityConfig's fields (none, 0: off); absent, the
    defaults stay; on the EMD front end, which holds its gaze rather than reading flow, they are refused."""
    from experiments.velocity import apply_velocity_options
    from lobula.config import VelocityConfig

    parse = lambda *extra: build_parser(["velocity"]).parse_args(["velocity", "F", "--out", "o.nc", *extra])  # noqa: E731
    cfg = apply_velocity_options(VelocityConfig(), parse("--saccade-gate", "none", "--heading-reset", "20"))
    assert cfg.saccade_gate_deg_s is None and cfg.heading_reset_deg == 20.0
    cfg = apply_velocity_options(VelocityConfig(), parse("--saccade-gate", "500"))
    assert cfg.saccade_gate_deg_s == 500.0 and cfg.heading_reset_deg == VelocityConfig().heading_reset_deg
    cfg = apply_velocity_options(VelocityConfig(), parse())
    assert (cfg.saccade_gate_deg_s, cfg.heading_reset_deg) == (150.0, 15.0)
    with pytest.raises(ValueError, match="--heading-reset .* holds its gaze"):
        apply_velocity_options(VelocityConfig(front_end="emd"), parse("--heading-reset", "10"))
    assert apply_velocity_options(VelocityConfig(), parse("--heading-walk", "0.15")).heading_walk == 0.15
    assert apply_velocity_options(VelocityConfig(), parse()).heading_walk == 0.0
    with pytest.raises(ValueError, match="--heading-walk .* holds its gaze"):
        apply_velocity_options(VelocityConfig(front_end="emd"), parse("--heading-walk", "0.3"))
    with pytest.raises(ValueError, match="heading_walk must be"):
        VelocityConfig(heading_walk=-0.1)
