"""Speed benchmark: the fast CPU kernels against the plain PyTorch reference, side by side.

    python tests/benchmarks/bench_speed.py                       # training step profile, ~5 min on 2 cores
    python tests/benchmarks/bench_speed.py --model igavatar-run/model   # + export 512^3 and animate
    python tests/benchmarks/bench_speed.py --train               # + `igavatar train` end to end, ~12 min
    python tests/benchmarks/bench_speed.py --quick               # a smoke run

Table 1 is the `cpu` preset's training step on the default synthetic subject, built twice from
the same weights: once with every kernel off (``IGAVATAR_KERNELS=0``: the PyTorch reference
path) and once with them on. Steps alternate between the two (round-robin, so machine noise hits
both alike) and each step is split into components by timers around the avatar's parts, each
charged exclusively (a call nested in another counts for its own component only):

    root finding     Avatar.correspond: start selection, Broyden iterations, duplicates
    hash grid        every forward of the encoding (with its closed-form Jacobian in training)
    MLPs             SDF, color and non-rigid MLPs (also those scoring candidates)
    renderer         posed occupancy, sampling, compositing
    losses           the loss terms
    backward         one backward pass through everything above
    optimizer        Adam (torch's fused kernel on the fast path, its per-tensor loop in the reference)
    occupancy        the canonical occupancy grid's periodic update (its field queries excluded)
    other            the rest of the step (ray generation, batching, bookkeeping)

With ``--train``, `igavatar train --preset cpu` runs end to end in two processes, kernels off
then on: the figure to quote for the whole run (steps, shape fit, stage wall time).

Table 2 (with ``--model``) runs `igavatar export` (512^3 marching cubes) and `igavatar animate`
on a trained model in separate processes with the kernels off and on. Table 3 is the hash-grid
kernel alone (forward + Jacobian + backward). Numbers are measured, never asserted.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_train import ensure_dataset  # noqa: E402
from provenance import command, commit  # noqa: E402

from igavatar.artifacts.manifest import read_artifact  # noqa: E402
from igavatar.avatar.dataset import read_dataset, training_data  # noqa: E402
from stages.train_options import with_outline_px  # noqa: E402
from igavatar.avatar.model import build_avatar  # noqa: E402
from igavatar.kernels import kernel_status, load_kernel, set_kernels_enabled  # noqa: E402
import igavatar.model.posed as posed_module  # noqa: E402
from igavatar.training.checkpoint import load_state  # noqa: E402
from igavatar.training.config import preset, with_overrides  # noqa: E402
import igavatar.training.trainer as trainer_module  # noqa: E402
from igavatar.training.trainer import Trainer  # noqa: E402
from stages.resources import peak_ram_bytes, tune_host_allocator  # noqa: E402

COMPONENTS = ("root finding", "hash grid", "MLPs", "renderer", "losses", "backward", "optimizer", "occupancy", "other")


class Profiler:
    """Exclusive wall time per label, charged to the trainer that is stepping.

    Timers wrap methods and functions; a wrapped call nested in another is charged to its own
    label and subtracted from its parent's, so the labels of one step add up without overlap.
    """

    def __init__(self) -> None:
        self.current = "reference"
        self.seconds: dict[str, dict[str, float]] = collections.defaultdict(lambda: collections.defaultdict(float))
        self._stack: list[list[float]] = []  # per open call: [time spent in nested wrapped calls]

    def wrap(self, owner, name: str, label: str) -> None:
        original = getattr(owner, name)
        profiler = self

        @functools.wraps(original)
        def timed(*args, **kwargs):
            profiler._stack.append([0.0])
            started = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - started
                nested = profiler._stack.pop()[0]
                profiler.seconds[profiler.current][label] += elapsed - nested
                if profiler._stack:
                    profiler._stack[-1][0] += elapsed

        setattr(owner, name, timed)

    def clear(self) -> None:
        self.seconds.clear()


def instrument(profiler: Profiler, trainer: Trainer) -> None:
    """Timers on one trainer's avatar parts (module functions are wrapped once, see below)."""
    avatar = trainer.avatar
    profiler.wrap(avatar, "correspond", "root finding")
    profiler.wrap(avatar.sdf_field, "forward_with_gradient", "MLPs")
    profiler.wrap(avatar.sdf_field, "forward", "MLPs")
    if avatar.sdf_field.encoding is not None:
        profiler.wrap(avatar.sdf_field.encoding, "forward_with_jacobian", "hash grid")
        profiler.wrap(avatar.sdf_field.encoding, "forward", "hash grid")
    profiler.wrap(avatar.color_field, "forward", "MLPs")
    profiler.wrap(avatar.nonrigid, "forward", "MLPs")
    profiler.wrap(trainer.optimizer, "step", "optimizer")
    profiler.wrap(trainer, "_update_occupancy", "occupancy")
    profiler.wrap(trainer, "_regularizer_terms", "losses")


