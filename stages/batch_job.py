"""One batch job: its stages run in order as the `igavatar` commands themselves, in child processes.

    result = run_job(JobPlan("a", Path("runs/a"), [("preprocess", [...argv...]), ...], threads=1), report)
    result["status"]   # "ok" or "failed"; result["error"] the failing stage's one line

Each stage is `python -m igavatar_cli.main STAGE --run-dir OUT/<job> OPTIONS...`: exactly the
command a user runs, with its defaults, checks, one-line errors and skipping of up-to-date
artifacts (so a second run of a batch does no work and a crashed one resumes). A child process
also keeps one job's torch threads (`threads`, through OMP_NUM_THREADS) from another's, and dies
with the worker that runs it (PR_SET_PDEATHSIG), so a killed worker leaves no stage running.
Training interrupted by a dead worker continues from its checkpoint (`train --resume`).

Progress comes from the commands' plain progress lines on stderr ("training: 120/800 ... eta 1 min
05 s"), parsed and handed to `report`.
"""

from __future__ import annotations

import ctypes
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

#: The artifact (run-directory entry) each stage writes.
STAGE_ARTIFACT = {"preprocess": "dataset", "train": "model", "export": "mesh", "eval": "report"}
#: The report's metrics a batch summary lists, by their metrics.json keys.
SUMMARY_METRICS = ("psnr_full_db", "psnr_mask_bbox_db", "ssim_mask_bbox", "chamfer_l1_surface_mm",
                   "normal_consistency_surface", "volumetric_iou")
_PROGRESS = re.compile(r"^(?P<task>[^:]+): (?P<done>\d+)/(?P<total>\d+)(?P<rest>.*)$")
_ETA = re.compile(r"\beta (?P<eta>.+)$")


@dataclass(frozen=True)
class JobPlan:
    """What a worker needs to run a job: name, run directory, (stage, command-line args) in order,
    and torch threads."""

    name: str
    run_dir: Path
    commands: list[tuple[str, list[str]]] = field(default_factory=list)
    threads: int = 1


def parse_progress(line: str) -> dict | None:
    """A plain progress line -> {"task", "step", "total", "eta"}; None for any other line."""
    match = _PROGRESS.match(line.strip())
    if match is None:
        return None
    eta = _ETA.search(match["rest"])
    return {"task": match["task"], "step": int(match["done"]), "total": int(match["total"]),
            "eta": eta["eta"].strip() if eta else ""}


def _die_with_parent() -> None:
    """In the child before exec: be killed when the worker that started us dies (Linux)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass  # not Linux: a killed worker's stage then runs to its end on its own


def _stage_env(threads: int) -> dict[str, str]:
    env = dict(os.environ)
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[name] = str(threads)
    env["COLUMNS"] = "1000"  # one error line stays one line
    return env


def _run_stage(argv: list[str], threads: int, on_progress: Callable[[dict], None]) -> tuple[int, str]:
    """Run one command; its exit code and its error line (or the end of its stderr)."""
    child = subprocess.Popen([sys.executable, "-m", "igavatar_cli.main", *argv], stdin=subprocess.DEVNULL,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=_stage_env(threads),
                             preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
    tail: list[str] = []
    error = ""
    assert child.stderr is not None
    for line in child.stderr:
        line = line.rstrip("\n")
        event = parse_progress(line)
        if event is not None:
            on_progress(event)
            continue
        if line.startswith("error:"):
            error = line[len("error:"):].strip()
        elif line.strip():
            tail = (tail + [line.strip()])[-3:]
    code = child.wait()
    return code, error or " ".join(tail)


def _artifact_stamp(run_dir: Path, stage: str) -> int | None:
    manifest = run_dir / STAGE_ARTIFACT[stage] / "manifest.json"
    return manifest.stat().st_mtime_ns if manifest.is_file() else None


def report_metrics(run_dir: Path) -> dict[str, float]:
    """The report's mean metrics (those in SUMMARY_METRICS that it has)."""
    path = run_dir / "report" / "metrics.json"
    if not path.is_file():
        return {}
    metrics = json.loads(path.read_text()).get("metrics", {})
    means = {key: (value.get("mean") if isinstance(value, dict) else value) for key, value in metrics.items()}
    return {key: float(means[key]) for key in SUMMARY_METRICS if isinstance(means.get(key), (int, float))}


def run_job(plan: JobPlan, report: Callable[[dict], None]) -> dict:
    """Run the plan's stages in order, stopping at the first that fails.

    `report` receives {"job", "stage", "step", "total", "eta", "status"} updates.
    Returns {"job", "status": "ok"|"failed", "error", "stages": {stage: {"seconds", "skipped"}}, "metrics"}.
    """
    result: dict = {"job": plan.name, "status": "ok", "error": "", "stages": {}, "metrics": {}}
    for stage, argv in plan.commands:
        report({"job": plan.name, "stage": stage, "step": 0, "total": 0, "eta": "", "status": "running"})
        if stage == "train" and (plan.run_dir / "model.work" / "checkpoint.npz").is_file():
            argv = [*argv, "--resume"]  # a worker died mid-training: continue from the checkpoint
        before = _artifact_stamp(plan.run_dir, stage)
        started = time.perf_counter()
        code, error = _run_stage(argv, plan.threads,
                                 lambda event: report({"job": plan.name, "stage": stage, "status": "running", **event}))
        seconds = time.perf_counter() - started
        skipped = code == 0 and before is not None and _artifact_stamp(plan.run_dir, stage) == before
        result["stages"][stage] = {"seconds": round(seconds, 2), "skipped": skipped}
        if code != 0:
            result.update(status="failed", error=f"{stage}: {error or f'exit code {code}'}")
            break
    if result["status"] == "ok" and any(stage == "eval" for stage, _ in plan.commands):
        result["metrics"] = report_metrics(plan.run_dir)
    last = next(reversed(result["stages"]), "")  # where a failed job stopped, the last stage of a finished one
    report({"job": plan.name, "stage": last, "step": 0, "total": 0, "eta": "", "status": result["status"]})
    return result
