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

A command that fails says so in one line, "lobula COMMAND: error: …", naming the file and the fix,
exit status 2: bad input, and an output it cannot write. Every output the command line names is
checked for writability before the run starts; a full disk met while writing names the output,
not its temporary (:class:`experiments.store.OutputError`); a command in :data:`ALL_OR_NOTHING`
leaves all of its outputs or none. SIGINT and SIGTERM unwind the run (temporaries removed) and
end it with one line, "lobula COMMAND: interrupted; …", exit status 130 or 143.
"""
from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
import time
import warnings
from contextlib import contextmanager, nullcontext

#: subcommand: ("module:function" that adds its parser to a subparsers object, one-line help shown by ``lobula --help``)
COMMANDS: dict[str, tuple[str, str]] = {
    "scene": ("experiments.render:add_parser", "render a synthetic track run (footage folder with exact truth)"),
    "suite": ("experiments.suite:add_parser", "accuracy suite: scene families x seeds, all configurations, baselines"),
    "velocity": ("experiments.velocity_command:add_parser", "estimate forward velocity from footage"),
    "calibrate-camera": ("experiments.parsers:add_calibrate_camera_parser",
                         "measure a footage's focal length from its gyro against the image's rotation"),
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


class _Parser(argparse.ArgumentParser):
    """argparse's parser, refusing an option in one line that names it and where the options are told."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (options: {self.prog} --help)\n")


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the subcommand named in ``argv`` (if any) gets its full options built."""
    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if not a.startswith("-")), None)
    p = _Parser(prog="lobula", description=DESCRIPTION, formatter_class=_Formatter)
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


#: commands whose --out (or positional OUT) is a folder they fill; every other output option names a file
FOLDER_OUTPUTS = frozenset({"scene", "suite", "depth-suite", "figures"})
#: the options (argparse dests) that name what a command writes
OUTPUT_OPTIONS = ("out", "plot", "csv", "tum")
#: commands whose few outputs appear together when the run ends, or none of them
#: (experiments.store.all_or_nothing); the others keep what they finish, to resume from it
ALL_OR_NOTHING = frozenset({"velocity", "eye-velocity", "compare", "depth", "ephys", "calibrate-emd", "calibrate-camera"})


def _outputs(args) -> list[tuple[str, str]]:
    """(option, path) of every output the parsed command line names."""
    found = []
    for dest in OUTPUT_OPTIONS:
        value = getattr(args, dest, None)
        for v in (value if isinstance(value, (list, tuple)) else [value]):
            if isinstance(v, str) and v:
                found.append((f"--{dest}" if dest != "out" or args.command != "scene" else "OUT", v))
    return found


class _Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM, raised in the main thread so that every ``with``/``finally`` on the way out
    (temporaries, worker threads) runs; ``signum`` says which."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _on_signal(signum, frame):
    # A second signal while the first one unwinds ends the process at once: the user asked twice.
    for s in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(s) is _on_signal:
            signal.signal(s, _exit_now)
    raise _Interrupted(signum)


def _exit_now(signum, frame):
    os._exit(128 + signum)


@contextmanager
def _signals_unwind():
    """SIGINT and SIGTERM raise :class:`_Interrupted` while the block runs (main thread only), so the
    run's context managers remove what it had begun; the previous handlers come back afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    # A signal the caller ignores (a background job's SIGINT, nohup) stays ignored.
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM) if signal.getsignal(s) != signal.SIG_IGN}
    for s in before:
        signal.signal(s, _on_signal)
    try:
        yield
    finally:
        for s, h in before.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


@contextmanager
def _one_line_warnings(command: str):
    """A warning while the command runs is one line, "lobula COMMAND: warning: …", not Python's two (the file and
    the source line that warned); the previous way of showing them comes back afterwards."""
    before = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"lobula {command}: warning: {message}", file=sys.stderr if file is None else file)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = before


def _fix_for(exc, outputs: list[tuple[str, str]]) -> str:
    """An OutputError's one line, its fix naming the option that chose the output where one did."""
    from pathlib import Path

    option = next((o for o, v in outputs if Path(v) == Path(exc.filename or "")), None)
    if option is None:
        return str(exc)
    fix = exc.fix.replace("choose another place for it", f"choose another {option}")
    return f"{exc.problem}; {fix}"


def _not_kept(command: str, group: list) -> str:
    """What a failed all-or-nothing run had finished and removed again, for the end of its error line."""
    if not group:
        return ""
    names = ", ".join(str(path) for _, path in group)
    return f" ({names} not kept: lobula {command} writes its outputs together or not at all)"