def instrument_functions(profiler: Profiler) -> None:
    """Timers on the module-level functions the trainer calls, and on backward."""
    for name, label in (("render_rays", "renderer"), ("sample_along_rays", "renderer"),
                        ("rgb_loss", "losses"), ("alpha_loss", "losses")):
        profiler.wrap(trainer_module, name, label)
    # The posed occupancy grid is built through PosedAvatar.occupancy.
    profiler.wrap(posed_module, "posed_occupancy", "renderer")
    profiler.wrap(torch.Tensor, "backward", "backward")


def components(seconds: dict[str, float], total: float, steps: int) -> dict[str, float]:
    """Per-step seconds of each reported component ("other": the step's untimed remainder)."""
    out = {key: seconds.get(key, 0.0) / steps for key in COMPONENTS if key != "other"}
    out["other"] = max(total - sum(out.values()), 0.0)
    return out


def training_profile(
    dataset: Path, warmup: int, measured: int, device: str, start_fraction: float, from_model: Path | None
) -> dict:
    """Both trainers from the same weights, stepping from `start_fraction` of the cpu preset's run
    (0: the rigid first half; 0.8: the non-rigid MLP on, the VolSDF beta capped). With
    `from_model`, the weights and occupancy grid are a trained model's: a trained surface keeps
    far fewer samples per ray than the initial sphere, which is what a real run spends most steps on."""
    artifact = read_dataset(dataset)
    data = training_data(artifact)
    config = with_outline_px(with_overrides(dataclasses.replace(preset("cpu"), shape_init_steps=0)), artifact.image_size)
    trainers: dict[str, Trainer] = {}
    profiler = Profiler()
    for name, enabled in (("reference", False), ("fast", True)):
        set_kernels_enabled(enabled)
        torch.manual_seed(0)
        avatar = build_avatar(config, artifact.subject, artifact.data["pose_dim"])
        trainers[name] = Trainer(config, data, avatar, device)
        if from_model is not None:
            weights = load_state(from_model / "weights.npz")
            avatar.load_state_dict(weights["avatar"])
            trainers[name].canonical_grid.load_state_dict(weights["canonical_grid"])
        trainers[name].step = int(start_fraction * trainers[name].total_steps)
        instrument(profiler, trainers[name])
    instrument_functions(profiler)
    totals: dict[str, list[float]] = {name: [] for name in trainers}
    samples: dict[str, list[int]] = {name: [] for name in trainers}
    losses: dict[str, list[float]] = {name: [] for name in trainers}
    for step in range(warmup + measured):
        if step == warmup:
            profiler.clear()
        for name, trainer in trainers.items():
            profiler.current = name
            set_kernels_enabled(name == "fast")
            started = time.perf_counter()
            logs = trainer.train_step()
            elapsed = time.perf_counter() - started
            if step >= warmup:
                totals[name].append(elapsed)
                samples[name].append(logs["samples"])
                losses[name].append(logs["loss"])
    set_kernels_enabled(None)
    result = {}
    for name in trainers:
        mean = statistics.mean(totals[name])
        result[name] = {
            "step_s": mean, "median_s": statistics.median(totals[name]), "it_s": 1.0 / mean,
            "rays_s": trainers[name].config.rays_per_step / mean,
            "samples_s": statistics.mean(samples[name]) / mean,
            "mean_loss": statistics.mean(losses[name]),
            "components": components(profiler.seconds[name], mean, measured),
        }
    return result


