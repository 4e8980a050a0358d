"""What eval's samples per ray do to the held-out image metrics, and what they cost.

For each run (a model and its dataset) and each sample count, `igavatar eval --no-geometry` renders
the test frames (eval's default frames, at `--image-scale`) and the box/full PSNR and SSIM are
recorded with the eval's wall time.

    python tests/benchmarks/bench_eval_samples.py --run demo=RUN/model,RUN/dataset [--run ...] \
        --samples 32,96 [--image-scale 0.25] --out tests/benchmarks/results/eval-samples
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from provenance import command, commit

ROOT = Path(__file__).resolve().parents[2]
KEYS = ("psnr_mask_bbox_db", "ssim_mask_bbox", "psnr_full_db", "ssim_full")


def run_eval(model: Path, dataset: Path, samples: int, scale: float, out: Path) -> dict:
    """One `igavatar eval` on CPU; its image metrics' means and its wall time (s)."""
    argv = [sys.executable, "-m", "igavatar_cli.main", "eval", "--model", str(model), "--dataset", str(dataset),
            "--no-geometry", "--samples", str(samples), "--image-scale", str(scale), "--out", str(out),
            "--device", "cpu", "--force", "--json"]
    started = time.perf_counter()
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"eval failed ({done.returncode}): {done.stderr.strip()[-800:]}")
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    return {"samples": samples, "eval_s": round(seconds, 1), **{k: round(metrics[k]["mean"], 3) for k in KEYS}}


def table(results: dict) -> str:
    lines = ["| run | samples | box PSNR dB | box SSIM | full PSNR dB | full SSIM | eval s |", "|---|---|---|---|---|---|---|"]
    for name, rows in results["runs"].items():
        for r in rows:
            lines.append(f"| {name} | {r['samples']} | {r['psnr_mask_bbox_db']} | {r['ssim_mask_bbox']} | "
                         f"{r['psnr_full_db']} | {r['ssim_full']} | {r['eval_s']} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="append", required=True, help="name=MODEL_DIR,DATASET_DIR")
    parser.add_argument("--samples", default="32,96", help="comma-separated samples per ray")
    parser.add_argument("--image-scale", type=float, default=0.25)
    parser.add_argument("--out", type=Path, required=True, help="results path without suffix (.json and .md)")
    args = parser.parse_args()
    counts = [int(s) for s in args.samples.split(",")]
    results = {"commit": commit(), "command": command(), "image_scale": args.image_scale, "runs": {}}
    with tempfile.TemporaryDirectory() as scratch:
        for spec in args.run:
            name, _, paths = spec.partition("=")
            model, dataset = (Path(p) for p in paths.split(","))
            results["runs"][name] = [run_eval(model, dataset, n, args.image_scale, Path(scratch) / f"{name}-{n}")
                                     for n in counts]
            print(name, results["runs"][name], flush=True)
    args.out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    args.out.with_suffix(".md").write_text(
        f"# eval's samples per ray against its image metrics\n\ncommit {results['commit']}; command:\n\n"
        f"    {results['command']}\n\nImage scale {args.image_scale}; CPU (2 cores); eval's default test frames.\n\n"
        f"{table(results)}\n")


if __name__ == "__main__":
    main()
