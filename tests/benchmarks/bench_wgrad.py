"""The weight-gradient kernel on this CPU: each ISA copy against oneDNN and torch, and the training step.

    python tests/benchmarks/bench_wgrad.py --dataset RUN/dataset [--then /tmp/then] [--rounds 3] [--steps 10]

Table 1 records the layer shapes one `cpu`-preset training step sends to ``weight_gradients`` (by
running one step with a recorder around it), then times ``grad^T x`` for each shape with every copy
of the ``wgrad`` kernel this CPU runs (``copies()``), with oneDNN's inner-product backward and with
torch's ``mm``: the median of 7 calls each, milliseconds.

Table 2 (with ``--then``, a worktree of an older commit) times the `cpu` preset's training step in
separate processes, "then" (that worktree's code) and "now" (this tree) alternated for ``--rounds``
rounds: ``--steps`` steps each after 5 warm-up steps, from step 900 of 1500 with no shape
initialisation (the non-rigid offset on). Writes results/wgrad-<cpu>.md and .json with the commit,
the command and the CPU's vector features.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
from provenance import command, commit  # noqa: E402

RESULTS = ROOT / "tests" / "benchmarks" / "results"

# Run in a child process with the code under test first on sys.path: prints ms per step.
STEP_SCRIPT = """
import dataclasses, sys, time, torch
sys.path.insert(0, sys.argv[1])
from igavatar.avatar.dataset import read_dataset, training_data
from stages.train_options import with_outline_px
from igavatar.avatar.model import build_avatar
from igavatar.training.config import preset
from igavatar.training.trainer import Trainer
dataset = read_dataset(sys.argv[2]); data = training_data(dataset)
config = with_outline_px(dataclasses.replace(preset("cpu"), steps=1500, shape_init_steps=0), dataset.image_size)
torch.manual_seed(0)
trainer = Trainer(config, data, build_avatar(config, dataset.subject, dataset.data["pose_dim"]))
trainer.step = 900
for _ in range(5):
    trainer.train_step()
tick = time.perf_counter()
for _ in range(int(sys.argv[3])):
    trainer.train_step()
