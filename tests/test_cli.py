"""The command line: every subcommand's --help works and states each option's default once."""
import argparse
import re
from pathlib import Path

import pytest

from experiments.cli import COMMANDS, _Formatter, build_parser


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_option_states_its_default_exactly_once(command):
    parser = build_parser([command])
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    fmt = _Formatter(command)
    for action in sub._actions:
        if (not action.option_strings or action.required or action.default is argparse.SUPPRESS
                or action.help in (None, argparse.SUPPRESS) or action.dest == "help"):
            continue
        text = fmt._get_help_string(action) % {"default": action.default, "prog": command, "dest": action.dest,
                                                 "choices": action.choices, "type": action.type}
        n = len(re.findall(r"default", text, flags=re.IGNORECASE))
        assert n >= 1, f"lobula {command} {action.option_strings[0]}: help does not state its default"
        assert n == 1 or "(default:" not in text, f"lobula {command} {action.option_strings[0]}: default twice: {text}"


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
    from experiments.cli import main

    out = tmp_path / "ds"
    assert main(["depth-suite", "--out", str(out), "--seeds", "1,x"]) == 2
    assert "--seeds must be a positive count or a comma-separated list" in capsys.readouterr().err
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
