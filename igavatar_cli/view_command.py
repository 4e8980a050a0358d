"""`igavatar view [RUN_DIR]`: the command (registered on the app by igavatar_cli.main).

    igavatar view igavatar-run                 # http://localhost:8080, Ctrl-C stops it
    igavatar view --model run/model --motion walk --port 0
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from igavatar_cli.cli_common import RunDir, err_console, print_summary, user_errors
from igavatar_cli.help_panels import CONSOLE, INPUTS, help_panels
from stages.layout import DEFAULT_RUN_DIR


@user_errors
@help_panels({INPUTS: ("run_dir_arg", "model", "dataset", "mesh", "report", "gt", "run_dir"),
              "Poses": ("motion", "seconds"),
              "Mesh": ("mesh_resolution", "faces"),
              "Server": ("host", "port", "screenshots"),
              CONSOLE: ("json_out",)})
def view(
    run_dir_arg: Annotated[Optional[Path], typer.Argument(
        metavar="[RUN_DIR]", help="Run directory to show (same as --run-dir).")] = None,
    model: Annotated[Optional[Path], typer.Option(help="Model directory \\[default: RUN_DIR/model].")] = None,
    dataset: Annotated[Optional[Path], typer.Option(
        help="Dataset whose frames, cameras and images are shown \\[default: the one the model was trained on].")] = None,
    mesh: Annotated[Optional[Path], typer.Option(
        help="Mesh artifact of `export` (its canonical.ply and baked texture) \\[default: RUN_DIR/mesh; "
             "without one, marching cubes of the model at --mesh-resolution].")] = None,
    report: Annotated[Optional[Path], typer.Option(
        help="Eval report whose scans are shown with the avatar's distance to them \\[default: RUN_DIR/report].")] = None,
    gt: Annotated[Optional[Path], typer.Option(
        help="Folder of world-space scans <frame>.ply to show instead of the report's \\[default: none].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    motion: Annotated[Optional[str], typer.Option(
        help="Poses for the frame slider: a procedural motion (walk, turn, arm_raise, squat, turntable), a pose "
             ".npz, a capture or a dataset \\[default: the dataset's training and test frames].")] = None,
    seconds: Annotated[float, typer.Option(help="Length of a procedural --motion in seconds (30 fps).", min=0.1)] = 4.0,
    mesh_resolution: Annotated[int, typer.Option(
        help="Marching-cubes resolution when there is no exported mesh.", min=16)] = 192,
    faces: Annotated[int, typer.Option(help="Face budget of the mesh sent to the browser (0: all).", min=0)] = 60_000,
    host: Annotated[str, typer.Option(
        help="Address to listen on: 127.0.0.1 keeps it on this machine; 0.0.0.0 opens it to the network.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="Port to listen on (0: any free port); a busy port is an error.")] = 8080,
    screenshots: Annotated[Optional[Path], typer.Option(
        help="Folder where the page's 'save screenshot' button writes PNGs \\[default: RUN_DIR/screenshots].")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout when the server stops.")] = False,
) -> None:
    """Show the avatar in a browser (viser): skinned on its skeleton, a frame slider with play, the capture's
    cameras, and after eval the scans and the avatar's distance to them. Serves until Ctrl-C."""
    from igavatar_cli.progress import progress_sink
    from stages.layout import RunLayout
    from stages.view import ViewOptions, serve_view

    root = run_dir_arg or run_dir
    layout = RunLayout(root)
    options = ViewOptions(
        model=model or layout.model, dataset=dataset, mesh=mesh or layout.mesh, report=report or layout.report,
        gt=gt, motion=motion, seconds=seconds, mesh_resolution=mesh_resolution, faces=faces, host=host, port=port,
        screenshots=screenshots or layout.root / "screenshots",
    )

    def ready(server, scene) -> None:
        from igavatar.viewer.server import server_url

        err_console.print(f"[bold]viewer[/]: {server_url(server)}  [dim](Ctrl-C stops it)[/]", highlight=False)

    with progress_sink(err_console, quiet=json_out) as progress:
        summary = serve_view(options, progress, on_ready=ready)
    print_summary(summary, json_out)
