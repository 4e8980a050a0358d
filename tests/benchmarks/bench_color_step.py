"""Step time of training options side by side: the colour options, and the root finding's starts.

    python tests/benchmarks/bench_color_step.py --dataset RUN/dataset [--rounds 5] [--steps 15]

One process builds a trainer per variant on the dataset (the `cpu` preset, no shape initialisation,
started at step 400 so the non-rigid offset is on), warms each up for 5 steps, then times
`--steps` steps of each in turn for `--rounds` rounds (round-robin, so the machine's noise falls
on all of them alike) and reports the median ms per step and its ratio to the paper's coupling.
Variants: `paper` (the preset without its colour grid: the official network), `cpu-default` (the
preset: the colour grid of config.color_grid_config, the paper's coupling), `decoupled` (colour grid of config.color_grid_config, SDF features
and normal detached, colour on fixed weights), `grid-detached` (the same with the weights coupled),
`decoupled-grid12` (decoupled with a copy of the SDF's grid), `no-shading` (the preset with `--shading none`:
the colour as the paper's, unlit), `no-root-fallback` (the preset without its deformer's fallback starts:
a point none of whose top-2 starts converged stays without a root), `top4` (four starts a point instead of two).
`--variants` picks some (the first is the one the others are compared with), `--name` the results
file: results/NAME.md and .json (default color-step) with the commit and the command.

    python tests/benchmarks/bench_color_step.py --dataset RUN/dataset --variants no-shading,cpu-default --name shading-step

`--model DIR --start N` starts every variant from that trained model's weights and occupancy grid at
step N instead (a variant's extra parameters start fresh), so the steps sample as a trained surface
does (late in training: fewer samples a ray than from scratch).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
from provenance import commit  # noqa: E402

from igavatar.avatar.dataset import read_dataset, training_data  # noqa: E402
from igavatar.avatar.model import build_avatar, load_model  # noqa: E402
from igavatar.training.config import TrainConfig, color_grid_config, preset  # noqa: E402
from igavatar.training.trainer import Trainer  # noqa: E402
from stages.train_options import with_outline_px  # noqa: E402

RESULTS = ROOT / "tests" / "benchmarks" / "results"


def decoupled(base: TrainConfig, grid, fixed_weights: bool = True) -> TrainConfig:
    color = dataclasses.replace(base.avatar.color, hash_grid=grid, feature_gradient=False, normal_gradient=False)
    return dataclasses.replace(base, color_shapes_geometry=not fixed_weights,
                               avatar=dataclasses.replace(base.avatar, color=color))


def with_deformer(base: TrainConfig, **changes) -> TrainConfig:
    deformer = dataclasses.replace(base.avatar.deformer, **changes)
    return dataclasses.replace(base, avatar=dataclasses.replace(base.avatar, deformer=deformer))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=15)
    parser.add_argument("--variants", default="paper,cpu-default,decoupled,grid-detached,decoupled-grid12")
    parser.add_argument("--name", default="color-step")
    parser.add_argument("--model", type=Path, default=None, help="start from this trained model's weights")
    parser.add_argument("--start", type=int, default=400, help="the step the trainers start at")
    args = parser.parse_args()
    dataset = read_dataset(args.dataset)
    data = training_data(dataset)
    base = with_outline_px(dataclasses.replace(preset("cpu"), steps=800, shape_init_steps=0), dataset.image_size)
    sdf_grid = base.avatar.sdf.hash_grid
    paper = dataclasses.replace(base, avatar=dataclasses.replace(
        base.avatar, color=dataclasses.replace(base.avatar.color, hash_grid=None)))
    variants = {"paper": paper, "cpu-default": base, "decoupled": decoupled(base, color_grid_config(sdf_grid)),
                "grid-detached": decoupled(base, color_grid_config(sdf_grid), fixed_weights=False),
                "decoupled-grid12": decoupled(base, sdf_grid),
                "no-shading": dataclasses.replace(base, avatar=dataclasses.replace(base.avatar, shading="none")),
                "no-root-fallback": with_deformer(base, fallback_starts=False), "top4": with_deformer(base, init_top_k=4)}
    variants = {name: variants[name] for name in args.variants.split(",")}
    reference = next(iter(variants))
    trained = None if args.model is None else load_model(args.model)
    trainers = {}
    for name, config in variants.items():
        torch.manual_seed(0)
        avatar = build_avatar(config, dataset.subject, dataset.data["pose_dim"])
        if trained is not None:
            avatar.load_state_dict(trained.avatar.state_dict(), strict=False)
        trainer = Trainer(config, data, avatar)
        if trained is not None:
            trainer.canonical_grid.load_state_dict(trained.canonical_grid.state_dict())
        trainer.step = args.start
        for _ in range(5):
            trainer.train_step()
        trainers[name] = trainer
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(args.rounds):
        for name, trainer in trainers.items():
            tick = time.perf_counter()
            for _ in range(args.steps):
                trainer.train_step()
            times[name].append(1000 * (time.perf_counter() - tick) / args.steps)
    medians = {name: statistics.median(values) for name, values in times.items()}
    command = "python tests/benchmarks/bench_color_step.py " + shlex.join(sys.argv[1:])
    lines = ["# Step time of training options, side by side", "", f"Commit: `{commit()}`. Command:", "", f"    {command}", "",
             f"Dataset `{args.dataset}`; `cpu` preset from step {args.start}"
             + (f" with the weights of `{args.model}`" if args.model else "") + f", {args.rounds} rounds of {args.steps} steps, "
             f"round-robin, {torch.get_num_threads()} threads.", "",
             f"| variant | median ms/step | vs {reference} | rounds (ms/step) |", "|---|---|---|---|"]
    for name, values in times.items():
        lines.append(f"| {name} | {medians[name]:.1f} | {medians[name] / medians[reference] - 1:+.1%} | "
                     + ", ".join(f"{v:.1f}" for v in values) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    (RESULTS / f"{args.name}.md").write_text(text)
    (RESULTS / f"{args.name}.json").write_text(json.dumps({"commit": commit(), "command": command, "ms_per_step": times},
                                                        indent=2) + "\n")


if __name__ == "__main__":
    main()
