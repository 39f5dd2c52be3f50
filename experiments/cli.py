"""The ``lobula`` command line: one entry point, one subcommand per protocol.

Each subcommand's options live beside the code that runs it, in an ``add_parser(subparsers)``
function of the module named in :data:`COMMANDS`. That module is imported only when its
subcommand runs, so ``lobula --help`` starts in a fraction of a second (no torch, no xarray).
To add a subcommand, write ``add_parser`` (which calls ``set_defaults(func=...)``) in its
module and add one line here.
"""
from __future__ import annotations

import argparse
import importlib
import sys

#: subcommand: (module with ``add_parser``, one-line help shown by ``lobula --help``)
COMMANDS: dict[str, tuple[str, str]] = {
    "scene": ("experiments.render", "render a synthetic track run (footage folder with exact truth)"),
    "suite": ("experiments.suite", "accuracy suite: scene families x seeds, all configurations, baselines"),
    "velocity": ("experiments.velocity_command", "estimate forward velocity from footage"),
    "calibrate-emd": ("experiments.calibrate", "fit the EMD front end's per-field gains on a synthetic run"),
    "depth": ("experiments.depth", "dense forward depth from flow and v̂ (ratio, TV, parallax)"),
    "depth-suite": ("experiments.depth_suite", "depth on the suite's families x seeds, beside baselines"),
    "ephys": ("experiments.ephys", "virtual electrophysiology: record photoreceptor/EMD/LC/readout neurons"),
    "compare": ("experiments.compare", "every front end on the same footage and readout, scored side by side"),
    "sweep": ("experiments.sweep", "a grid over any configuration path, on Dask, into Zarr"),
    "figures": ("experiments.figures", "regenerate the hypothesis figures with their JSON"),
    "eye-velocity": ("experiments.eye_velocity", "velocity from compound-eye footage: photoreceptors, EMDs, LC fields, readout"),
    "bench": ("experiments.bench", "frames/s per stage and end to end, peak memory"),
    "info": ("experiments.info", "what a recording holds: streams, rates, intrinsics, IMU, dropped frames, truth"),
}


class _Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help shows every option's default and keeps descriptions' line breaks.

    An option whose help already explains its default (e.g. "default: colour, else
    infrared" for a None that means something) is not given a second, literal one, and
    a required option has none to show.
    """

    def _get_help_string(self, action):
        text = action.help or ""
        if "default" in text.lower() or getattr(action, "required", False):
            return text
        return super()._get_help_string(action)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the subcommand named in ``argv`` (if any) gets its full options built."""
    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if not a.startswith("-")), None)
    p = argparse.ArgumentParser(prog="lobula", description=__doc__.split("\n\n")[0], formatter_class=_Formatter)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_) in COMMANDS.items():
        if name == chosen:
            importlib.import_module(module).add_parser(sub)
        else:
            sub.add_parser(name, help=help_)
    for action in sub.choices.values():
        action.formatter_class = _Formatter
    return p


#: glibc's mallopt parameters (malloc.h) and the values set: blocks up to 64 MiB come from the heap,
#: and up to 256 MiB of freed heap is kept for the next frame pair rather than handed back.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_TRIM_BYTES, _MMAP_BYTES = 256 << 20, 64 << 20


def keep_freed_blocks() -> bool:
    """Let glibc's allocator reuse the per-frame maps' memory instead of returning it to the system.

    Each 640×480 frame pair makes and frees megabyte maps (flow, derotated flow, pooled maps). By
    default glibc serves blocks above an adaptive threshold with fresh pages and unmaps them when
    freed, so every pair faults its pages in again: in a turning 640×480 run, 0.1-0.5 million page
    faults and 1-2 ms per pair in the flow composition alone, in some runs and not others. With the
    thresholds fixed the same run faults 20,000-25,000 times whatever the run. Process-wide, so only the
    command line sets it; returns False where the C library is not glibc (nothing is changed).
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_BYTES) and mallopt(_M_TRIM_THRESHOLD, _TRIM_BYTES))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    keep_freed_blocks()
    args = build_parser(argv).parse_args(argv)
    from lobula.version import set_command_line

    set_command_line(["lobula", *argv])
    if not hasattr(args, "func"):
        build_parser([args.command]).parse_args([args.command, "--help"])
    from stimuli.footage import FootageError

    try:
        return args.func(args)
    except (FootageError, FileExistsError, FileNotFoundError, ValueError) as exc:
        print(f"lobula {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and closed: not an error
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
