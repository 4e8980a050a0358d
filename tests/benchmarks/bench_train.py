"""Training benchmark: the `cpu` preset on the default synthetic subject, and regularizer costs.

    python tests/benchmarks/bench_train.py                  # full run (about 15-20 min on 2 cores)
    python tests/benchmarks/bench_train.py --quick          # fewer steps, for a smoke run

Prints two tables: (1) one full training run of the chosen preset: steps, wall time, it/s,
rays/s, samples/s, peak RAM, validation PSNR; (2) the per-step cost of every `--regularizer`
relative to `none`, measured side by side in one process (round-robin over the variants, so
machine noise hits them alike), from the same shape-initialized weights. Not a test: numbers are
measured, never asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from igavatar.artifacts.manifest import read_artifact  # noqa: E402
from igavatar.avatar.dataset import read_dataset, training_data  # noqa: E402
from stages.train_options import with_outline_px  # noqa: E402
from igavatar.avatar.model import build_avatar  # noqa: E402
from igavatar.training.config import REGULARIZERS, preset, with_overrides  # noqa: E402
from igavatar.training.trainer import Trainer  # noqa: E402
from stages.preprocess import PreprocessOptions, run_preprocess  # noqa: E402
from stages.resources import peak_ram_bytes  # noqa: E402
from stages.synth import SynthOptions, run_synth  # noqa: E402
from stages.train import TrainOptions, run_train  # noqa: E402


def ensure_dataset(run_dir: Path) -> Path:
    """Synthesise and preprocess the default subject once (both stages skip when up to date)."""
    run_synth(SynthOptions(out=run_dir / "capture"))
    run_preprocess(PreprocessOptions(capture=run_dir / "capture", out=run_dir / "dataset"))
    return run_dir / "dataset"


def full_run(dataset: Path, out: Path, preset_name: str, steps: int | None, device: str) -> dict:
    started = time.perf_counter()
    summary = run_train(TrainOptions(dataset=dataset, out=out, preset=preset_name, steps=steps, device=device))
    wall = time.perf_counter() - started
    manifest = read_artifact(out, expected="model")
    data = manifest["data"]
    return {
        "preset": preset_name, "steps": data["steps"], "wall_s": wall,
        "train_s": manifest["timings"]["train_s"], "shape_init_s": manifest["timings"]["shape_init_s"],
        "it_s": data["speed"]["iterations_per_second"], "rays_s": data["speed"]["rays_per_second"],
        "samples_s": data["speed"]["samples_per_second"], "peak_ram_gb": manifest["peak_memory"]["ram_bytes"] / 2**30,
        "validation_psnr": data.get("validation_psnr", {}), "threads": data["speed"]["threads"],
        "validation": summary["validation"],
    }


def regularizer_costs(dataset: Path, preset_name: str, warmup: int, measured: int, device: str) -> list[dict]:
    """Mean step time of each regularizer, interleaved step by step over the variants."""
    artifact = read_dataset(dataset)
    data = training_data(artifact)
    trainers = {}
    for name in REGULARIZERS:
        config = with_outline_px(with_overrides(dataclasses.replace(preset(preset_name), steps=10_000, shape_init_steps=0), regularizer=name), artifact.image_size)
        torch.manual_seed(0)
        avatar = build_avatar(config, artifact.subject, artifact.data["pose_dim"])
        trainers[name] = Trainer(config, data, avatar, device)
    times: dict[str, list[float]] = {name: [] for name in trainers}
    samples: dict[str, list[int]] = {name: [] for name in trainers}
    for step in range(warmup + measured):
        for name, trainer in trainers.items():
            logs = trainer.train_step()
            if step >= warmup:
                times[name].append(logs["step_seconds"])
                samples[name].append(logs["samples"])
    base = statistics.mean(times["none"])
    return [
        {"regularizer": name, "step_s": statistics.mean(t), "median_s": statistics.median(t),
         "ratio_vs_none": statistics.mean(t) / base, "samples_per_step": statistics.mean(samples[name])}
        for name, t in times.items()
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, default=Path("igavatar-bench"))
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--steps", type=int, default=None, help="training steps of the full run")
    parser.add_argument("--quick", action="store_true", help="200 training steps, 3+10 cost steps")
    parser.add_argument("--skip-full", action="store_true", help="only the regularizer costs")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()
    steps = 200 if args.quick and args.steps is None else args.steps
    warmup, measured = (3, 10) if args.quick else (10, 40)

    dataset = ensure_dataset(args.run_dir)
    results: dict = {"machine": {"threads": torch.get_num_threads(), "torch": torch.__version__, "device": args.device}}
    if not args.skip_full:
        full = full_run(dataset, args.run_dir / "model", args.preset, steps, args.device)
        results["full"] = full
        print(f"\n== full training run ({args.preset} preset, {full['threads']} threads, {args.device}) ==")
        print(f"{'steps':>6} {'wall s':>8} {'train s':>8} {'init s':>7} {'it/s':>6} {'rays/s':>8} {'samples/s':>10} {'peak RAM GB':>11}  validation PSNR (dB, white bg)")
        psnrs = ", ".join(f"{k} {v:.2f}" for k, v in full["validation_psnr"].items())
        print(f"{full['steps']:>6} {full['wall_s']:>8.1f} {full['train_s']:>8.1f} {full['shape_init_s']:>7.1f} {full['it_s']:>6.2f} "
              f"{full['rays_s']:>8.0f} {full['samples_s']:>10.0f} {full['peak_ram_gb']:>11.2f}  {psnrs}")
    costs = regularizer_costs(dataset, args.preset, warmup, measured, args.device)
    results["regularizers"] = costs
    results["peak_ram_gb"] = peak_ram_bytes() / 2**30
    print(f"\n== per-step cost of each regularizer ({measured} steps each after {warmup} warm-up, interleaved) ==")
    print(f"{'regularizer':<22} {'mean s':>8} {'median s':>9} {'vs none':>8} {'samples/step':>13}")
    for row in costs:
        print(f"{row['regularizer']:<22} {row['step_s']:>8.3f} {row['median_s']:>9.3f} {row['ratio_vs_none']:>8.2f} {row['samples_per_step']:>13.0f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str))


if __name__ == "__main__":
    main()
