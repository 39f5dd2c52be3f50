"""Where an output came from: the package version, the git commit and the command line.

Every file the project writes records these (with its full configuration), so a result can
be traced to the code and the command that made it.
"""
from __future__ import annotations

import functools
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

__version__ = "0.1.0"


@functools.lru_cache(maxsize=1)
def git_commit() -> str:
    """The commit of the source tree this package runs from, ``+dirty`` if it has uncommitted
    changes to tracked files, or ``"unknown"`` outside a git checkout (an installed wheel)."""
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{head}+dirty" if dirty else head


_invocation: list[str] | None = None


def set_command_line(argv: list[str]) -> None:
    """Record the command being run, ``argv`` (the ``lobula`` entry point calls this with its arguments, so a
    command run in-process from a notebook is recorded as the command, not as the notebook)."""
    global _invocation
    _invocation = list(argv)


def command_line(argv: list[str] | None = None) -> str:
    """The command that is running, shell-quoted (``lobula velocity …`` for the console script): ``argv``,
    else the one recorded by :func:`set_command_line`, else ``sys.argv``."""
    argv = list(argv if argv is not None else _invocation if _invocation is not None else sys.argv)
    if argv and Path(argv[0]).name in ("lobula", "cli.py", "__main__.py"):
        argv[0] = "lobula"
    return " ".join(shlex.quote(a) for a in argv)


def provenance_attrs() -> dict:
    """Version, commit, command line and creation time (UTC, ISO 8601) as flat string attributes."""
    return {"lobula_version": __version__, "git_commit": git_commit(), "command_line": command_line(),
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def provenance(config_json: str, **extra) -> dict:
    """Attributes every output carries: the full configuration (``config_json``, JSON), the package version, the git
    commit (or "unknown"), the command line and the creation time; ``extra`` adds more (non-strings as JSON)."""
    import json

    attrs = {**provenance_attrs(), "config": config_json}
    attrs.update({k: (v if isinstance(v, (str, int, float)) else json.dumps(v, default=str))
                  for k, v in extra.items()})
    return attrs
