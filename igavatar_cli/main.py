"""The `igavatar` command: thin Typer wrappers that call one stage each.

    igavatar synth && igavatar preprocess && igavatar validate igavatar-run/dataset

Commands only parse options, call a function in `stages/`, and print where the result is.
Library errors become one red line on stderr and a non-zero exit code; no tracebacks for
user mistakes. Heavy imports (torch, anny) happen inside commands so `--help` stays fast.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console

from igavatar import __version__
from igavatar.errors import IgavatarError, NotAvailableError
from stages.layout import DEFAULT_RUN_DIR, RunLayout

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    help="Turn a monocular video of a person into an animatable 3D avatar (InstantGeoAvatar).",
    pretty_exceptions_enable=False,
)
err_console = Console(stderr=True)
out_console = Console()

RunDir = Annotated[Path, typer.Option("--run-dir", help="Run directory holding every artifact by default.")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars; print only the result.")]
JsonOut = Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")]


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


def user_errors(func: Callable) -> Callable:
    """Turn library errors and Ctrl-C into one line and an exit code (never a traceback)."""

    @wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except IgavatarError as exc:
            err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
            raise typer.Exit(exc.exit_code) from None
        except KeyboardInterrupt:
            err_console.print("[yellow]interrupted[/]: nothing half-written was kept; earlier artifacts are untouched")
            raise typer.Exit(130) from None

    return wrapper


def _print_summary(summary: dict, as_json: bool) -> None:
    if as_json:
        typer.echo(json.dumps(summary, indent=2, default=str))
        return
    for key, value in summary.items():
        out_console.print(f"[bold]{key}[/]: {value}", highlight=False, soft_wrap=True)


def _not_available(stage: str, issue_hint: str) -> None:
    raise NotAvailableError(f"`igavatar {stage}` is not available yet in igavatar {__version__} ({issue_hint})")


@app.command()
@user_errors
def synth(
    out: Annotated[Optional[Path], typer.Option(help="Capture directory to write [default: RUN_DIR/capture].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    resolution: Annotated[int, typer.Option(help="Image height and width in pixels.", min=32, max=4096)] = 512,
    train_frames: Annotated[int, typer.Option(help="Frames of the 360-degree turn in A-pose (training split).", min=1)] = 100,
    test_frames: Annotated[int, typer.Option(help="Frames of novel poses (walk, arm raise, squat; test split).", min=0)] = 30,
    phenotype: Annotated[
        Optional[list[str]], typer.Option(help="Anny phenotype value, repeatable: --phenotype gender=0.2 --phenotype weight=0.7.")
    ] = None,
    garment: Annotated[str, typer.Option(help="Garment variant: shirt-trousers, dress, tight.")] = "shirt-trousers",
    texture: Annotated[str, typer.Option(help="Texture variant: stripes, checker, plain.")] = "stripes",
    seed: Annotated[int, typer.Option(help="Random seed (motion jitter, colours).")] = 0,
    anny_cache: Annotated[Optional[Path], typer.Option(help="Anny body-model cache directory [default: ~/.cache/anny].")] = None,
    force: Annotated[bool, typer.Option(help="Redo even if an identical capture exists.")] = False,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Make a synthetic monocular capture (capture v1) of a clothed, textured Anny subject."""
    from igavatar_cli.progress import RichProgress
    from stages.synth import SynthOptions, run_synth

    options = SynthOptions(
        out=out or RunLayout(run_dir).capture, resolution=resolution, train_frames=train_frames,
        test_frames=test_frames, phenotype=tuple(phenotype or ()), garment=garment, texture=texture,
        seed=seed, anny_cache=anny_cache, force=force,
    )
    with RichProgress(err_console, quiet=quiet or json_out) as progress:
        summary = run_synth(options, progress=progress)
    _print_summary(summary, json_out)


