"""What every results file records about where its numbers come from: the commit and the command.

    from provenance import commit, command
    results = {"commit": commit(), "command": command(), ...}
"""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def commit() -> str:
    """The short hash of HEAD, with "+uncommitted" when tracked files differ from it."""
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                           text=True).stdout.strip()
    return (head or "unknown") + ("+uncommitted" if dirty else "")


def command() -> str:
    """The command line that is running, as one could paste it."""
    return " ".join(["python", *(shlex.quote(a) for a in sys.argv)])
