"""Hash-grid micro-benchmark: PyTorch reference vs the C++/OpenMP kernel, forward_with_jacobian + backward.

    flock /tmp/igavatar-cpu.lock .venv/bin/python tests/benchmarks/bench_hashgrid.py [--points 32768] [--repeats 10]

Grid of the `cpu` training preset (12 levels, 2^17 rows, 16..1024 cells), box [-1, 1]^3, random points
with requires_grad; one step = forward_with_jacobian + backward of features.sum() + jacobian.square().sum().
Both paths are timed round-robin in one process (median of the repeats after a warm-up). Not a test:
numbers are measured, never asserted.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from igavatar import kernels  # noqa: E402
from igavatar.model.hashgrid import HashGridConfig, HashGridEncoding  # noqa: E402

CONFIG = HashGridConfig(n_levels=12, log2_hashmap_size=17, base_resolution=16, finest_resolution=1024)


def step(grid: HashGridEncoding, x: torch.Tensor, path: str) -> tuple[float, float]:
    """(forward seconds, backward seconds) of one step on ``path`` ("reference" or "kernel")."""
    grid.table.grad = None
    x.grad = None
    kernels.set_kernels_enabled(path == "kernel")
    try:
        start = time.perf_counter()
        features, jacobian = grid.forward_with_jacobian(x)
        middle = time.perf_counter()
        (features.sum() + jacobian.square().sum()).backward()
        end = time.perf_counter()
    finally:
        kernels.set_kernels_enabled(None)
    return middle - start, end - middle


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=32768)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    kernels.set_kernels_enabled(True)
    kernels.load_kernel("hashgrid")  # build/load outside the timings
    kernels.set_kernels_enabled(None)
    status = kernels.kernel_status().get("hashgrid")
    paths = ["reference"] + (["kernel"] if status == "loaded" else [])

    grid = HashGridEncoding(CONFIG, -torch.ones(3), torch.ones(3))
    with torch.no_grad():
        grid.table.uniform_(-1e-2, 1e-2)
    x = (torch.rand(args.points, 3) * 2 - 1).requires_grad_(True)

    # Agreement of the two paths on this input (gradients wrt table and x).
    results = {}
    for path in paths:
        step(grid, x, path)
        results[path] = (grid.table.grad.clone(), x.grad.clone())

    times: dict[str, list[tuple[float, float]]] = {path: [] for path in paths}
    for i in range(args.warmup + args.repeats):
        for path in paths:
            t = step(grid, x, path)
            if i >= args.warmup:
                times[path].append(t)

    print(f"hash grid {CONFIG.n_levels} levels, T=2^{CONFIG.log2_hashmap_size}, "
          f"N={CONFIG.base_resolution}..{CONFIG.finest_resolution}, P={args.points}, threads={args.threads}, "
          f"median of {args.repeats} (kernel: {status})")
    print(f"{'path':<10} {'forward ms':>11} {'backward ms':>12} {'total ms':>9} {'speed-up':>9}")
    base = None
    for path in paths:
        fwd = statistics.median(t[0] for t in times[path]) * 1e3
        bwd = statistics.median(t[1] for t in times[path]) * 1e3
        total = statistics.median(t[0] + t[1] for t in times[path]) * 1e3
        base = base or total
        print(f"{path:<10} {fwd:>11.1f} {bwd:>12.1f} {total:>9.1f} {base / total:>8.2f}x")
    if "kernel" in results:
        (table_ref, x_ref), (table_ker, x_ker) = results["reference"], results["kernel"]
        print(f"max |grad diff| / max |grad|: table {float((table_ker - table_ref).abs().max() / table_ref.abs().max()):.1e}, "
              f"x {float((x_ker - x_ref).abs().max() / x_ref.abs().max()):.1e}")


if __name__ == "__main__":
    main()
