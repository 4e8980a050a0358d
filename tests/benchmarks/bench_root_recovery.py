"""Does root finding bring a dataset's template back? The shape prior (`template.ply`) posed by the
dataset's own skinning grid into evenly spaced frames, then root-found back by the `cpu` preset's
deformer under each start policy: the share of its vertices with a valid root within 1 mm of their
true canonical place (a vertex without one renders as a hole in that frame, and training cannot
put its surface where it belongs). No training, no truth: any dataset, real ones included.

    python tests/benchmarks/bench_root_recovery.py --dataset RUN/dataset --name root-recovery-zju377 [--frames 8]

Policies: `top2` (the preset's two best-ranked starts, no fallback), `top2+fallback` (the preset:
points with no converged root try the other starts), `top4+fallback`, `all` (every start bone).
Writes results/NAME.md and .json with the commit and the command.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
from provenance import commit  # noqa: E402

from igavatar.avatar.dataset import read_dataset  # noqa: E402
from igavatar.avatar.model import build_avatar  # noqa: E402
from igavatar.model.deformer import DeformerConfig, FastSnarfDeformer  # noqa: E402
from igavatar.training.config import preset  # noqa: E402

RESULTS = ROOT / "tests" / "benchmarks" / "results"
RECOVERED_M = 1e-3


def policies(base: DeformerConfig) -> dict[str, DeformerConfig]:
    """The deformer configurations compared, from the preset's."""
    return {"top2": dataclasses.replace(base, fallback_starts=False), "top2+fallback": base,
            "top4+fallback": dataclasses.replace(base, init_top_k=4), "all": dataclasses.replace(base, init_top_k=None)}


def recovery(deformer: FastSnarfDeformer, vertices: torch.Tensor, bone_transforms: np.ndarray) -> float:
    """Share of (V, 3) canonical vertices root-found back within RECOVERED_M after posing by one frame's bones."""
    frame = deformer.prepare(torch.from_numpy(bone_transforms).float())
    candidates, valid = deformer.canonicalize(deformer.forward_skinning(vertices, frame), frame)
    close = (candidates - vertices.unsqueeze(1)).norm(dim=-1) < RECOVERED_M
    return float((valid & close).any(dim=1).float().mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=8, help="evenly spaced frames of the dataset")
    parser.add_argument("--name", required=True)
    args = parser.parse_args()
    dataset = read_dataset(args.dataset)
    subject = dataset.subject
    frames = dataset.frames()
    picked = np.linspace(0, frames.n_frames - 1, min(args.frames, frames.n_frames)).round().astype(int)
    vertices = torch.from_numpy(np.asarray(trimesh.load(args.dataset / "template.ply", process=False).vertices, np.float32))
    cpu = preset("cpu")
    table = {}
    for name, config in policies(cpu.avatar.deformer).items():
        # The deformer exactly as a model of this dataset builds it (grid, box, start bones and parts).
        avatar_config = dataclasses.replace(cpu.avatar, deformer=config)
        deformer = build_avatar(dataclasses.replace(cpu, avatar=avatar_config), subject, dataset.data["pose_dim"]).deformer
        table[name] = [recovery(deformer, vertices, frames.bone_transforms[i]) for i in picked]
    command = "python tests/benchmarks/bench_root_recovery.py " + shlex.join(sys.argv[1:])
    names = [frames.names[i] for i in picked]
    lines = [f"# Root recovery of the template: {args.name}", "", f"Commit: `{commit()}`. Command:", "", f"    {command}", "",
             f"Dataset `{args.dataset}` (skinning grid {list(subject.skinning_grid.shape[1:])} as D,H,W; "
             f"{len(vertices)} template vertices); share of the vertices root-found back within {RECOVERED_M * 1000:.0f} mm.", "",
             "| policy | mean | worst frame | " + " | ".join(names) + " |", "|---" * (len(names) + 3) + "|"]
    for name, values in table.items():
        lines.append(f"| {name} | {np.mean(values):.4f} | {np.min(values):.4f} | " + " | ".join(f"{v:.4f}" for v in values) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    (RESULTS / f"{args.name}.md").write_text(text)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(
        {"commit": commit(), "command": command, "dataset": str(args.dataset), "frames": names, "recovered": table}, indent=2) + "\n")


if __name__ == "__main__":
    main()
