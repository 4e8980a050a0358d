"""`igavatar batch`: many pipelines at once on Ray, on this machine or a cluster.

    results = run_batch(plans, BatchOptions(out=Path("runs"), cpus_per_job=1), on_update=draw_table)
    write_summary(Path("runs"), results)        # runs/summary.csv and runs/summary.md

One Ray task per job (stages.batch_job.run_job), asking Ray for `cpus_per_job` CPUs and
`gpus_per_job` GPUs (a fraction packs several small jobs on one GPU); Ray runs as many at once as
the machine or cluster has room for. A task whose worker dies is run again up to `max_retries`
times (Ray's own retry of system failures); a job that fails by itself (a bad capture) is not
retried and does not stop the others. A small actor collects the jobs' progress for the live
table. Without an address a local Ray is started on this machine (loopback only) and stopped
at the end; `auto`, `ray://host:10001` or RAY_ADDRESS join a running cluster, where every node
needs the same igavatar and the spec's paths on storage every node sees.
"""

from __future__ import annotations

import csv
import io
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from igavatar.artifacts.atomic import atomic_write_bytes
from igavatar.errors import InputError
from stages.batch_job import SUMMARY_METRICS, JobPlan, run_job


@dataclass(frozen=True)
class BatchOptions:
    """How jobs are scheduled (see `igavatar batch --help`)."""

    out: Path
    address: str | None = None
    cpus_per_job: float = 1.0
    gpus_per_job: float = 0.0
    max_retries: int = 2
    local_cpus: int | None = None
    """CPUs of a local Ray started here (default: this machine's)."""


def _import_ray():
    try:
        import ray
    except ImportError:
        raise InputError("igavatar batch runs on Ray, which is not installed: pip install 'igavatar[batch]'") from None
    return ray


def _token_mode_for_joining(options: BatchOptions) -> None:
    """`ray start` (2.5x+) turns token authentication on and keeps the token in ~/.ray/auth_token,
    but a driver sends it only in token mode, which Ray reads at import: without this, joining a
    head by its address fails. Before `import ray`; a RAY_AUTH_MODE of the user's is kept."""
    if not (options.address or os.environ.get("RAY_ADDRESS")) or "RAY_AUTH_MODE" in os.environ:
        return
    token_file = Path(os.environ.get("RAY_AUTH_TOKEN_PATH", Path.home() / ".ray" / "auth_token"))
    if os.environ.get("RAY_AUTH_TOKEN") or token_file.is_file():
        os.environ["RAY_AUTH_MODE"] = "token"


def _start_ray(ray, options: BatchOptions) -> None:
    """Join the cluster at --address or RAY_ADDRESS, or start a local Ray (loopback only)."""
    address = options.address or os.environ.get("RAY_ADDRESS")
    common = dict(include_dashboard=False, log_to_driver=False, logging_level="ERROR",
                  runtime_env={"env_vars": {"PYTHONWARNINGS": "ignore"}})
    if address:
        try:
            ray.init(address=address, **common)
        except (ConnectionError, RuntimeError, ValueError) as error:
            raise InputError(f"--address {address}: cannot join a Ray cluster there: {str(error).splitlines()[0]}") from None
        return
    os.environ.pop("RAY_ADDRESS", None)  # an empty one would otherwise reach ray.init
    ray.init(num_cpus=options.local_cpus or os.cpu_count(), _node_ip_address="127.0.0.1", **common)


def _board_class(ray):
    @ray.remote(num_cpus=0)
    class Board:
        """The latest progress of every job ({job: {stage, step, total, eta, status, attempt}})."""

        def __init__(self) -> None:
            self.rows: dict[str, dict] = {}

        def update(self, event: dict) -> None:
            row = self.rows.setdefault(event["job"], {"attempt": 0})
            if event.get("status") == "started":
                row["attempt"] += 1
            row.update({k: v for k, v in event.items() if k != "job"})

        def snapshot(self) -> dict[str, dict]:
            return {job: dict(row) for job, row in self.rows.items()}

    return Board