def hashgrid_micro(points: int, repeats: int) -> dict:
    """Median seconds of bench_hashgrid's step (forward + Jacobian + backward of the cpu preset's
    grid), reference vs kernel, round-robin after two warm-up rounds."""
    from bench_hashgrid import CONFIG, step

    from igavatar.model.hashgrid import HashGridEncoding

    grid = HashGridEncoding(CONFIG, torch.full((3,), -1.0), torch.ones(3))
    torch.nn.init.uniform_(grid.table, -0.1, 0.1)
    x = (torch.rand(points, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1).requires_grad_(True)
    times: dict[str, list[float]] = {"reference": [], "fast": []}
    for r in range(repeats + 2):
        for name, path in (("reference", "reference"), ("fast", "kernel")):
            forward_s, backward_s = step(grid, x, path)
            if r >= 2:
                times[name].append(forward_s + backward_s)
    return {name: statistics.median(t) for name, t in times.items()}


def cli_timings(model: Path, work: Path) -> dict:
    """export (512^3), animate (2 s walk, 256 px) and eval (every test frame against its scan, the
    model's own dataset) with the kernels off and on, separate processes."""
    rows = {}
    for name, flag in (("reference", "0"), ("fast", "1")):
        env = dict(os.environ, IGAVATAR_KERNELS=flag)
        export = _cli(["export", "--model", str(model), "--out", str(work / f"mesh-{name}"), "--resolution", "512",
                       "--device", "cpu", "--force"], env)
        animate = _cli(["animate", "--model", str(model), "--out", str(work / f"animation-{name}"), "--device", "cpu"], env)
        evaluation = _cli(["eval", "--model", str(model), "--out", str(work / f"report-{name}"), "--device", "cpu"], env)
        rows[name] = {"export": export, "animate": animate, "eval": evaluation}
    return rows


def train_timings(dataset: Path, work: Path, steps: int | None) -> dict:
    """`igavatar train --preset cpu` with the kernels off, then on, in separate processes; the
    stage's own timings (shape fit, training steps, final validation) and its wall time."""
    rows = {}
    for name, flag in (("reference", "0"), ("fast", "1")):
        env = dict(os.environ, IGAVATAR_KERNELS=flag)
        out = work / f"train-{name}"
        # From scratch: a model left here would hand its cached shape initialization to this run.
        shutil.rmtree(out, ignore_errors=True)
        args = ["train", "--dataset", str(dataset), "--out", str(out), "--preset", "cpu", "--device", "cpu", "--quiet"]
        if steps is not None:
            args += ["--steps", str(steps)]
        summary = _cli(args, env)
        manifest = read_artifact(out, expected="model")
        summary["timings"] = manifest["timings"] if "timings" in manifest else manifest["data"].get("timings")
        rows[name] = summary
    return rows


def print_train_timings(rows: dict) -> None:
    ref, fast = rows["reference"], rows["fast"]
    print(f"\n== igavatar train --preset cpu ({ref['steps']} steps), separate processes, kernels off then on ==")
    print(f"{'':<30} {'reference':>10} {'fast':>8} {'speed-up':>9}")
    lines = [("training steps, s", ref["train_seconds"], fast["train_seconds"])]
    if ref.get("timings") and fast.get("timings"):
        lines += [("shape initialization, s", ref["timings"]["shape_init_s"], fast["timings"]["shape_init_s"]),
                  ("whole stage (its own timer), s", ref["timings"]["total_s"], fast["timings"]["total_s"])]
    lines.append(("process wall time, s", ref["wall_s"], fast["wall_s"]))
    for label, r, f in lines:
        print(f"{label:<30} {r:>10.1f} {f:>8.1f} {r / f if f > 0 else float('nan'):>8.2f}x")
    print(f"it/s {ref['it_per_s']:.2f} -> {fast['it_per_s']:.2f}; validation PSNR {ref['validation_psnr']} vs {fast['validation_psnr']}")


def _cli(args: list[str], env: dict) -> dict:
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "igavatar_cli.main", *args, "--json"], cwd=ROOT, env=env,
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"igavatar {' '.join(args)} failed:\n{done.stderr[-2000:]}")
    summary = json.loads(done.stdout)
    summary["wall_s"] = time.perf_counter() - started
    return summary


