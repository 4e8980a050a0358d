"""What every command shares: the consoles, the common options, the user-error wrapper, the summary printer.

Library errors become one red line on stderr and a non-zero exit code; no tracebacks for user mistakes.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from igavatar.artifacts.storage import storage_message
from igavatar.errors import IgavatarError, ResourceLimitError, StorageError, Terminated
from igavatar.interrupts import signals_as_interrupts

err_console = Console(stderr=True)
out_console = Console()

RunDir = Annotated[Path, typer.Option("--run-dir", help="Run directory holding every artifact by default.")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars; print only the result.")]
JsonOut = Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")]


def error_line(message: str) -> None:
    # markup=False for the message: paths and shapes may contain [brackets].
    err_console.print("[bold red]error:[/] ", end="", highlight=False)
    err_console.print(message, markup=False, highlight=False, soft_wrap=True)


def user_errors(func: Callable) -> Callable:
    """Turn library errors, Ctrl-C, SIGTERM and fixable disk/memory failures into one line and an exit code."""

    @wraps(func)
    def wrapper(*args, **kwargs):
        try:
            with signals_as_interrupts():
                return func(*args, **kwargs)
        except IgavatarError as exc:
            error_line(str(exc))
            raise typer.Exit(exc.exit_code) from None
        except Terminated:
            err_console.print("[yellow]terminated[/] (SIGTERM): nothing half-written was kept; earlier artifacts are untouched")
            raise typer.Exit(143) from None
        except KeyboardInterrupt:
            err_console.print("[yellow]interrupted[/]: nothing half-written was kept; earlier artifacts are untouched")
            raise typer.Exit(130) from None
        except OSError as exc:
            # A safety net: stages translate these themselves; one that slipped through is still the
            # user's disk, not a bug, when it is one of the fixable kinds.
            message = storage_message(exc, Path.cwd())
            if message is None:
                raise
            error_line(message)
            raise typer.Exit(StorageError.exit_code) from None
        except MemoryError:
            error_line("out of memory; lower the sizes you chose (--resolution, --rays, --samples, image sizes) "
                        "or free memory, then run the command again")
            raise typer.Exit(ResourceLimitError.exit_code) from None

    return wrapper


def print_summary(summary: dict, as_json: bool) -> None:
    if as_json:
        typer.echo(json.dumps(summary, indent=2, default=str))
        return
    for key, value in summary.items():
        out_console.print(f"[bold]{key}[/]: {value}", highlight=False, soft_wrap=True)


def run_stage(stage: Callable[..., dict], options, quiet: bool, json_out: bool) -> dict:
    """Run `stage(options, progress=...)` under the console's progress bars (none when --quiet or
    --json) and print its summary; returns the summary."""
    from igavatar_cli.progress import progress_sink

    with progress_sink(err_console, quiet=quiet or json_out) as progress:
        summary = stage(options, progress=progress)
    print_summary(summary, json_out)
    return summary
