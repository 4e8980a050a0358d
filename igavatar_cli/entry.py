"""The console script `igavatar`: the Typer app, with Ctrl-C during start-up ending quietly.

The app's module imports typer and rich before any command installs its signal handlers
(igavatar.interrupts); an interrupt in those first moments would otherwise print a traceback.
"""

from __future__ import annotations

import sys


def main() -> None:
    try:
        from igavatar_cli.main import app
    except KeyboardInterrupt:
        sys.stderr.write("interrupted while starting: nothing was written\n")
        sys.exit(130)
    app()
