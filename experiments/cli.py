"""The ``lobula`` command line: one entry point, one subcommand per protocol.

Each subcommand's parser is built by the ``add_parser``-style function named in
:data:`COMMANDS`; only the subcommand named on the command line gets its full parser. Building
it imports nothing heavy (no torch, OpenCV, xarray or SciPy): the options of the commands whose
code needs those live in :mod:`experiments.parsers`, and a command's code is imported only when
it runs. So ``lobula --help``, ``lobula COMMAND --help`` and a refused option or value answer in
a fraction of a second. Numeric options are checked at parse time (:class:`experiments.parsers.Number`);
a refused value is argparse's one-line error naming the option and the allowed range, exit status 2.
To add a subcommand, write its parser function (which calls ``set_defaults(func=...)``) and add
one line here.
"""
from __future__ import annotations

import argparse
import importlib
import sys

#: subcommand: ("module:function" that adds its parser to a subparsers object, one-line help shown by ``lobula --help``)
COMMANDS: dict[str, tuple[str, str]] = {
    "scene": ("experiments.render:add_parser", "render a synthetic track run (footage folder with exact truth)"),
    "suite": ("experiments.suite:add_parser", "accuracy suite: scene families x seeds, all configurations, baselines"),
    "velocity": ("experiments.velocity_command:add_parser", "estimate forward velocity from footage"),
    "calibrate-emd": ("experiments.parsers:add_calibrate_parser",
                      "fit the EMD front end's per-field gains on a synthetic run"),
    "depth": ("experiments.parsers:add_depth_parser", "dense forward depth from flow and v̂ (ratio, TV, parallax)"),
    "depth-suite": ("experiments.parsers:add_depth_suite_parser",
                    "depth on the suite's families x seeds, beside baselines"),
    "ephys": ("experiments.ephys.command:add_parser",
              "virtual electrophysiology: record photoreceptor/EMD/LC/readout neurons"),
    "compare": ("experiments.parsers:add_compare_parser",
                "every front end on the same footage and readout, scored side by side"),
    "sweep": ("experiments.parsers:add_sweep_parser", "a grid over any configuration path, on Dask, into Zarr"),
    "figures": ("experiments.parsers:add_figures_parser", "regenerate the hypothesis figures with their JSON"),
    "eye-velocity": ("experiments.parsers:add_eye_velocity_parser",
                     "velocity from compound-eye footage: photoreceptors, EMDs, LC fields, readout"),
    "bench": ("experiments.bench:add_parser", "frames/s per stage and end to end, peak memory"),
    "info": ("experiments.info:add_parser",
             "what a recording holds: streams, rates, intrinsics, IMU, dropped frames, truth"),
}

#: ``lobula --help``'s description (plain text: argparse prints it as it is)
DESCRIPTION = ("Forward velocity from video and an IMU through a model of the fly's lobula\n"
               "(photoreceptors, EMDs, lobula-columnar fields, readout), and virtual\n"
               "electrophysiology of its neurons. 'lobula COMMAND --help' lists the options\n"
               "of a command.")


def _shown(action: argparse.Action) -> str:
    """An option's default as --help shows it: a flag is off; several values as they are typed."""
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
        return "off"
    d = action.default
    if isinstance(d, (list, tuple)):
        return " ".join(map(str, d))
    return str(d)


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """--help states each option's default exactly once, and keeps descriptions' line breaks.

    The default is written as "(default: …)" at the end of the option's help: by this
    formatter, from the option's default, unless the help text writes its own "(default: …)",
    which an option whose default is decided later must (None: the configuration's value, or
    one chosen from the data; argparse.SUPPRESS: an option the command must know was given).
    None is never shown as a default. A required option, a positional and --help/--version
    have none to show.
    """

    def _get_help_string(self, action):
        text = action.help or ""
        if ("(default: " in text or action.required or not action.option_strings
                or action.default in (None, argparse.SUPPRESS)):
            return text
        return f"{text} (default: {_shown(action).replace('%', '%%')})"  # help texts are %-formatted


class _Version(argparse.Action):
    """``lobula --version``: the package version and the git commit it runs from (read only when asked)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from lobula.version import __version__, git_commit

        print(f"lobula {__version__} (git commit {git_commit()})")
        parser.exit()


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the subcommand named in ``argv`` (if any) gets its full options built."""
    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if not a.startswith("-")), None)
    p = argparse.ArgumentParser(prog="lobula", description=DESCRIPTION, formatter_class=_Formatter)
    p.add_argument("--version", action=_Version, help="print the version and git commit, and exit")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (target, help_) in COMMANDS.items():
        if name == chosen:
            module, function = target.split(":")
            getattr(importlib.import_module(module), function)(sub)
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
    try:
        args = build_parser(argv).parse_args(argv)
    except SystemExit as exc:
        if exc.code == 2:  # refused: argparse has printed the usage and a one-line error naming the option
            return 2
        raise  # --help, --version: argparse's own exit
    keep_freed_blocks()  # after parsing: --help and a refused option need no allocator (nor its library look-up)
    from lobula.version import set_command_line

    set_command_line(["lobula", *argv])
    if not hasattr(args, "func"):
        build_parser([args.command]).parse_args([args.command, "--help"])
    from lobula._optional import MissingExtraError
    from stimuli.footage import FootageError

    try:
        return args.func(args)
    except (FootageError, FileExistsError, FileNotFoundError, ValueError, MissingExtraError) as exc:
        print(f"lobula {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and closed: not an error
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