def print_profile(phase: str, profile: dict, warmup: int, measured: int) -> None:
    ref, fast = profile["reference"], profile["fast"]
    print(f"\n== cpu preset training step, {phase}: reference vs fast ({measured} steps each after {warmup}, interleaved) ==")
    print(f"{'component':<14} {'reference ms':>13} {'fast ms':>9} {'speed-up':>9} {'share ref':>10} {'share fast':>11}")
    for key in COMPONENTS:
        r, f = ref["components"][key], fast["components"][key]
        print(f"{key:<14} {r * 1e3:>13.1f} {f * 1e3:>9.1f} {r / f if f > 0 else float('nan'):>8.2f}x "
              f"{100 * r / ref['step_s']:>9.1f}% {100 * f / fast['step_s']:>10.1f}%")
    print(f"{'step (mean)':<14} {ref['step_s'] * 1e3:>13.1f} {fast['step_s'] * 1e3:>9.1f} {ref['step_s'] / fast['step_s']:>8.2f}x")
    print(f"{'step (median)':<14} {ref['median_s'] * 1e3:>13.1f} {fast['median_s'] * 1e3:>9.1f} {ref['median_s'] / fast['median_s']:>8.2f}x")
    print(f"it/s {ref['it_s']:.2f} -> {fast['it_s']:.2f}; rays/s {ref['rays_s']:.0f} -> {fast['rays_s']:.0f}; "
          f"samples/s {ref['samples_s']:.0f} -> {fast['samples_s']:.0f}; mean loss {ref['mean_loss']:.4f} vs {fast['mean_loss']:.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, default=Path("igavatar-bench"))
    parser.add_argument("--model", type=Path, default=None, help="trained model: also time export, animate and eval")
    parser.add_argument("--dataset", type=Path, default=None,
                        help="time training on this dataset artifact instead of the default subject's (e.g. one made "
                             "by another version, to compare two versions of the code on the same data)")
    parser.add_argument("--from-model", type=Path, default=None,
                        help="start the profiled steps from this trained model's weights (realistic sample counts)")
    parser.add_argument("--skip-training", action="store_true", help="only the export/animate/eval table (needs --model)")
    parser.add_argument("--train", action="store_true",
                        help="also run `igavatar train --preset cpu` end to end, kernels off then on (~12 min on 2 cores)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()
    warmup, measured = (2, 4) if args.quick else (8, 30)
    # As the CLI does, for both trainers alike (the reference is the plain PyTorch *code* path).
    allocator = tune_host_allocator()

    status = {name: ("loaded" if load_kernel(name) is not None else kernel_status()[name]) for name in kernel_status()}
    dataset = args.dataset if args.dataset is not None else ensure_dataset(args.run_dir)
    results: dict = {"machine": {"threads": torch.get_num_threads(), "torch": torch.__version__}, "kernels": status,
                     "host_allocator": allocator}
    print(f"kernels: {status}; {torch.get_num_threads()} threads, torch {torch.__version__}; "
          f"host allocator settings: {allocator or 'default'}")

    results["training"] = {}
    phases = () if args.skip_training else (("rigid (first half)", 0.0), ("non-rigid on (second half)", 0.8))
    for phase, fraction in phases:
        profile = training_profile(dataset, warmup, measured, args.device, fraction, args.from_model)
        results["training"][phase] = profile
        print_profile(phase, profile, warmup, measured)
    if results["training"]:
        ref = statistics.mean(p["reference"]["step_s"] for p in results["training"].values())
        fast = statistics.mean(p["fast"]["step_s"] for p in results["training"].values())
        results["training_mean_speedup"] = ref / fast
        print(f"\nwhole run (the two halves alike): {ref * 1e3:.1f} -> {fast * 1e3:.1f} ms per step, {ref / fast:.2f}x")

        points = 8192 if args.quick else 32768
        micro = hashgrid_micro(points, 3 if args.quick else 10)
        results["hashgrid_micro"] = micro
        print(f"\n== hash grid alone: forward + Jacobian + backward, {points} points, cpu preset grid (median) ==")
        print(f"reference {micro['reference'] * 1e3:.1f} ms, fast {micro['fast'] * 1e3:.1f} ms, "
              f"{micro['reference'] / micro['fast']:.2f}x")

    if args.train:
        rows = train_timings(dataset, args.run_dir / "speed", 100 if args.quick else None)
        results["train_end_to_end"] = rows
        print_train_timings(rows)

    if args.model is not None:
        timings = cli_timings(args.model, args.run_dir / "speed")
        results["stages"] = timings
        print("\n== export (512^3), animate (60 frames, 256 px) and eval (test frames), separate processes ==")
        print(f"{'stage':<10} {'reference s':>12} {'fast s':>8} {'speed-up':>9}")
        for stage in ("export", "animate", "eval"):
            r, f = timings["reference"][stage]["wall_s"], timings["fast"][stage]["wall_s"]
            print(f"{stage:<10} {r:>12.1f} {f:>8.1f} {r / f:>8.2f}x")
        r, f = (timings[name]["animate"]["frames_per_s"] for name in ("reference", "fast"))
        print(f"animation rendering: {r:.2f} -> {f:.2f} frames/s (stage wall time includes start-up and video encoding)")
    results["peak_ram_gb"] = peak_ram_bytes() / 2**30
    print(f"\npeak RAM of this process: {results['peak_ram_gb']:.2f} GB")
    if args.json:
        args.json.write_text(json.dumps({"commit": commit(), "command": command(), **results}, indent=2, default=str))


if __name__ == "__main__":
    main()