#: the figure formats --plot writes (ephys writes a PNG and a PDF beside it, named by either)
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
PLOT_SUFFIXES_OF = {"ephys": (".png", ".pdf")}
#: the one format a command's --out file is written in, where its name must say so
OUT_SUFFIXES_OF = {"velocity": (".nc", "NetCDF"), "eye-velocity": (".nc", "NetCDF"), "compare": (".nc", "NetCDF"),
                   "calibrate-camera": (".json", "a camera.json"), "calibrate-emd": (".json", "JSON")}


def _either(suffixes) -> str:
    return f"{', '.join(suffixes[:-1])} or {suffixes[-1]}" if len(suffixes) > 1 else suffixes[0]


def _output_clash(outputs: list[tuple[str, str]], command: str | None = None) -> str | None:
    """Why the outputs a command line names cannot all be written (two options naming one file, a figure
    in a format not drawn, an ``--out`` whose name says another format than it gets), or None."""
    from pathlib import Path

    seen: dict[Path, str] = {}
    plots = PLOT_SUFFIXES_OF.get(command, PLOT_SUFFIXES)
    suffix, what = OUT_SUFFIXES_OF.get(command, (None, None))
    for option, path in outputs:
        key = Path(os.path.abspath(path))
        if key in seen:
            return f"{seen[key]} and {option} both name {path}: give each its own file"
        seen[key] = option
        if option == "--plot" and Path(path).suffix.lower() not in plots:
            return f"--plot {path}: use a {_either(plots)} file"
        if option == "--out" and suffix and Path(path).suffix.lower() != suffix:
            return f"--out {path}: lobula {command} writes {what}; give a name ending in {suffix}"
    return None


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # SIGINT and SIGTERM unwind from the first moment (imports, parsing, the output checks included).
    try:
        with _signals_unwind():
            return _main(argv)
    except (KeyboardInterrupt, ImportError) as exc:
        # An interrupt that lands inside a module's import comes out as that import's ImportError.
        if not isinstance(exc, KeyboardInterrupt) and not isinstance(exc.__context__, KeyboardInterrupt):
            raise
        signum = getattr(exc if isinstance(exc, KeyboardInterrupt) else exc.__context__, "signum", signal.SIGINT)
        command = next((a for a in argv if not a.startswith("-")), None)
        print(f"lobula{' ' + command if command else ''}: interrupted; nothing written", file=sys.stderr)
        return 128 + signum


def _main(argv: list[str]) -> int:
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
    from lobula.readers.core import FootageError

    from . import store

    outputs = _outputs(args)
    clash = _output_clash(outputs, args.command)
    if clash is not None:
        print(f"lobula {args.command}: error: {clash}", file=sys.stderr)
        return 2
    folders = args.command in FOLDER_OUTPUTS
    for option, path in outputs:  # before the run: a run is never lost to a folder it cannot write
        problem = store.writable_problem(path, folder=folders and option in ("--out", "OUT"))
        if problem is not None:
            print(f"lobula {args.command}: error: {_fix_for(problem, outputs)}", file=sys.stderr)
            return 2
    written, group = len(store.WRITTEN), []
    # the output folders, and whether this run makes them: what a failed or stopped run made there and left
    # empty is removed (a figure's cache, a suite's scenes/)
    roots = {path: not os.path.exists(path) for option, path in outputs if folders and option in ("--out", "OUT")}
    started, finished = time.time() - 0.02, False  # the kernel stamps files from a clock a jiffy coarse
    try:
        with _one_line_warnings(args.command), \
                store.all_or_nothing() if args.command in ALL_OR_NOTHING else nullcontext([]) as group:
            rc = args.func(args)
        finished = True
        return rc
    except (FootageError, FileExistsError, FileNotFoundError, ValueError, MissingExtraError) as exc:
        print(f"lobula {args.command}: error: {exc}{_not_kept(args.command, group)}", file=sys.stderr)
        return 2
    except store.OutputError as exc:  # a full disk, a read-only folder: the output is named, nothing half-written
        print(f"lobula {args.command}: error: {_fix_for(exc, outputs)}{_not_kept(args.command, group)}",
              file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and closed: not an error
        sys.stderr.close()
        return 0
    except OSError as exc:  # a writer outside experiments.store that met a full disk or a read-only folder
        err = store.output_error(exc, store.output_of(exc.filename)) if exc.filename else exc
        if not isinstance(err, store.OutputError):
            raise
        print(f"lobula {args.command}: error: {_fix_for(err, outputs)}{_not_kept(args.command, group)}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # SIGINT or SIGTERM: temporaries are removed on the way here
        signum = getattr(exc, "signum", signal.SIGINT)
        kept = len(store.WRITTEN) - written
        what = "nothing written" if kept <= 0 else f"{kept} finished output(s) kept, nothing half-written"
        print(f"lobula {args.command}: interrupted; {what}", file=sys.stderr)
        return 128 + signum
    finally:
        if not finished:
            store.remove_empty_folders(roots, started)


if __name__ == "__main__":
    sys.exit(main())
