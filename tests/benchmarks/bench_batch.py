"""`igavatar batch` against the same jobs run one after another, on this machine.

    python tests/benchmarks/bench_batch.py --run-dir RUN                       # 4 tiny jobs
    python tests/benchmarks/bench_batch.py --run-dir RUN --case demo-seeds --write-results

Cases:
- `tiny`: 4 jobs (the tiny preset on a 64 px synthetic subject, every stage);
- `demo-seeds`: the demo subject (synth defaults but for --resolution/--frames below) at the `cpu`
  preset with --steps S, seeds 0, 1, 2, every stage.
In sequence: each job's commands one after another, each command with torch's default threads
(what a shell loop gets). Batch: `igavatar batch SPEC --cpus-per-job C` on a local Ray. Both start
from empty run directories; the captures are made once beforehand and not timed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
from provenance import command, commit  # noqa: E402

RESULTS = ROOT / "tests" / "benchmarks" / "results"


def igavatar(*args: str) -> None:
    done = subprocess.run([sys.executable, "-m", "igavatar_cli.main", *args], cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"igavatar {' '.join(args)} failed ({done.returncode}):\n{done.stderr[-2000:]}")


def case_spec(case: str, captures: Path, args: argparse.Namespace) -> dict:
    """The batch spec of a case (also what the sequential run does, stage by stage)."""
    if case == "tiny":
        defaults = {"preprocess": {"max_size": 64}, "train": {"preset": "tiny", "device": "cpu"},
                    "export": {"resolution": 64, "formats": "ply", "device": "cpu"},
                    "eval": {"mesh_resolution": 64, "iou_points": 20000, "image_frames": 2, "device": "cpu"}}
        jobs = [{"name": f"t{i}", "capture": str(captures / "tiny"), "train": {"seed": i}} for i in range(4)]
    else:
        defaults = {"train": {"preset": "cpu", "steps": args.steps, "device": "cpu"}, "export": {"device": "cpu"},
                    "eval": {"device": "cpu"}}
        jobs = [{"name": f"seed{i}", "capture": str(captures / "demo"), "train": {"seed": i}} for i in range(3)]
    return {"out": str(args.run_dir / case / "batch"), "defaults": defaults, "jobs": jobs}


def make_captures(case: str, captures: Path, args: argparse.Namespace) -> None:
    if case == "tiny" and not (captures / "tiny" / "capture.json").is_file():
        igavatar("synth", "--out", str(captures / "tiny"), "--resolution", "64", "--train-frames", "4", "--test-frames", "2")
    if case == "demo-seeds" and not (captures / "demo" / "capture.json").is_file():
        igavatar("synth", "--out", str(captures / "demo"), "--resolution", str(args.resolution), "--train-frames",
                 str(args.frames), "--test-frames", str(max(2, args.frames // 5)))


def sequential(spec: dict, out: Path) -> float:
    """Every job's stages one after another, as a shell loop would; wall seconds."""
    started = time.perf_counter()
    for job in spec["jobs"]:
        run = out / job["name"]
        for stage in ("preprocess", "train", "export", "eval"):
            options = {**spec["defaults"].get(stage, {}), **job.get(stage, {})}
            flags = [a for k, v in options.items() for a in (f"--{k.replace('_', '-')}", str(v))]
            extra = ["--capture", job["capture"]] if stage == "preprocess" else []
            igavatar(stage, "--run-dir", str(run), *extra, *flags)
    return time.perf_counter() - started


def batched(spec: dict, spec_path: Path, cpus_per_job: float) -> float:
    spec_path.write_text(json.dumps(spec))
    started = time.perf_counter()
    igavatar("batch", str(spec_path), "--cpus-per-job", str(cpus_per_job))
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--case", choices=("tiny", "demo-seeds"), default="tiny")
    parser.add_argument("--cpus-per-job", type=float, default=1.0)
    parser.add_argument("--steps", type=int, default=1500, help="demo-seeds: training steps")
    parser.add_argument("--resolution", type=int, default=512, help="demo-seeds: synthetic image size")
    parser.add_argument("--frames", type=int, default=100, help="demo-seeds: training frames")
    parser.add_argument("--write-results", action="store_true")
    args = parser.parse_args()
    captures = args.run_dir / "captures"
    make_captures(args.case, captures, args)
    spec = case_spec(args.case, captures, args)
    for folder in ("sequential", "batch"):
        shutil.rmtree(args.run_dir / args.case / folder, ignore_errors=True)
    seq_s = sequential(spec, args.run_dir / args.case / "sequential")
    batch_s = batched(spec, args.run_dir / args.case / "spec.json", args.cpus_per_job)
    summary = (args.run_dir / args.case / "batch" / "summary.md").read_text()
    cores = os.cpu_count()
    text = "\n".join([
        f"# Batch against a sequential loop: {args.case}", "",
        f"Commit `{commit()}`; command: `{command()}`. {cores} CPU cores; no GPU.", "",
        "| jobs | sequential (default threads) | batch (--cpus-per-job " + f"{args.cpus_per_job:g}) | speed-up |",
        "|---|---|---|---|",
        f"| {len(spec['jobs'])} | {seq_s:.1f} s | {batch_s:.1f} s | {seq_s / batch_s:.2f}x |", "",
        "The batch's own summary:", "", summary])
    print(text)
    if args.write_results:
        (RESULTS / f"batch-{args.case}.md").write_text(text)
        (RESULTS / f"batch-{args.case}.json").write_text(json.dumps(
            {"commit": commit(), "command": command(), "cores": cores, "jobs": len(spec["jobs"]),
             "sequential_s": seq_s, "batch_s": batch_s, "cpus_per_job": args.cpus_per_job}, indent=2))


if __name__ == "__main__":
    main()
