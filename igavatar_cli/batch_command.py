"""`igavatar batch SPEC`: the command (registered on the app by igavatar_cli.main), its live table.

    igavatar batch batch.json --stages preprocess,train --cpus-per-job 2
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.live import Live
from rich.table import Table

from igavatar_cli.cli_common import JsonOut, err_console, print_summary, user_errors
from igavatar_cli.help_panels import CONSOLE, INPUTS, help_panels


def _table(rows: dict[str, dict], names: list[str]) -> Table:
    table = Table(title="igavatar batch")
    for column in ("job", "stage", "step", "eta", "status", "attempt"):
        table.add_column(column)
    for name in names:
        row = rows.get(name, {})
        step = f"{row['step']}/{row['total']}" if row.get("total") else ""
        table.add_row(name, row.get("stage", ""), step, row.get("eta", ""), row.get("status", "queued"),
                      str(row.get("attempt", "")))
    return table


class _LineLog:
    """Without a terminal: one line when a job's stage or status changes."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.seen: dict[str, tuple] = {}

    def __call__(self, rows: dict[str, dict]) -> None:
        for name, row in rows.items():
            key = (row.get("stage"), row.get("status"), row.get("attempt"))
            if self.seen.get(name) != key:
                self.seen[name] = key
                self.console.print(f"{name}: {row.get('stage') or '-'} {row.get('status', '')} (attempt "
                                   f"{row.get('attempt', 1)})", markup=False, highlight=False, soft_wrap=True)



@user_errors
@help_panels({INPUTS: ("stages", "dry_run"), "Scheduling on Ray": ("address", "cpus_per_job", "gpus_per_job", "max_retries", "local_cpus"),
              CONSOLE: ("json_out",)})
def batch(
    ctx: typer.Context,
    spec: Annotated[Path, typer.Argument(help="Spec file (JSON, or YAML with PyYAML): out, defaults per stage, jobs, "
                                              "optional grid; see the README's Batch section.")],
    stages: Annotated[Optional[str], typer.Option(
        help="Stages to run, in order \\[default: the spec's \"stages\", else preprocess,train,export,eval].")] = None,
    address: Annotated[Optional[str], typer.Option(
        help="Ray cluster to join: auto, host:port or ray://host:10001 \\[default: RAY_ADDRESS, else a local Ray "
             "on this machine's cores, loopback only].")] = None,
    cpus_per_job: Annotated[float, typer.Option(
        help="CPUs Ray gives each job; also its torch threads (rounded up). Two jobs that each take every core "
             "slow each other far more than 2x.", min=0.1)] = 1.0,
    gpus_per_job: Annotated[float, typer.Option(
        help="GPUs per job; a fraction (0.25) packs several small jobs on one GPU; 0 runs CPU jobs.",
        min=0.0)] = 0.0,
    max_retries: Annotated[int, typer.Option(help="Times a job whose worker died is run again.", min=0)] = 2,
    local_cpus: Annotated[Optional[int], typer.Option(
        help="CPUs of the local Ray started without --address \\[default: all of this machine's].", min=1)] = None,
    dry_run: Annotated[bool, typer.Option(help="Check the spec and print each job's commands; run nothing.")] = False,
    json_out: JsonOut = False,
) -> None:
    """Run many pipelines at once on Ray (one task per job): OUT/<job>/ run directories, OUT/summary.csv|.md."""
    import math

    from igavatar_cli.batch_plans import job_plans, known_options
    from stages.batch import BatchOptions, run_batch, write_summary
    from stages.batch_spec import STAGES, parse_stages, read_spec

    group = ctx.find_root().command  # the igavatar group: every command's options, for the spec's check
    parsed = read_spec(spec, known_options(group))
    chosen = parse_stages(stages) if stages else (parsed.stages or STAGES)
    plans = job_plans(group, parsed, chosen, threads=max(1, math.ceil(cpus_per_job)))
    if dry_run:
        print_summary({plan.name: [" ".join(["igavatar", *map(shlex.quote, args)]) for _, args in plan.commands]
                       for plan in plans}, json_out)
        return
    options = BatchOptions(out=parsed.out, address=address, cpus_per_job=cpus_per_job, gpus_per_job=gpus_per_job,
                           max_retries=max_retries, local_cpus=local_cpus)
    names = [plan.name for plan in plans]
    if err_console.is_terminal and not json_out:
        with Live(_table({}, names), console=err_console, refresh_per_second=4) as live:
            results = run_batch(plans, options, on_update=lambda rows: live.update(_table(rows, names)))
    else:
        results = run_batch(plans, options, on_update=None if json_out else _LineLog(err_console))
    command = " ".join(["igavatar", "batch", *map(shlex.quote, sys.argv[2:])])
    csv_path, md_path = write_summary(parsed.out, results, command)
    failed = [r for r in results if r["status"] != "ok"]
    print_summary({"jobs": len(results), "ok": len(results) - len(failed), "failed": len(failed),
                   **{f"failed {r['job']}": r["error"] for r in failed},
                   "summary": str(md_path), "csv": str(csv_path)}, json_out)
    if failed:
        raise typer.Exit(1)