print(1000 * (time.perf_counter() - tick) / int(sys.argv[3]))
"""


def cpu_features() -> str:
    """The CPU's model name and its x86 vector features that decide the kernel's copy."""
    info = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    model = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")), "?")
    flags = next((line.split(":", 1)[1].split() for line in info.splitlines() if line.startswith("flags")), [])
    return f"{model}; " + " ".join(f for f in ("avx2", "fma", "avx512f") if f in flags)


def step_shapes(dataset_path: Path) -> list[tuple[int, int, int]]:
    """(rows, in, out) of every weight gradient one `cpu`-preset step computes."""
    from igavatar.avatar.dataset import read_dataset, training_data
    from stages.train_options import with_outline_px
    from igavatar.avatar.model import build_avatar
    from igavatar.model import linear as linear_module
    from igavatar.training.config import preset
    from igavatar.training.trainer import Trainer

    dataset = read_dataset(dataset_path)
    config = with_outline_px(dataclasses.replace(preset("cpu"), steps=1500, shape_init_steps=0), dataset.image_size)
    torch.manual_seed(0)
    trainer = Trainer(config, training_data(dataset), build_avatar(config, dataset.subject, dataset.data["pose_dim"]))
    trainer.step = 900
    shapes: list[tuple[int, int, int]] = []
    original = linear_module.weight_gradients

    def recorder(grad, x, weight, with_bias):
        shapes.append((x.shape[0], x.shape[1], grad.shape[1]))
        return original(grad, x, weight, with_bias)

    linear_module.weight_gradients = recorder
    try:
        trainer.train_step()
    finally:
        linear_module.weight_gradients = original
    return shapes


def time_ms(fn, calls: int = 7) -> float:
    fn()
    times = []
    for _ in range(calls):
        tick = time.perf_counter()
        fn()
        times.append(1000 * (time.perf_counter() - tick))
    return statistics.median(times)


def product_table(shapes: list[tuple[int, int, int]]) -> tuple[list[str], list[dict]]:
    from igavatar.kernels import load_kernel
    from igavatar.model.linear import onednn_weight_gradients

    kernel = load_kernel("wgrad")
    copies = kernel.copies()
    rows_out = []
    lines = ["| rows x in -> out | " + " | ".join(f"wgrad {c}" for c in copies) + " | oneDNN | torch mm |",
             "|---|" + "---|" * (len(copies) + 2)]
    for rows, d_in, d_out in sorted(set(shapes), key=lambda s: (s[1], s[2], s[0])):
        x, grad = torch.randn(rows, d_in), torch.randn(rows, d_out)
        weight, empty = torch.randn(d_out, d_in), torch.empty(0)
        entry = {"rows": rows, "in": d_in, "out": d_out}
        for copy in copies:
            if d_in % 16 == 0:
                out = torch.empty(d_out, d_in)
                entry[copy] = time_ms(lambda: kernel.outer_sum(grad.numpy(), x.numpy(), out.numpy(), empty.numpy(), empty.numpy(), copy))
            elif d_out % 16 == 0:
                out = torch.empty(d_in, d_out)
                entry[copy] = time_ms(lambda: kernel.outer_sum(x.numpy(), grad.numpy(), out.numpy(), empty.numpy(), empty.numpy(), copy))
            else:
                entry[copy] = None
        entry["onednn"] = time_ms(lambda: onednn_weight_gradients(grad, x, weight, True))
        entry["mm"] = time_ms(lambda: grad.t() @ x)
        rows_out.append(entry)
        cells = [f"{entry[c]:.2f}" if entry[c] is not None else "-" for c in copies]
        lines.append(f"| {rows} x {d_in} -> {d_out} | " + " | ".join(cells) + f" | {entry['onednn']:.2f} | {entry['mm']:.2f} |")
    return lines, rows_out


def step_table(then: Path, dataset: Path, rounds: int, steps: int) -> tuple[list[str], dict]:
    times: dict[str, list[float]] = {"then": [], "now": []}
    for _ in range(rounds):
        for name, code in (("then", then), ("now", ROOT)):
            env = dict(os.environ, PYTHONPATH=str(code))
            result = subprocess.run([sys.executable, "-c", STEP_SCRIPT, str(code), str(dataset), str(steps)],
                                    capture_output=True, text=True, env=env, check=True)
            times[name].append(float(result.stdout.strip().splitlines()[-1]))
    then_commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=then, capture_output=True, text=True).stdout.strip()
    lines = ["| code | ms per step (rounds) | median |", "|---|---|---|"]
    for name, values in times.items():
        label = f"then ({then_commit})" if name == "then" else f"now ({commit()})"
        lines.append(f"| {label} | " + ", ".join(f"{v:.0f}" for v in values) + f" | {statistics.median(values):.0f} |")
    ratio = statistics.median(times["then"]) / statistics.median(times["now"])
    lines += ["", f"now is {ratio:.2f}x the speed of then."]
    return lines, {"then_commit": then_commit, "ms_per_step": times}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--then", type=Path, help="a worktree of the commit to compare the step with")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=10)
    args = parser.parse_args()
    features = cpu_features()
    shapes = step_shapes(args.dataset)
    table, products = product_table(shapes)
    lines = ["# The weight-gradient kernel's copies on this CPU, and the training step", "",
             f"Commit: `{commit()}`. Command:", "", f"    {command()}", "",
             f"CPU: {features}; {torch.get_num_threads()} threads. Dataset `{args.dataset}`.", "",
             "## Weight gradients grad^T x of one `cpu`-preset step's layers (median ms of 7 calls)", "", *table]
    record = {"commit": commit(), "command": command(), "cpu": features, "products_ms": products}
    if args.then is not None:
        step_lines, record["step"] = step_table(args.then, args.dataset, args.rounds, args.steps)
        lines += ["", f"## The `cpu` preset's training step, {args.rounds} rounds of {args.steps} steps "
                  "(separate processes, alternated)", "", *step_lines]
    text = "\n".join(lines) + "\n"
    print(text)
    tag = "avx512" if "avx512f" in features else "avx2" if "avx2" in features else "base"
    (RESULTS / f"wgrad-{tag}.md").write_text(text)
    (RESULTS / f"wgrad-{tag}.json").write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