def _job_task(plan: JobPlan, board) -> dict:
    """A Ray task: run one job, reporting progress to the board (never raising for a failed job)."""
    board.update.remote({"job": plan.name, "status": "started"})
    return run_job(plan, lambda event: board.update.remote(event))


def _failed(plan: JobPlan, error: str) -> dict:
    return {"job": plan.name, "status": "failed", "error": error, "stages": {}, "metrics": {}}


def run_batch(plans: list[JobPlan], options: BatchOptions,
              on_update: Callable[[dict[str, dict]], None] | None = None) -> list[dict]:
    """Run every plan as a Ray task; the results in the plans' order (see stages.batch_job.run_job).

    `on_update` gets the board's snapshot about twice a second (for the live table).
    """
    _token_mode_for_joining(options)
    ray = _import_ray()
    _start_ray(ray, options)
    try:
        board = _board_class(ray).remote()
        task = ray.remote(_job_task).options(num_cpus=options.cpus_per_job, num_gpus=options.gpus_per_job,
                                             max_retries=options.max_retries, retry_exceptions=False)
        pending = {task.remote(plan, board): plan for plan in plans}
        results: dict[str, dict] = {}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
            for ref in done:
                plan = pending.pop(ref)
                try:
                    results[plan.name] = ray.get(ref)
                except ray.exceptions.RayError as error:  # the worker died more than max_retries times
                    results[plan.name] = _failed(plan, f"worker lost {options.max_retries + 1} times: "
                                                       f"{type(error).__name__}")
            if on_update is not None:
                on_update(ray.get(board.snapshot.remote()))
        final = ray.get(board.snapshot.remote())
        return [{**results[plan.name], "attempts": final.get(plan.name, {}).get("attempt", 1)} for plan in plans]
    finally:
        ray.shutdown()  # stops a Ray started here; only disconnects from a cluster


SUMMARY_COLUMNS = ("job", "status", "attempts", "error", "preprocess_s", "train_s", "export_s", "eval_s", "skipped", *SUMMARY_METRICS)


def summary_rows(results: list[dict]) -> list[dict]:
    """One flat row per job: status, error, each stage's seconds, skipped stages and the metrics."""
    rows = []
    for result in results:
        row = {"job": result["job"], "status": result["status"], "attempts": result.get("attempts", 1),
               "error": result["error"],
               "skipped": ",".join(s for s, v in result["stages"].items() if v["skipped"])}
        for stage in ("preprocess", "train", "export", "eval"):
            row[f"{stage}_s"] = result["stages"].get(stage, {}).get("seconds", "")
        row.update({key: round(result["metrics"][key], 4) if key in result["metrics"] else "" for key in SUMMARY_METRICS})
        rows.append(row)
    return rows


def write_summary(out: Path, results: list[dict], command: str) -> tuple[Path, Path]:
    """OUT/summary.csv and OUT/summary.md (each written whole, then renamed into place)."""
    rows = summary_rows(results)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=SUMMARY_COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    failed = sum(r["status"] != "ok" for r in rows)
    lines = ["# Batch summary", "", f"Command: `{command}`; {time.strftime('%Y-%m-%d %H:%M:%S')}; "
             f"{len(rows) - failed} of {len(rows)} jobs ok.", "",
             "| " + " | ".join(SUMMARY_COLUMNS) + " |", "|" + "---|" * len(SUMMARY_COLUMNS)]
    lines += ["| " + " | ".join(str(row[c]).replace("|", "/") for c in SUMMARY_COLUMNS) + " |" for row in rows]
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "summary.csv", buffer.getvalue().encode())
    atomic_write_bytes(out / "summary.md", ("\n".join(lines) + "\n").encode())
    return out / "summary.csv", out / "summary.md"
