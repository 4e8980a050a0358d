"""The `igavatar` command: thin Typer wrappers that call one stage each.

    igavatar synth && igavatar preprocess && igavatar validate igavatar-run/dataset

Commands only parse options, call a function in `stages/`, and print where the result is
(capture_commands: synth, preprocess; train_command; output_commands: export, animate, eval;
batch_command; view_command; demo and validate here). Library errors become one red line on stderr
and a non-zero exit code (cli_common.user_errors); no tracebacks for user mistakes. Heavy imports
(torch, anny) happen inside commands so `--help` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from igavatar import __version__
from igavatar_cli import batch_command, capture_commands, output_commands, train_command, view_command
from igavatar_cli.cli_common import JsonOut, Quiet, RunDir, err_console, out_console, print_summary, user_errors
from igavatar_cli.help_panels import CONSOLE, INPUTS, QUALITY, help_panels
from stages.layout import DEFAULT_RUN_DIR
from stages.resources import tune_host_allocator

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    help="Turn a monocular video of a person into an animatable 3D avatar (InstantGeoAvatar).",
    pretty_exceptions_enable=False,
)


def _version_callback(value: bool) -> None:
    if value:
        out_console.print(f"igavatar {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        Optional[bool], typer.Option("--version", callback=_version_callback, is_eager=True, help="Show the version and exit.")
    ] = None,
) -> None:
    """igavatar: hash-grid SDF avatars from monocular video, in minutes, on CPU or GPU."""
    # Every command that trains or renders allocates large short-lived tensors; see the docstring.
    tune_host_allocator()

@user_errors
@help_panels({INPUTS: ("run_dir",), QUALITY: ("preset", "steps", "resolution", "train_frames", "test_frames", "device", "seed"),
              CONSOLE: ("quiet", "json_out")})
def demo(
    run_dir: RunDir = DEFAULT_RUN_DIR,
    preset: Annotated[Optional[str], typer.Option(help="Training preset \\[default: paper on a GPU, else cpu].")] = None,
    steps: Annotated[Optional[int], typer.Option(help="Training steps \\[default: the preset's].")] = None,
    resolution: Annotated[int, typer.Option(help="Synthetic image size in pixels.", min=32)] = 512,
    train_frames: Annotated[int, typer.Option(help="Synthetic training frames.", min=1)] = 100,
    test_frames: Annotated[int, typer.Option(help="Synthetic test frames.", min=0)] = 30,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    seed: Annotated[int, typer.Option(help="Random seed of every stage.")] = 0,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Run every stage on the built-in synthetic subject and print one summary.

    synth -> preprocess -> train (cpu preset, or paper on a GPU) -> export -> animate (walk) -> eval.
    """
    from rich.table import Table

    from igavatar_cli.progress import progress_sink
    from stages.demo import DemoOptions, run_demo

    options = DemoOptions(run_dir=run_dir, preset=preset, steps=steps, resolution=resolution,
                          train_frames=train_frames, test_frames=test_frames, device=device, seed=seed)
    with progress_sink(err_console, quiet=quiet or json_out) as progress:
        summary = run_demo(options, progress=progress)
    if json_out:
        print_summary(summary, True)
        return
    table = Table(title=f"igavatar demo ({summary['preset']} preset) in {summary['run_dir']}")
    table.add_column("stage")
    table.add_column("seconds", justify="right")
    table.add_column("result")
    for name, result in summary["stages"].items():
        seconds = str(result.get("stage_seconds", "-"))
        details = ", ".join(f"{k}={v}" for k, v in result.items() if k != "stage_seconds")
        table.add_row(name, seconds, details)
    out_console.print(table)


@user_errors
@help_panels({CONSOLE: ("json_out",)})
def validate(
    path: Annotated[Path, typer.Argument(help="An artifact directory (or a capture v1 directory).")],
    json_out: JsonOut = False,
) -> None:
    """Check an artifact against its JSON schema and the sha256 of every file it lists."""
    from stages.validate import validate_path

    summary = validate_path(path)
    print_summary(
        {"valid": str(summary.path), "kind": summary.kind, "schema_version": summary.schema_version,
         "files_checked": summary.files_checked},
        json_out,
    )


# The commands live in one module per group; registering them here keeps their order in --help.
app.command()(capture_commands.synth)
app.command()(capture_commands.preprocess)
app.command()(train_command.train)
app.command()(output_commands.export)
app.command()(output_commands.animate)
app.command(name="eval")(output_commands.eval_)
app.command()(demo)
app.command()(validate)
app.command()(batch_command.batch)
app.command()(view_command.view)


if __name__ == "__main__":
    app()
