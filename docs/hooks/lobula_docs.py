"""MkDocs hooks for the lobula site: the CLI reference from the parsers, and the figures.

* ``cli.md`` holds the marker ``<!-- lobula-cli -->``; at build time it becomes ``lobula --help``
  and ``lobula COMMAND --help`` for every subcommand in :data:`experiments.cli.COMMANDS`, taken
  from the parsers themselves (standard library only: nothing heavy is imported), so the
  reference cannot drift from the code.
* The PNGs of the repository's ``figures/`` folder are served under ``figures/`` of the site,
  so the results pages show the committed figures without copies in ``docs/``.
"""
from __future__ import annotations

import io
import os
import sys
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

from mkdocs.structure.files import File

MARKER = "<!-- lobula-cli -->"
#: help text width (characters): wide enough for the option lists, narrow enough for the page
WIDTH = 100


def _root(config) -> Path:
    return Path(config["config_file_path"]).resolve().parent


@contextmanager
def _help_environment():
    """argparse wraps at $COLUMNS; fix it (and no colour) so the page is the same on every machine."""
    saved = {k: os.environ.get(k) for k in ("COLUMNS", "NO_COLOR")}
    os.environ["COLUMNS"], os.environ["NO_COLOR"] = str(WIDTH + 2), "1"
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def cli_reference(root: Path) -> str:
    """Markdown: the top-level help, then one section per subcommand with its full --help."""
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    from experiments.cli import COMMANDS

    parts = []
    with _help_environment():
        parts.append(f"## lobula\n\n```text\n{_help([])}\n```\n")
        for name, (_, summary) in COMMANDS.items():
            parts.append(f"## lobula {name}\n\n{summary[:1].upper() + summary[1:]}.\n\n"
                         f"```text\n{_help([name])}\n```\n")
    return "\n".join(parts)


def _help(argv: list[str]) -> str:
    """What ``lobula *argv --help`` prints, from the same parser the command line builds."""
    from experiments.cli import build_parser

    out = io.StringIO()
    with redirect_stdout(out):
        try:
            build_parser(argv).parse_args([*argv, "--help"])
        except SystemExit:  # argparse exits after printing the help
            pass
    text = out.getvalue().rstrip()
    if not text:
        raise RuntimeError(f"lobula {' '.join(argv)} --help printed nothing")
    return text


def on_page_markdown(markdown, page, config, files):
    if MARKER in markdown:
        return markdown.replace(MARKER, cli_reference(_root(config)))
    return markdown


def on_files(files, config):
    figures = _root(config) / "figures"
    for png in sorted(figures.glob("*.png")):
        files.append(File.generated(config, f"figures/{png.name}", abs_src_path=str(png)))
    return files