@app.command()
@user_errors
def preprocess(
    capture: Annotated[Optional[Path], typer.Option(help="Capture directory [default: RUN_DIR/capture].")] = None,
    out: Annotated[Optional[Path], typer.Option(help="Dataset directory to write [default: RUN_DIR/dataset].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    input_format: Annotated[str, typer.Option("--format", help="Input layout: auto or capture-v1.")] = "auto",
    max_size: Annotated[int, typer.Option(help="Resize images so the longer side is at most this many pixels.", min=16)] = 512,
    grid_resolution: Annotated[
        str, typer.Option(help="Skinning-weight grid D,H,W (z,y,x) in canonical space.")
    ] = "64,16,64",
    anny_cache: Annotated[Optional[Path], typer.Option(help="Anny body-model cache directory [default: ~/.cache/anny].")] = None,
    force: Annotated[bool, typer.Option(help="Redo even if the inputs and options are unchanged.")] = False,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Turn a capture (images, masks, cameras, body poses) into a dataset artifact that `train` reads."""
    from igavatar_cli.progress import RichProgress
    from stages.preprocess import PreprocessOptions, parse_grid_resolution, run_preprocess

    layout = RunLayout(run_dir)
    options = PreprocessOptions(
        capture=capture or layout.capture, out=out or layout.dataset, input_format=input_format,
        max_size=max_size, grid_resolution=parse_grid_resolution(grid_resolution), anny_cache=anny_cache, force=force,
    )
    with RichProgress(err_console, quiet=quiet or json_out) as progress:
        summary = run_preprocess(options, progress=progress)
    _print_summary(summary, json_out)


@app.command()
@user_errors
def train(
    dataset: Annotated[Optional[Path], typer.Option(help="Dataset directory [default: RUN_DIR/dataset].")] = None,
    out: Annotated[Optional[Path], typer.Option(help="Model directory to write [default: RUN_DIR/model].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    preset: Annotated[str, typer.Option(help="paper (GPU, the paper's settings), cpu (~10 min on 2 cores) or tiny (tests).")] = "cpu",
    steps: Annotated[Optional[int], typer.Option(help="Optimisation steps [default: the preset's].")] = None,
    rays: Annotated[Optional[int], typer.Option("--rays", help="Rays per step [default: the preset's].")] = None,
    samples: Annotated[Optional[int], typer.Option("--samples", help="Samples per ray before empty-space skipping.")] = None,
    regularizer: Annotated[
        Optional[str], typer.Option(help="smooth (the paper), none, fd-eikonal, curvature, fd-eikonal+curvature or hybrid-pe.")
    ] = None,
    smooth_weight: Annotated[Optional[float], typer.Option(help="Weight of L_smooth (paper: 1.0; 0.5-1.5 works).")] = None,
    seed: Annotated[int, typer.Option(help="Random seed (runs are deterministic on CPU).")] = 0,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    resume: Annotated[bool, typer.Option(help="Continue from the last checkpoint of an interrupted run.")] = False,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Train the hash-grid SDF avatar on a dataset artifact and write a model artifact."""
    from igavatar_cli.progress import RichProgress
    from stages.train import TrainOptions, run_train

    layout = RunLayout(run_dir)
    options = TrainOptions(
        dataset=dataset or layout.dataset, out=out or layout.model, preset=preset, steps=steps, rays_per_step=rays,
        samples_per_ray=samples, regularizer=regularizer, smooth_weight=smooth_weight, seed=seed, device=device,
        resume=resume,
    )
    with RichProgress(err_console, quiet=quiet or json_out) as progress:
        summary = run_train(options, progress=progress)
    _print_summary(summary, json_out)


@app.command()
@user_errors
def export(run_dir: RunDir = DEFAULT_RUN_DIR) -> None:
    """Extract canonical or posed meshes (marching cubes, pymeshlab cleanup, --pose). Not available yet."""
    _not_available("export", "it needs a trained model")


@app.command()
@user_errors
def animate(run_dir: RunDir = DEFAULT_RUN_DIR) -> None:
    """Render the avatar driven by new poses. Not available yet."""
    _not_available("animate", "it needs a trained model")


@app.command(name="eval")
@user_errors
def eval_(run_dir: RunDir = DEFAULT_RUN_DIR) -> None:
    """Compare posed avatar meshes and renders with ground truth (--gt scans/). Not available yet."""
    _not_available("eval", "it needs a trained model")


@app.command()
@user_errors
def demo(
    run_dir: RunDir = DEFAULT_RUN_DIR,
    preset: Annotated[Optional[str], typer.Option(help="Training preset [default: paper on a GPU, else cpu].")] = None,
    steps: Annotated[Optional[int], typer.Option(help="Training steps [default: the preset's].")] = None,
    resolution: Annotated[int, typer.Option(help="Synthetic image size in pixels.", min=32)] = 512,
    train_frames: Annotated[int, typer.Option(help="Synthetic training frames.", min=1)] = 100,
    test_frames: Annotated[int, typer.Option(help="Synthetic test frames.", min=0)] = 30,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    seed: Annotated[int, typer.Option(help="Random seed of every stage.")] = 0,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Run every available stage on the built-in synthetic subject and print one summary.

    Stages still missing in this version (export, animate, eval) are listed as not available.
    """
    from rich.table import Table

    from igavatar_cli.progress import RichProgress
    from stages.demo import DemoOptions, run_demo

    options = DemoOptions(run_dir=run_dir, preset=preset, steps=steps, resolution=resolution,
                          train_frames=train_frames, test_frames=test_frames, device=device, seed=seed)
    with RichProgress(err_console, quiet=quiet or json_out) as progress:
        summary = run_demo(options, progress=progress)
    if json_out:
        _print_summary(summary, True)
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


@app.command()
@user_errors
def validate(
    path: Annotated[Path, typer.Argument(help="An artifact directory (or a capture v1 directory).")],
    json_out: JsonOut = False,
) -> None:
    """Check an artifact against its JSON schema and the sha256 of every file it lists."""
    from stages.validate import validate_path

    summary = validate_path(path)
    _print_summary(
        {"valid": str(summary.path), "kind": summary.kind, "schema_version": summary.schema_version,
         "files_checked": summary.files_checked},
        json_out,
    )


if __name__ == "__main__":
    app()
